"""Reader and writer of the calibration file (``scan-calibration/1``).

The format is a public contract (``shared/spec/interfaces.md``, section 2)::

    {"format": "scan-calibration/1",
     "camera": {"width", "height", "K": 3x3, "dist": [k1, k2, p1, p2, k3]},
     "light_plane": {"normal": [nx, ny, nz], "d": d},     # camera frame, normal . p + d = 0
                                                          # (null: camera-only calibration)
     "laser_origin_cam": [x, y, z],                       # optional: apex of the laser fan
     "covariance": {...},                                 # optional: see calibration_covariance
     "flange_from_cam": 4x4,
     "quality": {...free-form...}}

The quality record is free-form in the file (other tools write their own); in memory it is a
:class:`CalibrationQuality`: the figures every reader needs as typed fields (``None`` where a
file does not give them) and the whole record as written, for the reports.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scanner.core.conventions import check_transform
from scanner.core.fileio import InputError, json_int, read_json_object, write_json_atomic
from scanner.formats.calibration_covariance import CalibrationCovariance, apply_correction

__all__ = [
    "FORMAT",
    "Calibration",
    "CalibrationCovariance",
    "CalibrationQuality",
    "LightPlane",
    "read_calibration",
    "write_calibration",
]

FORMAT = "scan-calibration/1"

log = logging.getLogger(__name__)

# Physical bounds: a value beyond them is a typing, unit or file error, not a camera.
#: Focal length, px (a 100 Mpx sensor behind a long telephoto stays far below).
MAX_FOCAL_PX = 1.0e6
#: Image side, px.
MAX_IMAGE_PX = 100_000
#: Any distortion coefficient of OpenCV's models.
MAX_DISTORTION = 1.0e4
#: Camera from flange, light plane from camera, mm.
MAX_OFFSET_MM = 1.0e4
#: The light plane from the camera centre, mm.
MIN_PLANE_DISTANCE_MM = 1.0


@dataclass(frozen=True)
class LightPlane:
    """Laser light plane in the camera frame: ``normal . p_cam + d = 0``, ``|normal| = 1``."""

    normal: NDArray
    d: float

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64).reshape(-1)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or not np.isfinite(self.d):
            raise ValueError(
                f"light_plane: expected a finite 3-vector normal and d, got {self.normal}, {self.d}"
            )
        norm = float(np.linalg.norm(n))
        if norm < 1e-12:
            raise ValueError("light_plane.normal: expected a non-zero vector")
        object.__setattr__(self, "normal", n / norm)
        object.__setattr__(self, "d", float(self.d) / norm)
        if not MIN_PLANE_DISTANCE_MM <= abs(self.d) <= MAX_OFFSET_MM:
            raise ValueError(
                f"light_plane.d: expected the plane {MIN_PLANE_DISTANCE_MM:g} to {MAX_OFFSET_MM:g} "
                f"mm from the camera centre (a plane through it images as a line), got {self.d:g}"
            )

    @classmethod
    def from_coefficients(cls, a: float, b: float, c: float, d: float) -> LightPlane:
        """From ``a x + b y + c z + d = 0`` (any scale), e.g. the paper's plane."""
        return cls(np.array([a, b, c], dtype=np.float64), d)

    def signed_distance(self, points_cam: NDArray) -> NDArray:
        return np.asarray(points_cam, dtype=np.float64) @ self.normal + self.d


def _number(record: Mapping[str, Any], section: str | None, key: str) -> float | None:
    part: Any = record if section is None else record.get(section)
    value = part.get(key) if isinstance(part, Mapping) else None
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if np.isfinite(value) else None


def _text(record: Mapping[str, Any], section: str | None, key: str) -> str | None:
    part: Any = record if section is None else record.get(section)
    value = part.get(key) if isinstance(part, Mapping) else None
    return value if isinstance(value, str) else None


@dataclass(frozen=True)
class CalibrationQuality:
    """How good a calibration is: typed headline figures and the full record as written.

    Attributes
    ----------
    verdict : str or None
        ``"good"``, ``"usable"``, ``"poor"`` ... as the calibration judged itself.
    method : str or None
        ``"default"`` or ``"paper"``.
    intrinsics_rms_px, hand_eye_rms_px : float or None
        Reprojection RMS of the intrinsics and of the full chain (base to image), px.
    light_plane_rms_mm : float or None
        RMS distance of the stripe points to the light plane, mm.
    light_plane_frames : int or None
        Laser frames the light plane was fitted to.
    hand_eye_method : str or None
    warnings : tuple of str
    record : mapping
        The ``quality`` object of the file, unchanged (written back as read).
    """

    verdict: str | None = None
    method: str | None = None
    intrinsics_rms_px: float | None = None
    light_plane_rms_mm: float | None = None
    light_plane_frames: int | None = None
    hand_eye_method: str | None = None
    hand_eye_rms_px: float | None = None
    warnings: tuple[str, ...] = ()
    record: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_json(cls, record: Any) -> CalibrationQuality:
        """Read the typed figures from a file's free-form ``quality`` (missing ones: None)."""
        if not isinstance(record, Mapping):
            return cls()
        plane = record.get("light_plane")
        per_frame = plane.get("per_frame") if isinstance(plane, Mapping) else None
        warnings = record.get("warnings")
        return cls(
            verdict=_text(record, None, "verdict"),
            method=_text(record, None, "method"),
            intrinsics_rms_px=_number(record, "intrinsics", "rms_px"),
            light_plane_rms_mm=_number(record, "light_plane", "rms_mm"),
            light_plane_frames=len(per_frame) if isinstance(per_frame, list) else None,
            hand_eye_method=_text(record, "hand_eye", "method"),
            hand_eye_rms_px=_number(record, "hand_eye", "rms_px"),
            warnings=tuple(str(w) for w in warnings) if isinstance(warnings, list) else (),
            record=dict(record),
        )

    def to_json(self) -> dict[str, Any]:
        return dict(self.record)


@dataclass
class Calibration:
    """Camera intrinsics, distortion, light plane and hand-eye transform of one sensor."""

    width: int
    height: int
    K: NDArray
    dist: NDArray
    light_plane: LightPlane | None
    """``None`` for a camera + hand-eye calibration from a session without laser images."""
    flange_from_cam: NDArray
    quality: CalibrationQuality = field(default_factory=CalibrationQuality)
    laser_origin_cam: NDArray | None = None
    """The apex of the laser fan, camera frame, mm (optional)."""
    covariance: CalibrationCovariance | None = None
    """Uncertainty of the estimated values and the robot's repeatability (optional)."""

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64)
        if self.K.shape != (3, 3) or not np.all(np.isfinite(self.K)):
            raise ValueError(f"camera.K: expected a finite 3x3 matrix, got shape {self.K.shape}")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0 or not np.allclose(self.K[2], [0, 0, 1]):
            raise ValueError("camera.K: expected fx, fy > 0 and last row [0, 0, 1]")
        if not (abs(self.K[0, 2]) <= MAX_IMAGE_PX and abs(self.K[1, 2]) <= MAX_IMAGE_PX):
            raise ValueError(
                f"camera.K: expected the principal point within ±{MAX_IMAGE_PX} px, got "
                f"{self.K[0, 2]:g}, {self.K[1, 2]:g}"
            )
        if not (self.K[0, 0] <= MAX_FOCAL_PX and self.K[1, 1] <= MAX_FOCAL_PX):
            raise ValueError(
                f"camera.K: expected fx, fy <= {MAX_FOCAL_PX:g} px, got {self.K[0, 0]:g}, "
                f"{self.K[1, 1]:g}"
            )
        dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if dist.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
            raise ValueError(
                f"camera.dist: expected OpenCV's 4, 5, 8, 12 or 14 coefficients, got {dist.size}"
            )
        if np.any(np.abs(dist) > MAX_DISTORTION):
            raise ValueError(
                f"camera.dist: expected coefficients within ±{MAX_DISTORTION:g}, got {dist.tolist()}"
            )
        self.dist = dist
        if not isinstance(self.quality, CalibrationQuality):
            self.quality = CalibrationQuality.from_json(self.quality)
        self.flange_from_cam = check_transform(self.flange_from_cam, "flange_from_cam", tol=1e-5)
        if np.linalg.norm(self.flange_from_cam[:3, 3]) > MAX_OFFSET_MM:
            raise ValueError(
                f"flange_from_cam: expected the camera within {MAX_OFFSET_MM:g} mm of the flange, "
                f"got {np.linalg.norm(self.flange_from_cam[:3, 3]):g} mm"
            )
        if self.laser_origin_cam is not None:
            origin = np.asarray(self.laser_origin_cam, dtype=np.float64).reshape(-1)
            if origin.shape != (3,) or not np.all(np.abs(origin) <= MAX_OFFSET_MM):
                raise ValueError(
                    f"laser_origin_cam: expected [x, y, z] within {MAX_OFFSET_MM:g} mm of the "
                    f"camera, got {self.laser_origin_cam!r}"
                )
            self.laser_origin_cam = origin
        if not (0 < self.width <= MAX_IMAGE_PX and 0 < self.height <= MAX_IMAGE_PX):
            raise ValueError(
                f"camera: expected a positive image size, got {self.width}x{self.height}"
            )

    def require_light_plane(self, source: str | os.PathLike[str], what: str) -> LightPlane:
        """The light plane, or an :class:`InputError` naming ``source``: ``what`` needs one."""
        if self.light_plane is None:
            raise InputError(
                source, f"a camera-only calibration (light_plane: null): {what} needs a light plane"
            )
        return self.light_plane

    def corrected(self, delta: NDArray) -> Calibration:
        """This calibration with a correction ``delta`` over
        :data:`~scanner.formats.calibration_covariance.PARAMETERS` applied (a draw of its
        uncertainty); the covariance stays as it is."""
        plane = None if self.light_plane is None else (self.light_plane.normal, self.light_plane.d)
        K, dist, plane2, flange_from_cam = apply_correction(
            self.K, self.dist, plane, self.flange_from_cam, delta
        )
        return Calibration(
            width=self.width,
            height=self.height,
            K=K,
            dist=dist,
            light_plane=None if plane2 is None else LightPlane(*plane2),
            flange_from_cam=flange_from_cam,
            quality=self.quality,
            laser_origin_cam=self.laser_origin_cam,
            covariance=self.covariance,
        )

    def to_json(self) -> dict[str, Any]:
        extra: dict[str, Any] = (
            {}
            if self.laser_origin_cam is None
            else {"laser_origin_cam": self.laser_origin_cam.tolist()}
        )
        if self.covariance is not None:
            extra["covariance"] = self.covariance.to_json()
        return {
            "format": FORMAT,
            "camera": {
                "width": int(self.width),
                "height": int(self.height),
                "K": self.K.tolist(),
                "dist": self.dist.tolist(),
            },
            "light_plane": None
            if self.light_plane is None
            else {"normal": self.light_plane.normal.tolist(), "d": float(self.light_plane.d)},
            "flange_from_cam": self.flange_from_cam.tolist(),
            **extra,
            "quality": self.quality.to_json(),
        }


def write_calibration(path: str | os.PathLike[str], calibration: Calibration) -> None:
    """Write the calibration file atomically (temporary file, then rename)."""
    write_json_atomic(path, calibration.to_json())


def _covariance_or_none(path: Path, record: Any, has_origin: bool) -> CalibrationCovariance | None:
    """The optional ``covariance`` key; one this reader cannot use (another tool's, or
    damaged) is ignored with a warning: the calibration itself stays valid. Its
    ``laser_origin_mm2`` is judged apart, since no measured value's budget uses it: one that is
    damaged, or without a ``laser_origin_cam`` to belong to, is dropped alone."""
    if record is None:
        return None
    origin_record = record.get("laser_origin_mm2") if isinstance(record, Mapping) else None
    if origin_record is not None:
        record = {k: v for k, v in record.items() if k != "laser_origin_mm2"}
    try:
        covariance = CalibrationCovariance.from_json(record)
    except (TypeError, ValueError) as exc:
        log.warning("%s: covariance ignored (%s): measurements get no calibration share", path, exc)
        return None
    if origin_record is None:
        return covariance
    if not has_origin:
        log.warning(
            "%s: covariance.laser_origin_mm2 ignored (the file has no laser_origin_cam)", path
        )
        return covariance
    try:
        return replace(covariance, laser_origin_mm2=np.asarray(origin_record, dtype=np.float64))
    except (TypeError, ValueError) as exc:
        log.warning("%s: covariance.laser_origin_mm2 ignored (%s)", path, exc)
        return covariance


def read_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read and validate a calibration file.

    Raises
    ------
    InputError
        ``"<path>: <reason>"`` for a missing file, invalid JSON, wrong format or bad values.
    """
    p = Path(path)
    obj = read_json_object(p, "calibration file not found")
    if obj.get("format") != FORMAT:
        raise InputError(p, f"format: expected {FORMAT!r}, got {obj.get('format')!r}")
    try:
        cam = obj["camera"]
        plane = obj.get("light_plane")
        origin = obj.get("laser_origin_cam")
        covariance = _covariance_or_none(p, obj.get("covariance"), origin is not None)
        return Calibration(
            width=json_int(cam["width"], "camera.width"),
            height=json_int(cam["height"], "camera.height"),
            K=np.asarray(cam["K"], dtype=np.float64),
            dist=np.asarray(cam["dist"], dtype=np.float64),
            light_plane=None
            if plane is None
            else LightPlane(np.asarray(plane["normal"], dtype=np.float64), float(plane["d"])),
            laser_origin_cam=None if origin is None else np.asarray(origin, dtype=np.float64),
            covariance=covariance,
            flange_from_cam=np.asarray(obj["flange_from_cam"], dtype=np.float64),
            quality=CalibrationQuality.from_json(obj.get("quality")),
        )
    except KeyError as exc:
        raise InputError(p, f"missing key {exc.args[0]!r}") from None
    except (TypeError, ValueError, OverflowError) as exc:
        raise InputError(p, str(exc)) from None
