"""Detection of the standard targets labs already own: chessboard and circle grid.

OpenCV finds them (``findChessboardCornersSB``, ``findCirclesGrid``); the points come back as
:class:`TargetObservation` so they go through the same calibration as the concentric target.

Labelling: OpenCV orders the points row by row along the pattern's first dimension, but a
chessboard with an even/odd symmetry (or any circle grid) can come back rotated by 180
degrees between images. That does not matter for intrinsics (each view has its own pose);
consumers that need one board frame across views (hand-eye with a fixed target) must
check the poses' consistency.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.detection.observations import TargetObservation
from scanner.core.images import to_gray_float
from scanner.core.targets import ChessboardTarget, CircleGridTarget

__all__ = ["detect_chessboard", "detect_circle_grid"]


def _to_u8(image: NDArray) -> NDArray:
    g = to_gray_float(image)
    lo, hi = np.percentile(g, [0.5, 99.5])
    if hi <= lo:
        hi = lo + 1e-6
    return np.clip((g - lo) / (hi - lo) * 255.0, 0, 255).astype(np.uint8)


def _found(
    kind: str,
    size: tuple[int, int],
    points_px: NDArray,
    target: ChessboardTarget | CircleGridTarget,
) -> TargetObservation:
    """The observation of a standard target found whole: points in OpenCV's order, ``c0, c1, ...``.

    Parameters
    ----------
    kind : str
        ``"chessboard"`` or ``"circle_grid"``.
    size : tuple of int
        Image ``(width, height)``.
    points_px : ndarray, shape (N, 2)
        The found points, in the order of ``target.object_points()``.
    target : ChessboardTarget or CircleGridTarget
    """
    return TargetObservation(
        ok=True,
        reason="",
        image_size=size,
        kind=kind,
        points_px=points_px,
        points_target=target.object_points(),
        point_names=[f"c{i}" for i in range(len(points_px))],
    )


def detect_chessboard(image: NDArray, target: ChessboardTarget) -> TargetObservation:
    """Inner corners of a chessboard (``findChessboardCornersSB``).

    Returns
    -------
    TargetObservation
        ``points_px`` (cols*rows, 2) in OpenCV's order and ``points_target`` from
        ``target.object_points()``; falsy with a reason when the board is not found whole.
    """
    img = _to_u8(image)
    size = (int(img.shape[1]), int(img.shape[0]))
    pattern = tuple(int(v) for v in target.inner_corners)
    # Plain first (fast, and image normalisation hurts on some real boards), then the
    # exhaustive search for hard views.
    found, corners = False, None
    for flags in (0, cv2.CALIB_CB_EXHAUSTIVE):
        found, corners = cv2.findChessboardCornersSB(img, pattern, flags=flags)
        if found:
            break
    if not found or corners is None:
        return TargetObservation.failed(
            f"chessboard with {pattern[0]}x{pattern[1]} inner corners not found", size, "chessboard"
        )
    pts = corners.reshape(-1, 2).astype(np.float64)
    n = pattern[0] * pattern[1]
    if len(pts) != n:
        return TargetObservation.failed(
            f"chessboard: expected {n} corners, got {len(pts)}", size, "chessboard"
        )
    return _found("chessboard", size, pts, target)


def _blob_detector(image_shape: tuple[int, ...]) -> cv2.SimpleBlobDetector:
    p = cv2.SimpleBlobDetector_Params()
    p.minArea = 10
    p.maxArea = float(image_shape[0] * image_shape[1]) / 20
    p.filterByCircularity = False
    p.filterByConvexity = True
    p.minConvexity = 0.8
    p.filterByInertia = True
    p.minInertiaRatio = 0.1
    p.minDistBetweenBlobs = 5
    return cv2.SimpleBlobDetector_create(p)


def detect_circle_grid(image: NDArray, target: CircleGridTarget) -> TargetObservation:
    """Circle centres of a (symmetric or asymmetric) circle grid (``findCirclesGrid``).

    The centres are the blob detector's centroids, which under perspective lie slightly off
    the images of the circle centres (by a fraction of a pixel for small circles).
    """
    img = _to_u8(image)
    size = (int(img.shape[1]), int(img.shape[0]))
    pattern = tuple(int(v) for v in target.grid)
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if target.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    det = _blob_detector(img.shape)
    found, centres = cv2.findCirclesGrid(img, pattern, flags=flags, blobDetector=det)
    if not found:
        found, centres = cv2.findCirclesGrid(
            img, pattern, flags=flags | cv2.CALIB_CB_CLUSTERING, blobDetector=det
        )
    if not found or centres is None:
        return TargetObservation.failed(
            f"circle grid {pattern[0]}x{pattern[1]} not found", size, "circle_grid"
        )
    return _found("circle_grid", size, centres.reshape(-1, 2).astype(np.float64), target)
