"""A small analytic renderer of planar targets for the detection and intrinsics tests.

Inverse mapping: every (supersampled) pixel is back-projected onto the target plane through
the pinhole (no distortion), the printed reflectance is evaluated there, then blur, vignetting
and noise. Independent of the virtual cell, so detection is tested against an exact truth.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from scanner.core.conventions import make_transform
from scanner.core.targets import ChessboardTarget, ConcentricCirclesTarget, OrientationMarker

WHITE, BLACK = 0.85, 0.08


def demo_target() -> ConcentricCirclesTarget:
    return ConcentricCirclesTarget(
        ring_diameters_mm=(40.0, 60.0, 80.0, 100.0, 120.0, 140.0, 160.0),
        line_width_mm=0.8,
        orientation_marker=OrientationMarker(diameter_mm=8.0, center_mm=(92.0, 0.0)),
    )


def seen_rings(
    rng: np.random.Generator, radii_mm: tuple[float, ...]
) -> tuple[NDArray, dict[int, NDArray], NDArray]:
    """Concentric circles of ``radii_mm`` seen through a random homography (tilts up to about
    60 deg, 600 mm away, f 900 px): its inverse, the ring conics and the image of O."""
    H = np.array([[900.0, 0, 320], [0, 900.0, 240], [0, 0, 1]]) @ np.column_stack(
        [*cv2.Rodrigues(rng.uniform(-0.6, 0.6, 3))[0][:, :2].T, [0.0, 0.0, 600.0]]
    )
    Hinv = np.linalg.inv(H)
    conics = {k: Hinv.T @ np.diag([1.0, 1.0, -r * r]) @ Hinv for k, r in enumerate(radii_mm)}
    o = H @ np.array([0.0, 0.0, 1.0])
    return Hinv, conics, o[:2] / o[2]


def look_at_pose(
    distance_mm: float, tilt_deg: float, tilt_axis_deg: float, roll_deg: float, offset=(0, 0)
) -> NDArray:
    """cam_from_target: target facing the camera, tilted by ``tilt_deg`` about an in-plane axis."""
    face = Rotation.from_euler("x", 180, degrees=True)  # target z towards the camera
    axis = np.array([np.cos(np.radians(tilt_axis_deg)), np.sin(np.radians(tilt_axis_deg)), 0.0])
    tilt = Rotation.from_rotvec(np.radians(tilt_deg) * axis)
    roll = Rotation.from_euler("z", roll_deg, degrees=True)
    rot = tilt * face * roll
    return make_transform(rot, [offset[0], offset[1], distance_mm])


def _reflectance_concentric(x: NDArray, y: NDArray, target: ConcentricCirclesTarget) -> NDArray:
    w2 = target.line_width_mm / 2
    rho = np.hypot(x, y)
    dark = np.zeros(x.shape, bool)
    for r in target.ring_radii_mm:
        dark |= np.abs(rho - r) <= w2
    big = target.radius_mm
    dark |= (np.abs(x) <= w2) & (np.abs(y) <= big)
    dark |= (np.abs(y) <= w2) & (np.abs(x) <= big)
    m = target.orientation_marker
    dark |= np.hypot(x - m.center_mm[0], y - m.center_mm[1]) <= m.diameter_mm / 2
    return np.where(dark, BLACK, WHITE)


def _reflectance_chessboard(x: NDArray, y: NDArray, target: ChessboardTarget) -> NDArray:
    s = target.square_mm
    cols, rows = target.inner_corners
    i = np.floor(x / s)
    j = np.floor(y / s)
    inside = (i >= -1) & (i <= cols - 1) & (j >= -1) & (j <= rows - 1)
    dark = inside & (((i + j) % 2) == 0)
    return np.where(dark, BLACK, WHITE)


def render(
    target,
    K: NDArray,
    cam_from_target: NDArray,
    size: tuple[int, int],
    rng: np.random.Generator,
    blur_px: float = 0.8,
    noise: float = 0.01,
    vignetting: float = 0.3,
    supersample: int = 4,
    laser_line: tuple[float, float, float] | None = None,
    clutter: bool = False,
) -> NDArray:
    """Render a uint8 image of ``target`` seen from ``cam_from_target``.

    ``laser_line`` = (a, b, c): a bright stripe along the image line a u + b v + c = 0.
    """
    w, h = size
    n = supersample
    offs = (np.arange(n) + 0.5) / n - 0.5
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    Kinv = np.linalg.inv(K)
    R, t = cam_from_target[:3, :3], cam_from_target[:3, 3]
    acc = np.zeros((h, w))
    o = -R.T @ t
    for du in offs:
        for dv in offs:
            pix = np.stack([uu + du, vv + dv, np.ones_like(uu)], axis=-1)
            rays = pix @ Kinv.T @ R  # directions in the target frame (R^T d)
            s = -o[2] / rays[..., 2]
            x = o[0] + s * rays[..., 0]
            y = o[1] + s * rays[..., 1]
            if isinstance(target, ConcentricCirclesTarget):
                refl = _reflectance_concentric(x, y, target)
            else:
                refl = _reflectance_chessboard(x, y, target)
            acc += np.where(s > 0, refl, 0.3)
    img = acc / n**2
    if clutter:
        cv2.rectangle(img, (5, 5), (w // 6, h // 5), 0.1, -1)
        cv2.circle(img, (w - w // 8, h - h // 6), max(h // 12, 3), 0.15, 2)
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    rr = np.hypot(uu - w / 2, vv - h / 2) / np.hypot(w / 2, h / 2)
    img = img * (1 - vignetting * rr**2) * (0.9 + 0.2 * uu / w)
    if laser_line is not None:
        a, b, c = laser_line
        dist = np.abs(a * uu + b * vv + c) / np.hypot(a, b)
        img = img + 0.9 * np.exp(-0.5 * (dist / 2.0) ** 2)
    img = img + rng.normal(0.0, noise, img.shape)
    return np.clip(np.round(img * 255), 0, 255).astype(np.uint8)
