"""Scan orientation of a frame: rows (the stripe runs top to bottom) or columns.

From the light plane's image (:func:`orientation_from_calibration`, once per sweep) or from
the frame's own gradients (:func:`orientation_from_image`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["orientation_from_calibration", "orientation_from_image"]


def orientation_from_calibration(calibration: Any, depth_mm: float | None = None) -> str:
    """Scan orientation from the light plane's image: ``"rows"`` when its line runs top-bottom.

    The light plane is cut with a fronto-parallel plane at ``depth_mm`` (default: where the
    plane crosses the optical axis, or 300 mm) and the cut is projected through the intrinsics.

    Parameters
    ----------
    calibration : scanner.formats.calibration_file.Calibration
        Needs ``K``, ``width``, ``height`` and ``light_plane`` (``normal . p + d = 0``, camera).
    """
    n = np.asarray(calibration.light_plane.normal, dtype=np.float64)
    d = float(calibration.light_plane.d)
    if depth_mm is None:
        depth_mm = -d / n[2] if abs(n[2]) > 1e-9 and -d / n[2] > 0 else 300.0
    # The cut is the line {p: n.p + d = 0, z = depth}: its direction is n x z_axis.
    direction = np.cross(n, [0.0, 0.0, 1.0])
    if np.linalg.norm(direction) < 1e-9:  # plane facing the camera: every line looks the same
        return "rows"
    K = np.asarray(calibration.K, dtype=np.float64)
    # Image direction of a 3-D direction in the plane z = depth: K[:2,:2] @ direction[:2].
    du, dv = K[:2, :2] @ direction[:2]
    return "rows" if abs(dv) >= abs(du) else "cols"


def orientation_from_image(image: NDArray) -> str:
    """``"rows"`` when the bright stripe runs top-bottom (its gradients point along u)."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image: expected a 2-D grey image, got shape {img.shape}")
    small = img[::2, ::2].astype(np.float32)
    gu = np.abs(np.diff(small, axis=1)).sum()
    gv = np.abs(np.diff(small, axis=0)).sum()
    return "rows" if gu >= gv else "cols"
