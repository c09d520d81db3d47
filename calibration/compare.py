"""How far one calibration is from another (an estimate from the truth): the accuracy figures.

Used by the demo, the benchmarks and the tests, so every place states accuracy the same way.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from scanner.core.camera import CameraModel
from scanner.core.conventions import angle_between_rotations_deg
from scanner.core.planes import plane_errors
from scanner.formats.calibration_file import Calibration

__all__ = ["CalibrationErrors", "compare_calibrations", "model_reprojection_error_px"]


@dataclass(frozen=True)
class CalibrationErrors:
    """Errors of an estimated calibration against the truth.

    Attributes
    ----------
    fx_rel_pct, fy_rel_pct : float
        Relative focal-length errors, percent (signed).
    cx_px, cy_px : float
        Principal-point errors, pixels (signed).
    model_max_px, model_rms_px : float
        Over a grid covering the whole image: where the estimated camera model (K and
        distortion) puts the rays the true model assigns to each pixel, largest and RMS
        distance, pixels. This is the "reprojects every pixel within X px" figure.
    plane_angle_deg : float
        Angle between the light-plane normals.
    plane_d_mm : float
        Difference of the plane offsets after aligning the normals' signs, mm.
    hand_eye_rotation_deg, hand_eye_translation_mm : float
        Rotation angle and translation distance between the two ``flange_from_cam``.
    """

    fx_rel_pct: float
    fy_rel_pct: float
    cx_px: float
    cy_px: float
    model_max_px: float
    model_rms_px: float
    plane_angle_deg: float
    plane_d_mm: float
    hand_eye_rotation_deg: float
    hand_eye_translation_mm: float

    def to_json(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}


def model_reprojection_error_px(
    estimate: CameraModel, truth: CameraModel, step_px: int = 16
) -> tuple[float, float]:
    """Largest and RMS pixel distance between the two camera models over the whole image."""
    us = np.arange(0, truth.width, step_px, dtype=np.float64)
    vs = np.arange(0, truth.height, step_px, dtype=np.float64)
    uu, vv = np.meshgrid(np.append(us, truth.width - 1), np.append(vs, truth.height - 1))
    uv = np.column_stack([uu.ravel(), vv.ravel()])
    rays = truth.rays(uv)
    uv_est = estimate.project(rays)
    d = np.linalg.norm(uv_est - uv, axis=1)
    return float(d.max()), float(np.sqrt(np.mean(d**2)))


def compare_calibrations(estimate: Calibration, truth: Calibration) -> CalibrationErrors:
    """Accuracy figures of ``estimate`` against ``truth`` (see :class:`CalibrationErrors`)."""
    K, Kt = estimate.K, truth.K
    cam = CameraModel(estimate.width, estimate.height, K, estimate.dist)
    cam_t = CameraModel(truth.width, truth.height, Kt, truth.dist)
    model_max, model_rms = model_reprojection_error_px(cam, cam_t)
    angle, d_error = math.nan, math.nan  # a camera-only calibration has no plane to compare
    if estimate.light_plane is not None and truth.light_plane is not None:
        angle, d_error = plane_errors(estimate.light_plane, truth.light_plane)
    return CalibrationErrors(
        fx_rel_pct=100.0 * (K[0, 0] - Kt[0, 0]) / Kt[0, 0],
        fy_rel_pct=100.0 * (K[1, 1] - Kt[1, 1]) / Kt[1, 1],
        cx_px=float(K[0, 2] - Kt[0, 2]),
        cy_px=float(K[1, 2] - Kt[1, 2]),
        model_max_px=model_max,
        model_rms_px=model_rms,
        plane_angle_deg=angle,
        plane_d_mm=d_error,
        hand_eye_rotation_deg=angle_between_rotations_deg(
            estimate.flange_from_cam, truth.flange_from_cam
        ),
        hand_eye_translation_mm=float(
            np.linalg.norm(estimate.flange_from_cam[:3, 3] - truth.flange_from_cam[:3, 3])
        ),
    )
