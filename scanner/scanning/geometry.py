"""Where each point of a cloud came from: the robot stop that saw it, and how it moves when the
calibration or that stop's pose is off by a little.

A cloud written by :func:`scanner.scanning.pipeline.scan_session` carries each point's
``frame_id`` and ``sweep_id``; with the sweep sessions (their ``frames.csv`` poses) and the
calibration that made it, :class:`ScanGeometry` recovers each point's stop, its pixel on the
stripe, and so the point any other calibration would have triangulated from it. The
uncertainty of a measurement (:mod:`metrology.uncertainty`) is built on this.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from scanner.core.fileio import InputError
from scanner.formats.calibration_file import Calibration, read_calibration
from scanner.formats.clouds import cloud_arrays, read_cloud, read_ply_metadata
from scanner.formats.session import Session, read_session
from scanner.scanning.triangulate import Triangulator, camera_from_calibration

__all__ = ["MAX_PLANE_OFFSET_MM", "ScanGeometry", "scan_geometry_of", "sweep_numbering"]

#: A cloud whose points lie farther (median) from their stops' light plane was not made by
#: this geometry (ICP between sweeps moves points by hundredths of a millimetre).
MAX_PLANE_OFFSET_MM = 0.05


def sweep_numbering(sessions: Sequence[Session]) -> tuple[NDArray, dict[tuple[int, int], int]]:
    """The scan's numbering of its stops: ``(base_from_flange (F, 4, 4), index)`` where
    ``index[(sweep_id, frame_id)]`` is the stop's row; sweeps are (session, sweep column) pairs
    numbered in order, as :func:`~scanner.scanning.pipeline.scan_session` numbers them."""
    poses: list[NDArray] = []
    index: dict[tuple[int, int], int] = {}
    sweep_ids: dict[tuple[int, int], int] = {}
    for si, s in enumerate(sessions):
        for f in s.frames:
            sweep = sweep_ids.setdefault((si, f.sweep), len(sweep_ids))
            index[(sweep, f.id)] = len(poses)
            poses.append(np.asarray(f.base_from_flange, dtype=np.float64))
    return np.stack(poses) if poses else np.zeros((0, 4, 4)), index


@dataclass(frozen=True)
class ScanGeometry:
    """The stop of every cloud point and the calibration that triangulated it.

    Attributes
    ----------
    calibration : Calibration
    base_from_flange : ndarray, shape (F, 4, 4)
        The robot's stops.
    frame_index : ndarray, shape (N,), int
        Each point's stop (row of ``base_from_flange``).
    """

    calibration: Calibration
    base_from_flange: NDArray
    frame_index: NDArray

    @classmethod
    def from_sessions(
        cls,
        calibration: Calibration,
        sessions: Sequence[Session],
        sweep_id: NDArray,
        frame_id: NDArray,
    ) -> ScanGeometry:
        """From the sweep sessions and the cloud's ``sweep_id`` and ``frame_id`` columns.

        Raises
        ------
        ValueError
            A point whose (sweep, frame) the sessions do not hold.
        """
        poses, index = sweep_numbering(sessions)
        sweep_id = np.asarray(sweep_id, dtype=np.int64).reshape(-1)
        frame_id = np.asarray(frame_id, dtype=np.int64).reshape(-1)
        keys = (sweep_id << 32) + (frame_id & 0xFFFFFFFF)
        uniq, inverse = np.unique(keys, return_inverse=True)
        rows = []
        for key in uniq.tolist():
            s, f = key >> 32, int(np.int64(key & 0xFFFFFFFF).astype(np.int32))
            if (s, f) not in index:
                raise ValueError(
                    f"cloud: expected its stops in the sessions, got sweep {s} frame {f} not there"
                )
            rows.append(index[(s, f)])
        return cls(calibration, poses, np.asarray(rows, dtype=np.int64)[inverse.reshape(-1)])

    def points_cam(self, points_base: NDArray, which: NDArray) -> NDArray:
        """``(M, 3)`` the points ``points_base[which]`` in the camera frame of their own stops."""
        base_from_cam = self.base_from_flange[self.frame_index[which]] @ (
            self.calibration.flange_from_cam
        )
        cam_from_base = np.linalg.inv(base_from_cam)
        p = np.einsum("nij,nj->ni", cam_from_base[:, :3, :3], points_base[which])
        return p + cam_from_base[:, :3, 3]

    def pixels(self, points_base: NDArray, which: NDArray) -> NDArray:
        """``(M, 2)`` stripe pixels the points ``points_base[which]`` were triangulated from."""
        return camera_from_calibration(self.calibration).project(
            self.points_cam(points_base, which)
        )

    def plane_distances(self, points_base: NDArray, which: NDArray) -> NDArray:
        """``(M,)`` distances (mm) of ``points_base[which]`` from the light plane of their own
        stops: near zero for a cloud this geometry made, large for one it did not (another
        calibration, stops mixed by a voxel filter)."""
        plane = self.calibration.require_light_plane("calibration", "scan geometry")
        return np.abs(self.points_cam(points_base, which) @ plane.normal + plane.d)

    def retriangulated(self, calibration: Calibration, pixels: NDArray, which: NDArray) -> NDArray:
        """``(M, 3)`` base-frame points that ``calibration`` gives for the same pixels."""
        tri = Triangulator(calibration, grid_step_px=0)
        return tri.points_base(pixels, self.frame_index[which], self.base_from_flange)

    def calibration_moves(self, points_base: NDArray, which: NDArray) -> tuple[NDArray, NDArray]:
        """How the calibration's uncertainty moves the points ``points_base[which]``.

        Returns
        -------
        points : ndarray, shape (M, 3)
            The points re-triangulated from their pixels with the calibration as it is.
        moves : ndarray, shape (D, M, 3)
            Their change under each of the ``D`` one-sigma principal directions of the
            calibration's covariance (``D = 0`` without a covariance, or for a zero one).
        """
        cal, cov = self.calibration, self.calibration.covariance
        pixels = self.pixels(points_base, which)
        as_is = cal if cov is None else cal.corrected(np.zeros(cov.matrix.shape[0]))
        points = self.retriangulated(as_is, pixels, which)
        dirs = np.zeros((0, 0)) if cov is None else cov.principal_directions()
        moves = np.zeros((len(dirs), len(points), 3))
        for k, direction in enumerate(dirs):
            moves[k] = self.retriangulated(cal.corrected(direction), pixels, which) - points
        return points, moves

    def pose_moved(
        self,
        points_base: NDArray,
        which: NDArray,
        rotvec_flange: NDArray,
        translation_flange_mm: NDArray,
    ) -> NDArray:
        """``(M, 3)`` points as seen from stops each missed by a small motion of the flange.

        ``rotvec_flange`` and ``translation_flange_mm`` are ``(F, 3)``, one miss per stop, in
        the flange frame: ``base_from_flange -> base_from_flange @ [R(r), t]``.
        """
        misses = np.tile(np.eye(4), (len(self.base_from_flange), 1, 1))
        misses[:, :3, :3] = Rotation.from_rotvec(rotvec_flange).as_matrix()
        misses[:, :3, 3] = translation_flange_mm
        b = self.base_from_flange
        moved = b @ misses @ np.linalg.inv(b)
        t = moved[self.frame_index[which]]
        return np.einsum("nij,nj->ni", t[:, :3, :3], points_base[which]) + t[:, :3, 3]


def scan_geometry_of(
    cloud_path: str | os.PathLike[str],
    calibration_path: str | os.PathLike[str] | None = None,
) -> tuple[ScanGeometry | None, str]:
    """The geometry of a cloud this scanner wrote: ``(geometry, "")``, or ``(None, reason)``.

    The cloud's provenance names its sweep sessions and calibration file; ``calibration_path``
    overrides the latter. A cloud from elsewhere, moved sessions, or a cloud without its
    ``frame_id`` and ``sweep_id`` columns give the reason instead.
    """
    path = Path(cloud_path)
    if path.suffix.lower() != ".ply":
        return None, f"the stops of a {path.suffix or 'suffix-less'} cloud are not recorded"
    try:
        meta = read_ply_metadata(path)
        cal_path = calibration_path or meta.get("calibration")
        sessions = meta.get("sessions") or []
        if not cal_path:
            return None, "the cloud names no calibration file (give --calibration)"
        if not sessions or not all(Path(s).is_dir() for s in sessions):
            return None, f"the cloud's sweep sessions are not found ({', '.join(sessions)})"
        arrays = cloud_arrays(read_cloud(path))
        if "frame_id" not in arrays or "sweep_id" not in arrays:
            return None, "the cloud has no frame_id and sweep_id columns"
        geometry = ScanGeometry.from_sessions(
            read_calibration(cal_path),
            [read_session(s, check_images=False) for s in sessions],
            arrays["sweep_id"].reshape(-1),
            arrays["frame_id"].reshape(-1),
        )
    except (InputError, ValueError) as exc:
        return None, str(exc)
    if geometry.calibration.light_plane is None:
        return None, "the calibration has no light plane"
    points = arrays["positions"].reshape(-1, 3).astype(np.float64)
    sample = np.random.default_rng(0).choice(len(points), min(len(points), 2000), replace=False)
    off = geometry.plane_distances(points, sample)
    if float(np.median(off)) > MAX_PLANE_OFFSET_MM:
        return None, (
            f"the cloud's points lie {float(np.median(off)):.3f} mm (median) off the light plane "
            "of their stops: another calibration made it, or a filter mixed its stops"
        )
    return geometry, ""
