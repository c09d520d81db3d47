"""Find a calibration target in one grey image, whatever its kind."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from calibration.observations import TargetObservation
from scanner.targets import (
    ChessboardTarget,
    CircleGridTarget,
    ConcentricCirclesTarget,
    TargetSpec,
)

__all__ = ["detect_target", "to_gray_float"]


def to_gray_float(image: NDArray) -> NDArray:
    """A 2-D float64 copy of an 8/16-bit or float grey (or BGR colour) image, in [0, 1]."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        w = np.array([0.114, 0.587, 0.299])  # BGR luminance
        img = img[..., :3].astype(np.float64) @ w
        scale = 65535.0 if image.dtype == np.uint16 else 255.0 if image.dtype == np.uint8 else 1.0
        return img / scale
    if img.ndim != 2:
        raise ValueError(f"image: expected a 2-D grey image, got shape {img.shape}")
    if img.dtype == np.uint8:
        return img.astype(np.float64) / 255.0
    if img.dtype == np.uint16:
        return img.astype(np.float64) / 65535.0
    out = img.astype(np.float64)
    if not np.all(np.isfinite(out)):
        raise ValueError("image: expected finite values, got NaN or inf")
    return out


def detect_target(image: NDArray, target: TargetSpec) -> TargetObservation:
    """Find ``target`` in ``image`` and return its labelled observation.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Grey image (uint8, uint16 or float in [0, 1]); a BGR colour image is reduced to grey.
    target : TargetSpec
        The target printed, from the session.

    Returns
    -------
    TargetObservation
        Truthy with exact point correspondences when found; falsy with a reason otherwise.
        Never a wrong labelling: ambiguous detections are refused.
    """
    if isinstance(target, ConcentricCirclesTarget):
        from calibration.detect_concentric import detect_concentric

        return detect_concentric(image, target)
    if isinstance(target, ChessboardTarget):
        from calibration.detect_standard import detect_chessboard

        return detect_chessboard(image, target)
    if isinstance(target, CircleGridTarget):
        from calibration.detect_standard import detect_circle_grid

        return detect_circle_grid(image, target)
    raise ValueError(
        f"target: expected a ConcentricCirclesTarget, ChessboardTarget or CircleGridTarget, "
        f"got {type(target).__name__}"
    )
