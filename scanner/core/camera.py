"""The camera model shared by every stage: pinhole + OpenCV distortion.

Pixel convention: OpenCV's (u = column, v = row, origin at the centre of the top-left pixel).
Distortion: OpenCV's model and order ``(k1, k2, p1, p2, k3)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanner.core.conventions import check_points

__all__ = ["CameraModel", "intersect_rays_with_plane"]

# Undistortion iterates; OpenCV's default (5 iterations) leaves ~0.01 px error at the corners of
# a strongly distorted lens, far above what metrology needs.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics ``K`` (3x3), distortion ``dist`` (OpenCV order) and image size in pixels."""

    width: int
    height: int
    K: NDArray
    dist: NDArray

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K: expected shape (3, 3), got {K.shape}")
        dist = np.zeros(5) if self.dist is None else np.asarray(self.dist, dtype=np.float64)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist.reshape(-1))

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    def project(self, points_cam: ArrayLike) -> NDArray:
        """Project ``(N, 3)`` camera-frame points (mm, z > 0) to ``(N, 2)`` distorted pixels."""
        p = check_points(points_cam, min_count=0, name="points_cam")
        if p.shape[0] == 0:
            return np.zeros((0, 2))
        uv, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, self.dist)
        return uv.reshape(-1, 2)

    def normalize(self, uv: ArrayLike) -> NDArray:
        """Undistorted normalised image coordinates ``(N, 2)`` (x/z, y/z) of pixels ``(N, 2)``."""
        uv = check_points(uv, min_count=0, name="uv", dim=2)
        if uv.shape[0] == 0:
            return np.zeros((0, 2))
        if not self.has_distortion:
            return cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, None).reshape(-1, 2)
        xy = cv2.undistortPointsIter(
            uv.reshape(-1, 1, 2), self.K, self.dist, None, None, _UNDISTORT_CRITERIA
        )
        return xy.reshape(-1, 2)

    def rays(self, uv: ArrayLike) -> NDArray:
        """Rays ``(N, 3)`` through pixels, as ``(x, y, 1)`` in the camera frame (not unit)."""
        xy = self.normalize(uv)
        return np.column_stack([xy, np.ones(len(xy))])

    def undistort_pixels(self, uv: ArrayLike) -> NDArray:
        """Pixels as an ideal (distortion-free) camera with the same ``K`` would see them."""
        xy = self.normalize(uv)
        return xy @ self.K[:2, :2].T + self.K[:2, 2]

    def in_image(self, uv: ArrayLike, margin_px: float = 0.0) -> NDArray:
        """Boolean mask of pixels inside the image, ``margin_px`` from its border."""
        uv = np.asarray(uv, dtype=np.float64)
        return (
            (uv[:, 0] >= -0.5 + margin_px)
            & (uv[:, 0] <= self.width - 0.5 - margin_px)
            & (uv[:, 1] >= -0.5 + margin_px)
            & (uv[:, 1] <= self.height - 0.5 - margin_px)
        )


def intersect_rays_with_plane(rays_cam: ArrayLike, normal: ArrayLike, d: float) -> NDArray:
    """Points where rays from the camera centre meet the plane ``normal . p + d = 0``.

    Parameters
    ----------
    rays_cam : array_like, shape (N, 3)
        Ray directions from the optical centre (any length).
    normal, d
        The plane in the camera frame.

    Returns
    -------
    ndarray, shape (N, 3)
        Intersection points, mm; NaN rows where a ray is parallel to the plane or meets it
        behind the camera.
    """
    r = check_points(rays_cam, min_count=0, name="rays_cam")
    n = np.asarray(normal, dtype=np.float64).reshape(3)
    denom = r @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -float(d) / denom
    bad = ~np.isfinite(s) | (s <= 0) | (np.abs(denom) < 1e-12)
    s = np.where(bad, np.nan, s)
    return r * s[:, None]
