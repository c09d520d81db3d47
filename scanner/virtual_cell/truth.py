"""Ground truth of a simulated cell: ``truth.json`` plus ``*_stripes.npz``.

Written by :func:`scanner.virtual_cell.simulate.simulate_cell` beside the three sessions::

    OUT/truth.json               camera, light plane, laser origin, hand-eye, target placement,
                                 objects, and per session per frame id the true and reported poses
    OUT/<session>_stripes.npz    exact stripe centre points of every laser image (u, v, surface)
    OUT/calibration_true.json    the true sensor as a ``scan-calibration/1`` file

Read it back with :func:`read_truth`. Transforms are ``a_from_b`` 4x4 arrays, lengths mm.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from scanner.core.camera import CameraModel
from scanner.core.fileio import InputError
from scanner.core.targets import TargetSpec, parse_target, target_to_json
from scanner.formats.calibration_file import Calibration, LightPlane

__all__ = [
    "FORMAT",
    "CellTruth",
    "FrameTruth",
    "ObjectTruth",
    "SessionTruth",
    "StripeTable",
    "read_truth",
]

FORMAT = "virtual-cell-truth/1"


def _mat(value: Any) -> NDArray | None:
    return None if value is None else np.asarray(value, dtype=np.float64)


@dataclass(frozen=True)
class FrameTruth:
    """One row of a simulated session.

    ``stage`` says why the row exists: ``hand_held`` (intrinsics, no pose), ``light_plane``
    (diameter A-O-B in the light plane, no pose), ``posed``, ``aim`` (the robot put the stripe
    through ``aim`` = O, A or C), ``check`` (stripe through O) or ``sweep``.
    """

    id: int
    stage: str
    aim: str = ""
    base_from_flange_reported: NDArray | None = None
    base_from_flange_true: NDArray | None = None
    base_from_cam_true: NDArray | None = None
    cam_from_target_true: NDArray | None = None

    def to_json(self) -> dict[str, Any]:
        def m(a: NDArray | None) -> list | None:
            return None if a is None else np.asarray(a).tolist()

        return {
            "id": self.id,
            "stage": self.stage,
            "aim": self.aim,
            "base_from_flange_reported": m(self.base_from_flange_reported),
            "base_from_flange_true": m(self.base_from_flange_true),
            "base_from_cam_true": m(self.base_from_cam_true),
            "cam_from_target_true": m(self.cam_from_target_true),
        }

    @classmethod
    def from_json(cls, obj: dict[str, Any]) -> FrameTruth:
        return cls(
            id=int(obj["id"]),
            stage=str(obj["stage"]),
            aim=str(obj.get("aim", "")),
            base_from_flange_reported=_mat(obj.get("base_from_flange_reported")),
            base_from_flange_true=_mat(obj.get("base_from_flange_true")),
            base_from_cam_true=_mat(obj.get("base_from_cam_true")),
            cam_from_target_true=_mat(obj.get("cam_from_target_true")),
        )


@dataclass(frozen=True)
class StripeTable:
    """Exact stripe centres of the laser images of one session.

    Attributes
    ----------
    frame_id : ndarray, shape (M,)
    uv : ndarray, shape (M, 2)
        Distorted pixel coordinates of the true stripe centre.
    surface : ndarray, shape (M,)
        Index into ``surface_ids``.
    points : ndarray, shape (M, 3)
        The curve points in the frame's world frame (base for posed rows, camera otherwise), mm.
    surface_ids : tuple of str
    """

    frame_id: NDArray
    uv: NDArray
    surface: NDArray
    points: NDArray
    surface_ids: tuple[str, ...]

    def of_frame(self, frame_id: int) -> tuple[NDArray, NDArray]:
        """``(uv (K, 2), surface id strings (K,))`` of one frame."""
        sel = self.frame_id == frame_id
        ids = np.asarray(self.surface_ids, dtype=object)[self.surface[sel]]
        return self.uv[sel], ids

    def save(self, path: str | os.PathLike[str]) -> None:
        np.savez_compressed(
            path,
            frame_id=self.frame_id.astype(np.int32),
            uv=self.uv.astype(np.float64),
            surface=self.surface.astype(np.int16),
            points=self.points.astype(np.float32),
            surface_ids=np.asarray(self.surface_ids, dtype=str),
        )

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> StripeTable:
        with np.load(path) as z:
            return cls(
                z["frame_id"],
                z["uv"],
                z["surface"].astype(np.int32),
                z["points"].astype(np.float64),
                tuple(str(s) for s in z["surface_ids"]),
            )


@dataclass
class SessionTruth:
    """Truth of one session: its frames and (lazily) its stripe table."""

    kind: str
    frames: list[FrameTruth]
    stripes_path: Path | None = None
    _stripes: StripeTable | None = field(default=None, repr=False)

    def frame(self, frame_id: int) -> FrameTruth:
        for f in self.frames:
            if f.id == frame_id:
                return f
        raise KeyError(f"frame id {frame_id} not in the {self.kind} truth")

    @property
    def stripes(self) -> StripeTable | None:
        if self._stripes is None and self.stripes_path is not None and self.stripes_path.is_file():
            self._stripes = StripeTable.load(self.stripes_path)
        return self._stripes


@dataclass(frozen=True)
class ObjectTruth:
    """One scene object, exact, base frame, mm: ``type`` and its parameters.

    sphere: ``center_mm``, ``diameter_mm``; cylinder: ``p0_mm``, ``p1_mm``, ``diameter_mm``;
    box: ``base_from_box`` (4x4), ``size_mm``; plane: ``normal``, ``d`` (``normal . p + d = 0``).
    """

    id: str
    type: str
    params: dict[str, Any]


@dataclass
class CellTruth:
    """Everything that is true about a simulated cell."""

    cell: str
    seed: int
    camera: CameraModel
    light_plane: LightPlane
    laser_origin_cam: NDArray
    flange_from_cam: NDArray
    base_from_target: NDArray
    target: TargetSpec
    objects: list[ObjectTruth]
    sessions: dict[str, SessionTruth]
    extra: dict[str, Any] = field(default_factory=dict)

    def calibration(self) -> Calibration:
        """The true sensor as a calibration (what a perfect ``scanner calibrate`` returns)."""
        return Calibration(
            width=self.camera.width,
            height=self.camera.height,
            K=self.camera.K,
            dist=self.camera.dist,
            light_plane=self.light_plane,
            flange_from_cam=self.flange_from_cam,
            quality={"method": "virtual cell truth"},
        )

    def object(self, object_id: str) -> ObjectTruth:
        for o in self.objects:
            if o.id == object_id:
                return o
        raise KeyError(f"object {object_id!r} not in the truth ({[o.id for o in self.objects]})")


def along_line_errors(
    uv_px: NDArray, orientation: str, uv_true_px: NDArray
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Each extracted stripe point's error along its scan line against the true centre curve.

    Parameters
    ----------
    uv_px : ndarray, shape (N, 2)
        Extracted centres (``StripeProfile.uv``).
    orientation : {"rows", "cols"}
        The profile's scan lines (the error is along ``u`` for rows, ``v`` for columns).
    uv_true_px : ndarray, shape (M, 2), M >= 2
        The true curve's samples (:attr:`StripeTable.of_frame`, ``StripeTruth.uv``).

    Returns
    -------
    err_px : ndarray, shape (N,)
        Along-line error: the point minus the true curve at the point's across coordinate,
        interpolated between its two nearest samples.
    dist_px : ndarray, shape (N,)
        Distance to the nearest sample.
    nearest : ndarray, shape (N,), int
        Index of the nearest sample (its surface in the truth's tables).
    ok : ndarray, shape (N,), bool
        Where the two samples differ across the line (the interpolation is defined).
    """
    dist, k = cKDTree(uv_true_px).query(uv_px, k=2)
    p1, p2 = uv_true_px[k[:, 0]], uv_true_px[k[:, 1]]
    a = 1 if orientation == "cols" else 0  # the coordinate along the scan line
    b = 1 - a
    step = p2[:, b] - p1[:, b]
    ok = np.abs(step) > 1e-6
    along = p1[:, a] + (uv_px[:, b] - p1[:, b]) * (p2[:, a] - p1[:, a]) / np.where(ok, step, 1.0)
    return uv_px[:, a] - along, dist[:, 0], k[:, 0], ok


def truth_to_json(truth: CellTruth) -> dict[str, Any]:

    return {
        "format": FORMAT,
        "cell": truth.cell,
        "seed": truth.seed,
        "units": "mm",
        "camera": {
            "width": truth.camera.width,
            "height": truth.camera.height,
            "K": truth.camera.K.tolist(),
            "dist": truth.camera.dist.tolist(),
        },
        "light_plane": {"normal": truth.light_plane.normal.tolist(), "d": truth.light_plane.d},
        "laser_origin_cam_mm": np.asarray(truth.laser_origin_cam).tolist(),
        "flange_from_cam": np.asarray(truth.flange_from_cam).tolist(),
        "base_from_target": np.asarray(truth.base_from_target).tolist(),
        "target": target_to_json(truth.target),
        "objects": [{"id": o.id, "type": o.type, **o.params} for o in truth.objects],
        "sessions": {
            name: {
                "kind": s.kind,
                "stripes": None if s.stripes_path is None else s.stripes_path.name,
                "frames": [f.to_json() for f in s.frames],
            }
            for name, s in truth.sessions.items()
        },
        **truth.extra,
    }


def read_truth(path: str | os.PathLike[str]) -> CellTruth:
    """Read ``truth.json`` (a file, or the simulation folder that holds it).

    Raises
    ------
    InputError
        Missing file, invalid JSON, wrong format or missing keys.
    """
    p = Path(path)
    if p.is_dir():
        p = p / "truth.json"
    if not p.is_file():
        raise InputError(p, "truth file not found")
    try:
        obj = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(p, f"cannot read: {exc}") from None
    if not isinstance(obj, dict) or obj.get("format") != FORMAT:
        got = obj.get("format") if isinstance(obj, dict) else type(obj).__name__
        raise InputError(p, f"format: expected {FORMAT!r}, got {got!r}")
    known = {
        "format", "cell", "seed", "units", "camera", "light_plane", "laser_origin_cam_mm",
        "flange_from_cam", "base_from_target", "target", "objects", "sessions",
    }  # fmt: skip
    try:
        cam = obj["camera"]
        objects = []
        for o in obj["objects"]:
            params = {k: v for k, v in o.items() if k not in ("id", "type")}
            objects.append(ObjectTruth(str(o["id"]), str(o["type"]), params))
        sessions = {}
        for name, s in obj["sessions"].items():
            stripes = s.get("stripes")
            sessions[name] = SessionTruth(
                kind=str(s["kind"]),
                frames=[FrameTruth.from_json(f) for f in s["frames"]],
                stripes_path=None if not stripes else p.parent / stripes,
            )
        return CellTruth(
            cell=str(obj["cell"]),
            seed=int(obj["seed"]),
            camera=CameraModel(
                int(cam["width"]), int(cam["height"]), np.asarray(cam["K"]), np.asarray(cam["dist"])
            ),
            light_plane=LightPlane(
                np.asarray(obj["light_plane"]["normal"]), float(obj["light_plane"]["d"])
            ),
            laser_origin_cam=np.asarray(obj["laser_origin_cam_mm"], dtype=np.float64),
            flange_from_cam=np.asarray(obj["flange_from_cam"], dtype=np.float64),
            base_from_target=np.asarray(obj["base_from_target"], dtype=np.float64),
            target=parse_target(obj["target"]),
            objects=objects,
            sessions=sessions,
            extra={k: v for k, v in obj.items() if k not in known},
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(p, f"bad truth file: {type(exc).__name__}: {exc}") from None
