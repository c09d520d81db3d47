import numpy as np

from scanner.core.camera import CameraModel, intersect_rays_with_plane

K = np.array([[1800.0, 0.0, 652.3], [0.0, 1795.0, 498.1], [0.0, 0.0, 1.0]])
DIST = np.array([-0.12, 0.08, 5e-4, -3e-4, -0.01])


def test_rays_invert_projection_to_a_tiny_fraction_of_a_pixel():
    rng = np.random.default_rng(0)
    cam = CameraModel(1280, 1024, K, DIST)
    points_cam = rng.uniform([-250, -200, 400], [250, 200, 700], size=(2000, 3))
    uv = cam.project(points_cam)
    rays = cam.rays(uv)
    err_px = np.abs(rays[:, :2] - points_cam[:, :2] / points_cam[:, 2:]).max() * K[0, 0]
    assert err_px < 1e-6


def test_undistort_pixels_matches_the_ideal_camera():
    rng = np.random.default_rng(1)
    cam = CameraModel(1280, 1024, K, DIST)
    ideal = CameraModel(1280, 1024, K, np.zeros(5))
    points_cam = rng.uniform([-200, -150, 500], [200, 150, 600], size=(100, 3))
    np.testing.assert_allclose(
        cam.undistort_pixels(cam.project(points_cam)), ideal.project(points_cam), atol=1e-6
    )


def test_ray_plane_intersection_lands_on_the_plane_and_the_ray():
    rng = np.random.default_rng(2)
    normal = np.array([0.3, -0.9, 0.2])
    normal /= np.linalg.norm(normal)
    d = -120.0
    rays = np.column_stack([rng.uniform(-0.3, 0.3, (50, 2)), np.ones(50)])
    points = intersect_rays_with_plane(rays, normal, d)
    ok = np.isfinite(points[:, 0])
    assert ok.sum() > 10
    np.testing.assert_allclose(points[ok] @ normal + d, 0.0, atol=1e-9)
    np.testing.assert_allclose(np.cross(points[ok], rays[ok]), 0.0, atol=1e-9)
    # Points behind the camera are NaN, never mirrored in front of it.
    assert np.all(points[ok, 2] > 0)
