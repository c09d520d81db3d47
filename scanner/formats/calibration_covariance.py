"""The calibration's uncertainty as the calibration file carries it (optional key ``covariance``).

A calibration estimates a camera (``K``, ``dist``), a light plane and ``flange_from_cam``. Their
joint uncertainty is a covariance over small *corrections* ``delta`` to the values in the file,
in this order (:data:`PARAMETERS`)::

    fx, fy, cx, cy            px, added to K
    k1, k2, p1, p2, k3        added to dist (OpenCV's order)
    plane_a, plane_b          rad: the normal tilts to normalise(n + a e1 + b e2), where
                              e1 = normalise(n x z_cam) (or n x x_cam when n is along z) and
                              e2 = n x e1
    plane_d                   mm, added to d
    cam_rx, cam_ry, cam_rz    rad: flange_from_cam @ [Rotation.from_rotvec(r), 0]
    cam_tx, cam_ty, cam_tz    mm:  flange_from_cam @ [I, t] (both in the camera frame)

and the robot's repeatability, one sigma per axis of the flange's rotation (deg) and
translation (mm), for the stops of a scan; where the calibration estimated the laser origin
(``laser_origin_cam``), that point's own covariance (mm², camera frame; rank 2, within the
light plane). In the file::

    "covariance": {"parameters": ["fx", ...], "matrix": [[...], ...],
                   "robot": {"rotation_deg": 0.002, "translation_mm": 0.01},
                   "laser_origin_mm2": [[...3 x 3...]],      # optional
                   "method": "..."}

The laser origin moves no point of a scan: it decides only which points the incidence limit
flags, so it has no share in a measured value's uncertainty.

A parameter the calibration held fixed has zero variance. :func:`apply_correction` gives the
calibration a correction describes, so that a reader can carry the uncertainty into whatever
it measures (by Monte Carlo over draws, or linearised over :meth:`principal_directions`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

__all__ = [
    "PARAMETERS",
    "CalibrationCovariance",
    "apply_correction",
    "camera_correction",
    "plane_correction",
    "plane_tilt_axes",
]

PARAMETERS = (
    "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3",
    "plane_a", "plane_b", "plane_d",
    "cam_rx", "cam_ry", "cam_rz", "cam_tx", "cam_ty", "cam_tz",
)  # fmt: skip


def plane_tilt_axes(normal: ArrayLike) -> tuple[NDArray, NDArray]:
    """The two unit axes ``(e1, e2)`` normal to ``normal`` that ``plane_a, plane_b`` tilt along."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    ref = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(n, ref)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def apply_correction(
    K: NDArray,
    dist: NDArray,
    plane: tuple[NDArray, float] | None,
    flange_from_cam: NDArray,
    delta: ArrayLike,
) -> tuple[NDArray, NDArray, tuple[NDArray, float] | None, NDArray]:
    """``(K, dist, (normal, d), flange_from_cam)`` corrected by ``delta``, shape ``(18,)``.

    ``plane`` is ``None`` for a camera-only calibration (its three entries are then ignored).
    Distortion vectors with fewer than five terms take only the ones they have.
    """
    delta = np.asarray(delta, dtype=np.float64).reshape(-1)
    if delta.shape != (len(PARAMETERS),):
        raise ValueError(f"delta: expected shape ({len(PARAMETERS)},), got {delta.shape}")
    K2 = np.array(K, dtype=np.float64)
    K2[0, 0] += delta[0]
    K2[1, 1] += delta[1]
    K2[0, 2] += delta[2]
    K2[1, 2] += delta[3]
    d2 = np.array(dist, dtype=np.float64).reshape(-1)
    n_terms = min(5, d2.size)
    d2[:n_terms] += delta[4 : 4 + n_terms]
    plane2 = None
    if plane is not None:
        normal, d = plane
        e1, e2 = plane_tilt_axes(normal)
        n2 = np.asarray(normal, dtype=np.float64) + delta[9] * e1 + delta[10] * e2
        norm = float(np.linalg.norm(n2))
        plane2 = (n2 / norm, (float(d) + delta[11]) / norm)
    correction = np.eye(4)
    correction[:3, :3] = Rotation.from_rotvec(delta[12:15]).as_matrix()
    correction[:3, 3] = delta[15:18]
    return K2, d2, plane2, np.asarray(flange_from_cam, dtype=np.float64) @ correction


def plane_correction(normal: ArrayLike, d: float, ref_normal: ArrayLike, ref_d: float) -> NDArray:
    """``(plane_a, plane_b, plane_d)`` taking the reference plane to ``(normal, d)`` (the
    inverse of :func:`apply_correction` for the plane; either orientation of a plane)."""
    n, ref = np.asarray(normal, dtype=np.float64), np.asarray(ref_normal, dtype=np.float64)
    if float(n @ ref) < 0:
        n, d = -n, -d
    e1, e2 = plane_tilt_axes(ref)
    scale = float(n @ ref)
    return np.array([n @ e1 / scale, n @ e2 / scale, d / scale - ref_d])


def camera_correction(flange_from_cam: ArrayLike, ref_flange_from_cam: ArrayLike) -> NDArray:
    """``(cam_rx, ..., cam_tz)`` with ``flange_from_cam = ref @ [R(r), t]`` (the inverse of
    :func:`apply_correction` for the hand-eye)."""
    c = np.linalg.inv(np.asarray(ref_flange_from_cam, dtype=np.float64)) @ np.asarray(
        flange_from_cam, dtype=np.float64
    )
    return np.concatenate([Rotation.from_matrix(c[:3, :3]).as_rotvec(), c[:3, 3]])


def _checked_covariance(matrix: Any, shape: tuple[int, int], name: str) -> NDArray:
    """``matrix`` as a finite, symmetric (symmetrised), positive semi-definite float64 matrix
    of ``shape``; ValueError naming ``covariance.<name>`` otherwise."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != shape or not np.all(np.isfinite(m)):
        raise ValueError(
            f"covariance.{name}: expected a finite {shape[0]}x{shape[1]} matrix, got {m.shape}"
        )
    m = 0.5 * (m + m.T)
    if np.linalg.eigvalsh(m).min() < -1e-9 * max(1e-30, float(np.abs(m).max())):
        raise ValueError(f"covariance.{name}: expected a positive semi-definite matrix")
    return m


@dataclass(frozen=True)
class CalibrationCovariance:
    """Covariance of a calibration's corrections, and the robot's repeatability.

    Attributes
    ----------
    matrix : ndarray, shape (18, 18)
        Over :data:`PARAMETERS`, in their units (px, rad, mm).
    robot_rotation_deg, robot_translation_mm : float
        The robot's repeatability at a stop: one sigma per axis.
    method : str
        How the covariance was estimated, in words.
    laser_origin_mm2 : ndarray, shape (3, 3), or None
        The estimated laser origin's covariance, camera frame, mm²; ``None`` where the file
        has no estimated origin (none, or one given from the sensor's drawing).
    """

    matrix: NDArray
    robot_rotation_deg: float = 0.0
    robot_translation_mm: float = 0.0
    method: str = ""
    laser_origin_mm2: NDArray | None = None

    def __post_init__(self) -> None:
        p = len(PARAMETERS)
        object.__setattr__(self, "matrix", _checked_covariance(self.matrix, (p, p), "matrix"))
        for name in ("robot_rotation_deg", "robot_translation_mm"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"covariance.robot.{name}: expected a finite value >= 0, got {v}")
            object.__setattr__(self, name, v)
        if self.laser_origin_mm2 is not None:
            o = _checked_covariance(self.laser_origin_mm2, (3, 3), "laser_origin_mm2")
            object.__setattr__(self, "laser_origin_mm2", o)

    @property
    def std(self) -> dict[str, float]:
        """One sigma of each parameter, by name."""
        return dict(zip(PARAMETERS, np.sqrt(np.clip(np.diag(self.matrix), 0, None)).tolist()))

    def principal_directions(self, rel_tol: float = 1e-12) -> NDArray:
        """``(M, 18)`` one-sigma corrections along the covariance's eigenvectors.

        A linear function ``g`` of the corrections has variance ``sum((g @ s) ** 2)`` over
        these rows ``s``. Each direction's units are mixed, so the eigen-decomposition is taken
        of the correlation-scaled matrix (scale-free), then mapped back.
        """
        sd = np.sqrt(np.clip(np.diag(self.matrix), 0, None))
        live = sd > 0
        if not np.any(live):
            return np.zeros((0, len(PARAMETERS)))
        corr = self.matrix[np.ix_(live, live)] / np.outer(sd[live], sd[live])
        w, v = np.linalg.eigh(corr)
        keep = w > rel_tol * w.max()
        rows = np.zeros((int(keep.sum()), len(PARAMETERS)))
        rows[:, live] = (v[:, keep] * np.sqrt(w[keep])).T * sd[live]
        return rows

    def draws(self, n: int, rng: np.random.Generator) -> NDArray:
        """``(n, 18)`` corrections drawn from the normal distribution of this covariance."""
        dirs = self.principal_directions()
        return rng.standard_normal((n, len(dirs))) @ dirs

    def to_json(self) -> dict[str, Any]:
        origin = self.laser_origin_mm2
        return {
            "parameters": list(PARAMETERS),
            "matrix": self.matrix.tolist(),
            "robot": {
                "rotation_deg": self.robot_rotation_deg,
                "translation_mm": self.robot_translation_mm,
            },
            **({} if origin is None else {"laser_origin_mm2": origin.tolist()}),
            "method": self.method,
        }

    @classmethod
    def from_json(cls, record: Any) -> CalibrationCovariance:
        """Read the file's ``covariance`` object; ``ValueError`` saying what is wrong."""
        if not isinstance(record, Mapping):
            raise ValueError(f"covariance: expected an object, got {type(record).__name__}")
        names = record.get("parameters")
        if list(names or []) != list(PARAMETERS):
            raise ValueError(f"covariance.parameters: expected {list(PARAMETERS)}, got {names!r}")
        robot = record.get("robot") or {}
        if not isinstance(robot, Mapping):
            raise ValueError("covariance.robot: expected an object")
        return cls(
            matrix=np.asarray(record.get("matrix"), dtype=np.float64),
            robot_rotation_deg=float(robot.get("rotation_deg", 0.0)),
            robot_translation_mm=float(robot.get("translation_mm", 0.0)),
            method=str(record.get("method", "")),
            laser_origin_mm2=(
                None
                if record.get("laser_origin_mm2") is None
                else np.asarray(record["laser_origin_mm2"], dtype=np.float64)
            ),
        )
