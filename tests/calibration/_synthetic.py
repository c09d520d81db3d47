"""Synthetic cells for the calibration tests: known camera, hand-eye, target and robot poses."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from calibration.extrinsics import project_target
from calibration.hand_eye import PosedView
from scanner.core.camera import CameraModel
from scanner.core.conventions import invert_transform, make_transform


def camera() -> CameraModel:
    K = np.array([[1800.0, 0.0, 640.0], [0.0, 1800.0, 512.0], [0.0, 0.0, 1.0]])
    return CameraModel(1280, 1024, K, np.array([-0.08, 0.12, 0.0004, -0.0003, 0.0]))


def grid_points(n: int = 9, pitch: float = 15.0) -> NDArray:
    g = (np.arange(n) - (n - 1) / 2) * pitch
    xx, yy = np.meshgrid(g, g)
    return np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])


FLANGE_FROM_CAM = make_transform(
    Rotation.from_euler("xyz", [2.0, -3.0, 91.0], degrees=True), [62.0, -35.0, 118.0]
)
BASE_FROM_TARGET = make_transform(
    Rotation.from_euler("xyz", [1.5, -2.0, 30.0], degrees=True), [800.0, 150.0, 20.0]
)


def look_at_target(
    rng: np.random.Generator, distance: float = 450.0, tilt_deg: float = 25.0
) -> NDArray:
    """A ``cam_from_target`` viewing the target centre from ``distance`` with random tilt."""
    tilt = Rotation.from_rotvec(
        np.r_[rng.uniform(-1, 1, 2) * np.radians(tilt_deg), rng.uniform(-np.pi, np.pi)]
    )
    # Camera z looks at the target face (target z out of the face => camera z = -target z).
    target_from_cam_rot = tilt * Rotation.from_euler("x", 180, degrees=True)
    centre = rng.uniform(-10, 10, 3) * np.array([1, 1, 0])
    cam_pos = centre - target_from_cam_rot.apply([0, 0, 1]) * distance
    target_from_cam = make_transform(target_from_cam_rot, cam_pos)
    return invert_transform(target_from_cam)


def posed_views(
    n: int, rng: np.random.Generator, noise_px: float = 0.1, cam: CameraModel | None = None
) -> tuple[list[PosedView], CameraModel]:
    cam = cam or camera()
    pts = grid_points()
    views = []
    for i in range(n):
        ct = look_at_target(rng)
        base_from_cam = BASE_FROM_TARGET @ invert_transform(ct)
        bf = base_from_cam @ invert_transform(FLANGE_FROM_CAM)
        uv = project_target(cam, ct, pts) + rng.normal(0, noise_px, (len(pts), 2))
        views.append(PosedView(i, bf, uv, pts))
    return views, cam
