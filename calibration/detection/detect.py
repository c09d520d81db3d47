"""Find a calibration target in one grey image, whatever its kind."""

from __future__ import annotations

from numpy.typing import NDArray

from calibration.detection.concentric import detect_concentric
from calibration.detection.observations import TargetObservation
from calibration.detection.standard import detect_chessboard, detect_circle_grid
from scanner.core.targets import (
    ChessboardTarget,
    CircleGridTarget,
    ConcentricCirclesTarget,
    TargetSpec,
)

__all__ = ["detect_target"]


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
        return detect_concentric(image, target)
    if isinstance(target, ChessboardTarget):
        return detect_chessboard(image, target)
    if isinstance(target, CircleGridTarget):
        return detect_circle_grid(image, target)
    raise ValueError(
        f"target: expected a ConcentricCirclesTarget, ChessboardTarget or CircleGridTarget, "
        f"got {type(target).__name__}"
    )
