"""Triangulation: pixels back to light-plane points, exact and through the undistortion table."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from scanner.core.camera import CameraModel
from scanner.core.conventions import make_transform, transform_points
from scanner.formats.calibration_file import Calibration, LightPlane
from scanner.scanning.triangulate import Triangulator, triangulate_frame


def _calibration(dist=(-0.25, 0.12, 0.0008, -0.0005, -0.02)) -> Calibration:
    K = np.array([[1400.0, 0.0, 515.0], [0.0, 1398.0, 380.0], [0.0, 0.0, 1.0]])
    normal = np.array([0.96, 0.02, 0.28])
    plane = LightPlane(normal, -0.28 / np.linalg.norm(normal) * 300.0)
    flange_from_cam = make_transform(
        Rotation.from_euler("xyz", [5, -3, 88], degrees=True), [40, -5, 90]
    )
    return Calibration(1024, 768, K, np.array(dist), plane, flange_from_cam)


def _plane_points(cal: Calibration, rng: np.random.Generator, n: int = 400) -> np.ndarray:
    """Points on the light plane that the camera sees, camera frame, mm."""
    cam = CameraModel(cal.width, cal.height, cal.K, cal.dist)
    uv = rng.uniform([5, 5], [cal.width - 5, cal.height - 5], (4 * n, 2))
    xy = cam.normalize(uv)
    rays = np.column_stack([xy, np.ones(len(xy))])
    s = -cal.light_plane.d / (rays @ cal.light_plane.normal)
    in_front = (s > 0) & (s < 3000)
    return (rays * s[:, None])[in_front][:n]


def test_triangulate_frame_recovers_plane_points_in_the_base_frame():
    rng = np.random.default_rng(0)
    cal = _calibration()
    points_cam = _plane_points(cal, rng)
    cam = CameraModel(cal.width, cal.height, cal.K, cal.dist)
    uv = cam.project(points_cam)
    base_from_flange = make_transform(Rotation.from_rotvec([0.1, -0.2, 0.3]), [400, 20, 600])
    points_base = triangulate_frame(uv, cal, base_from_flange)
    truth = transform_points(base_from_flange @ cal.flange_from_cam, points_cam)
    assert np.abs(points_base - truth).max() < 1e-6


@pytest.mark.parametrize("step", [2.0, 4.0])
def test_undistortion_table_error_is_negligible(step):
    rng = np.random.default_rng(1)
    cal = _calibration()
    uv = rng.uniform([-0.5, -0.5], [cal.width - 0.5, cal.height - 0.5], (5000, 2))
    exact = Triangulator(cal, grid_step_px=0).normalize(uv)
    table = Triangulator(cal, grid_step_px=step).normalize(uv)
    # In pixels (times the focal length): far below the stripe's 0.015 px.
    assert np.abs(table - exact).max() * cal.K[0, 0] < 2e-3


def test_points_base_uses_each_points_own_pose():
    rng = np.random.default_rng(2)
    cal = _calibration(dist=(0, 0, 0, 0, 0))
    poses = np.stack(
        [
            make_transform(Rotation.from_rotvec(rng.normal(0, 0.2, 3)), rng.uniform(-500, 500, 3))
            for _ in range(3)
        ]
    )
    points_cam = _plane_points(cal, rng, 30)
    assert len(points_cam) == 30
    cam = CameraModel(cal.width, cal.height, cal.K, cal.dist)
    uv = cam.project(points_cam)
    idx = rng.integers(0, 3, 30)
    got = Triangulator(cal).points_base(uv, idx, poses)
    for i in range(30):
        want = transform_points(poses[idx[i]] @ cal.flange_from_cam, points_cam[i : i + 1])
        np.testing.assert_allclose(got[i], want[0], atol=1e-6)
    with pytest.raises(ValueError, match=r"frame_index: expected values in 0\.\.2"):
        Triangulator(cal).points_base(uv, idx + 3, poses)


def test_rays_missing_the_plane_give_nan():
    cal = _calibration(dist=(0, 0, 0, 0, 0))
    # Plane through the camera centre's side: a ray parallel to it cannot meet it.
    cal.light_plane = LightPlane(np.array([1.0, 0.0, 0.0]), -50.0)
    pts = Triangulator(cal).points_cam(np.array([[515.0, 380.0]]))
    assert np.all(np.isnan(pts))
