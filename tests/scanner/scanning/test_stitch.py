"""Incidence angles from the cloud and the sensor geometry, and ICP between sweeps (scanner.scanning.stitch)."""

from __future__ import annotations

import numpy as np
import pytest

from metrology.fits import fit_sphere
from scanner.scanning.stitch import build_cloud, filter_cloud, incidence_cosines, refine_sweeps

RADIUS_MM = 12.7
CENTER_MM = np.array([600.0, 60.0, 40.0])


def _sphere_sweep(rng: np.random.Generator, noise_mm: float):
    """A sphere swept by a camera 350 mm above it: profiles 0.45 mm apart, points 0.2 mm apart
    along each, the laser 140 mm beside the camera. Returns points, frame index, base_from_cam
    of each frame, the laser origin (camera frame) and the true cosines."""
    laser_cam = np.array([0.0, -140.0, 0.0])
    ys = np.arange(-RADIUS_MM + 0.2, RADIUS_MM, 0.45)
    poses, pts, idx = [], [], []
    for k, y in enumerate(ys):
        pose = np.eye(4)
        pose[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking down
        pose[:3, 3] = CENTER_MM + np.array([0.0, y, 350.0])
        poses.append(pose)
        # The profile: the sphere cut by the plane y = const through the camera.
        rho = np.sqrt(RADIUS_MM**2 - y**2)
        phi = np.arange(0.0, np.pi, 0.2 / rho)
        p = CENTER_MM + np.column_stack(
            [rho * np.cos(phi), np.full_like(phi, y), rho * np.sin(phi)]
        )
        pts.append(p)
        idx.append(np.full(len(p), k))
    pts, idx, poses = np.concatenate(pts), np.concatenate(idx), np.stack(poses)
    normals = (pts - CENTER_MM) / RADIUS_MM
    cam = poses[idx, :3, 3]
    laser = np.einsum("kij,j->ki", poses[idx, :3, :3], laser_cam) + cam

    def true_cos(origin):
        d = origin - pts
        return np.abs(np.einsum("ij,ij->i", normals, d)) / np.linalg.norm(d, axis=1)

    cos_view, cos_laser = true_cos(cam), true_cos(laser)
    pts = pts + normals * rng.normal(0.0, noise_mm, (len(pts), 1))
    return pts, idx, poses, laser_cam, cos_view, cos_laser


def test_incidence_cosines_match_the_true_sphere_geometry():
    rng = np.random.default_rng(0)
    pts, idx, poses, laser_cam, cv_true, cl_true = _sphere_sweep(rng, noise_mm=0.03)
    cos_view, cos_laser = incidence_cosines(pts, idx, poses, laser_cam, normals_radius_mm=1.5)
    ok = np.isfinite(cos_view)
    assert np.count_nonzero(ok) > 0.99 * len(pts)
    # Normals from 1.5 mm neighbourhoods of a 12.7 mm sphere: within a few degrees, so the
    # cosines within a few hundredths (the rim's one-sided neighbourhoods included).
    assert np.percentile(np.abs(cos_view - cv_true)[ok], 95) < 0.03
    assert np.percentile(np.abs(cos_laser - cl_true)[ok], 95) < 0.03
    assert np.all(np.isnan(incidence_cosines(pts, idx, poses, None)[1]))


def test_incidence_limit_removes_a_grazing_bias_from_the_sphere_diameter():
    """Stripe centres biased outward where the surface is seen or lit at grazing angles (as
    a skewed, widened stripe does) enlarge the fitted sphere; dropping points beyond 65 degrees
    of incidence gives back the true diameter."""
    rng = np.random.default_rng(1)
    pts, idx, poses, laser_cam, cv_true, cl_true = _sphere_sweep(rng, noise_mm=0.02)
    graze = np.clip(1.0 - np.minimum(cv_true, cl_true) / 0.4, 0.0, None)  # 0 below 66 deg
    biased = pts + (pts - CENTER_MM) / RADIUS_MM * (0.1 * graze)[:, None]
    plain = fit_sphere(biased)
    assert 2 * plain.radius_mm - 2 * RADIUS_MM > 0.03  # the error the limit is for

    cos_view, cos_laser = incidence_cosines(biased, idx, poses, laser_cam)
    limit = np.cos(np.radians(65.0))
    keep = ~((cos_view < limit) | (cos_laser < limit))
    fit = fit_sphere(biased[keep])
    assert fit
    assert 2 * fit.radius_mm == pytest.approx(2 * RADIUS_MM, abs=0.01)


def test_incidence_cosines_refuse_bad_input():
    with pytest.raises(ValueError, match="frame_index"):
        incidence_cosines(np.zeros((5, 3)), np.zeros(4, int), np.eye(4)[None])
    with pytest.raises(ValueError, match="points_base"):
        incidence_cosines(np.zeros((5, 2)), np.zeros(5, int), np.eye(4)[None])


def _grid(rng: np.random.Generator, x: tuple, y: tuple, z: float, spacing: float = 0.3):
    xs, ys = np.meshgrid(np.arange(*x, spacing), np.arange(*y, spacing))
    p = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)])
    return p + rng.normal(0.0, 0.01, p.shape)


def _block(rng: np.random.Generator) -> np.ndarray:
    """The top and two walls of a 60 x 40 x 30 mm block: a corner pins all six directions."""
    top = _grid(rng, (0, 60), (0, 40), 30.0)
    wall_x = _grid(rng, (0, 60), (0, 30), 0.0)[:, [0, 2, 1]]  # y = 0 wall, z up
    wall_y = _grid(rng, (0, 40), (0, 30), 0.0)[:, [2, 0, 1]]  # x = 0 wall
    return np.concatenate([top, wall_x, wall_y])


def test_icp_corrects_a_sweep_offset_where_the_overlap_pins_it():
    rng = np.random.default_rng(8)
    ref, moved = _block(rng), _block(rng)
    offset = np.array([0.12, -0.08, 0.25])
    pts = np.concatenate([ref, moved + offset])
    sid = np.repeat([0, 1], [len(ref), len(moved)])
    out, (c,) = refine_sweeps(pts, sid)
    assert c.applied
    np.testing.assert_allclose(out[sid == 1].mean(axis=0), moved.mean(axis=0), atol=0.01)
    assert c.translation_mm == pytest.approx(np.linalg.norm(offset), abs=0.01)


def test_icp_leaves_a_sweep_alone_along_directions_its_overlap_does_not_pin():
    """Two sweeps overlapping on one plane: the offset across the plane is corrected, the slide
    along it (which nothing in the overlap can see) is left as the poses put it."""
    rng = np.random.default_rng(9)
    ref = _grid(rng, (0, 60), (0, 40), 30.0)
    moved = _grid(rng, (0, 60), (0, 40), 30.0)
    pts = np.concatenate([ref, moved + np.array([0.4, 0.3, 0.2])])
    sid = np.repeat([0, 1], [len(ref), len(moved)])
    out, (c,) = refine_sweeps(pts, sid)
    assert c.applied
    shift = out[sid == 1].mean(axis=0) - moved.mean(axis=0)
    np.testing.assert_allclose(shift, [0.4, 0.3, 0.0], atol=0.01)


def test_isolated_points_go_and_the_surface_stays():
    rng = np.random.default_rng(10)
    surface = _grid(rng, (0, 30), (0, 20), 5.0)
    strays = np.array([[15.0, 10.0, 52.0], [100.0, 0.0, 5.0]])
    cloud = build_cloud(np.concatenate([surface, strays]))
    kept = filter_cloud(cloud, isolated_radius_mm=2.0).point.positions.numpy()
    assert len(kept) == len(surface)
    assert np.abs(kept[:, 2] - 5.0).max() < 0.1
