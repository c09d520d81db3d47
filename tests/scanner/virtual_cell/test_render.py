"""Rendered images agree with the projection of the truth to a small fraction of a pixel."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from scanner.core.conventions import make_transform, transform_points
from scanner.virtual_cell import render_laser_image, render_target_image
from scanner.virtual_cell.capture import TABLE_ID, sweep_scene
from scanner.virtual_cell.cell import CellConfig
from scanner.virtual_cell.poses import sweep_poses
from scanner.virtual_cell.render import Scene, expose, expose_colour, ray_map
from scanner.virtual_cell.scene import PlaneSurface, segment_blocked
from tests.scanner.virtual_cell.conftest import back_project


def _tilted_view(wd: float, tilt_deg: tuple[float, float, float], offset=(0.0, 0.0)) -> np.ndarray:
    rot = Rotation.from_euler("xyz", [180.0 + tilt_deg[0], tilt_deg[1], tilt_deg[2]], degrees=True)
    return make_transform(rot, [offset[0], offset[1], wd])


def _ring_offsets_px(cell: CellConfig, cam_from_target: np.ndarray, image: np.ndarray):
    """Darkness-weighted radial offset of each ring from its true radius, per sector, in px."""
    spec = cell.target_spec()
    cam = cell.camera_model()
    x, y = back_project(cam, cam_from_target)
    r = np.hypot(x, y)
    phi = np.arctan2(y, x)
    white = cell.imaging.white_exposure * 65535.0
    dark = np.clip(white - image.astype(float), 0, None)
    radii = spec.ring_radii_mm
    half = (radii[1] - radii[0]) / 2 - spec.line_width_mm
    mk = spec.orientation_marker
    clear = (
        (np.abs(x) > 2.0)
        & (np.abs(y) > 2.0)
        & (np.hypot(x - mk.center_mm[0], y - mk.center_mm[1]) > mk.diameter_mm)
    )
    out = []
    for ring in radii:
        for k in range(8):
            a0 = -np.pi + k * np.pi / 4
            sel = clear & (np.abs(r - ring) < half) & (phi >= a0) & (phi < a0 + np.pi / 4)
            if sel.sum() < 200 or dark[sel].sum() <= 0:
                continue
            offset_mm = float(np.sum(dark[sel] * (r[sel] - ring)) / np.sum(dark[sel]))
            mid = a0 + np.pi / 8
            p = np.array([[ring * np.cos(mid), ring * np.sin(mid), 0.0]])
            q = p * (1 + 1.0 / ring)
            uv = cam.project(transform_points(cam_from_target, np.vstack([p, q])))
            px_per_mm = float(np.linalg.norm(uv[1] - uv[0]))
            out.append(offset_mm * px_per_mm)
    return np.asarray(out)


@pytest.mark.slow
@pytest.mark.parametrize(
    "cell_fixture, tilt",
    [("paper_exact", (25.0, -10.0, 30.0)), ("modern_exact", (-15.0, 20.0, 70.0))],
)
def test_ring_lines_sit_on_the_projected_rings(cell_fixture, tilt, request):
    cell = request.getfixturevalue(cell_fixture)
    c_t = _tilted_view(cell.capture.working_distance_mm * 1.1, tilt)
    image = render_target_image(cell, c_t, None)
    offsets = _ring_offsets_px(cell, c_t, image)
    assert len(offsets) > 40
    assert np.max(np.abs(offsets)) < 0.05
    assert abs(np.mean(offsets)) < 0.01


def test_diameter_lines_cross_at_projected_centre(paper_exact):
    cell = paper_exact
    spec = cell.target_spec()
    c_t = _tilted_view(520.0, (20.0, 15.0, -40.0), (8.0, -5.0))
    image = render_target_image(cell, c_t, None)
    x, y = back_project(cell.camera_model(), c_t)
    dark = np.clip(cell.imaging.white_exposure * 65535.0 - image.astype(float), 0, None)
    radii = spec.ring_radii_mm
    off_ring = np.min(np.abs(np.hypot(x, y)[..., None] - radii), axis=-1) > 1.5
    # Centre line of the x diameter (y = 0) and of the y diameter (x = 0), mm.
    sel_x = off_ring & (np.abs(y) < 2.0) & (np.abs(x) < radii[-1] - 2)
    sel_y = off_ring & (np.abs(x) < 2.0) & (np.abs(y) < radii[-1] - 2)
    y0 = np.sum(dark[sel_x] * y[sel_x]) / np.sum(dark[sel_x])
    x0 = np.sum(dark[sel_y] * x[sel_y]) / np.sum(dark[sel_y])
    mm_per_px = c_t[2, 3] / cell.camera.fx
    assert abs(y0) / mm_per_px < 0.02
    assert abs(x0) / mm_per_px < 0.02


def test_marker_disc_is_where_the_spec_puts_it(paper_exact):
    cell = paper_exact
    mk = cell.target_spec().orientation_marker
    c_t = _tilted_view(480.0, (10.0, -20.0, 10.0))
    image = render_target_image(cell, c_t, None)
    x, y = back_project(cell.camera_model(), c_t)
    dark = np.clip(cell.imaging.white_exposure * 65535.0 - image.astype(float), 0, None)
    near = np.hypot(x - mk.center_mm[0], y - mk.center_mm[1]) < mk.diameter_mm
    # Weighted by the area each pixel covers on the target: a centroid in the target plane.
    jx = np.hypot(*np.gradient(x))
    jy = np.hypot(*np.gradient(y))
    w = dark[near] * jx[near] * jy[near]
    cx, cy = np.sum(w * x[near]) / np.sum(w), np.sum(w * y[near]) / np.sum(w)
    assert np.hypot(cx - mk.center_mm[0], cy - mk.center_mm[1]) < 0.02  # mm (0.08 px)
    area = np.sum(dark[near] / dark[near].max() * jx[near] * jy[near])
    assert area == pytest.approx(np.pi * mk.diameter_mm**2 / 4, rel=0.02)


def _plain_plane_scene(cell: CellConfig, c_t: np.ndarray) -> Scene:
    return Scene([PlaneSurface(c_t, id="plate", albedo_value=0.85)], np.eye(4), 0.85)


@pytest.mark.parametrize("cell_fixture", ["paper_exact", "modern_exact"])
def test_stripe_centroid_matches_projected_truth(cell_fixture, request):
    cell = request.getfixturevalue(cell_fixture)
    cell = dataclasses.replace(
        cell,
        imaging=dataclasses.replace(cell.imaging, laser_ambient=0.0),
        laser=dataclasses.replace(cell.laser, power=0.6),
    )
    c_t = _tilted_view(cell.capture.working_distance_mm, (15.0, 25.0, 0.0))
    image, truth = render_laser_image(cell, _plain_plane_scene(cell, c_t), None)
    assert len(truth.uv) > 500
    order = np.argsort(truth.uv[:, 0])
    tu, tv = truth.uv[order, 0], truth.uv[order, 1]
    img = image.astype(float)
    errors = []
    for u in range(int(tu.min()) + 5, int(tu.max()) - 5, 3):
        v_true = np.interp(u, tu, tv)
        lo, hi = int(v_true) - 12, int(v_true) + 13
        if lo < 0 or hi > cell.camera.height:
            continue
        col = img[lo:hi, u]
        v_c = np.sum(col * np.arange(lo, hi)) / np.sum(col)
        errors.append(v_c - v_true)
    errors = np.asarray(errors)
    assert len(errors) > 100
    assert np.max(np.abs(errors)) < 0.05
    assert abs(np.mean(errors)) < 0.01


def test_distortion_is_applied(modern_exact):
    """The modern lens bends the stripe by pixels away from the pinhole projection, and the
    rendered stripe follows CameraModel.project (test_stripe_centroid_matches_projected_truth)."""
    cell = modern_exact
    c_t = _tilted_view(cell.capture.working_distance_mm, (0.0, 30.0, 0.0))
    _, truth = render_laser_image(cell, _plain_plane_scene(cell, c_t), None)
    pc = truth.points_world  # world = camera frame here
    pinhole = pc[:, :2] / pc[:, 2:] @ cell.camera.K[:2, :2].T + cell.camera.K[:2, 2]
    np.testing.assert_allclose(truth.uv, cell.camera_model().project(pc), atol=1e-9)
    assert np.max(np.linalg.norm(truth.uv - pinhole, axis=1)) > 3.0


def test_ray_map_inverts_the_camera_projection(modern_exact):
    cam = modern_exact.camera_model()
    rmap = ray_map(modern_exact.camera)
    rng = np.random.default_rng(3)
    i = rng.integers(0, rmap.shape[0], 2000)
    j = rng.integers(0, rmap.shape[1], 2000)
    xy = rmap[i, j]
    uv = cam.project(np.column_stack([xy, np.ones(len(xy))]))
    assert np.max(np.abs(uv - np.column_stack([j - 1.0, i - 1.0]))) < 1e-6


def test_shadow_behind_a_sphere(paper_exact):
    cell = dataclasses.replace(paper_exact, laser=dataclasses.replace(paper_exact.laser, power=0.8))
    b_cams, _ = sweep_poses(cell)
    sphere = np.array(cell.sweep.objects[0].center_mm)
    n, d = cell.laser.normal, cell.laser.d
    f = [n @ transform_points(np.linalg.inv(b), sphere[None])[0] + d for b in b_cams]
    scene = sweep_scene(cell, b_cams[int(np.argmin(np.abs(f)))])
    image, truth = render_laser_image(cell, scene, None)
    table = scene.surface_index(TABLE_ID)
    ids = [scene.surfaces[k].id for k in np.unique(truth.surface)]
    assert "sphere_1" in ids and TABLE_ID in ids
    # The exact table cut, split into points the laser lights and points in the sphere's shadow.
    from scanner.virtual_cell.render import Laser

    laser = Laser.from_cell(cell, scene.world_from_cam)
    pts = scene.surfaces[table].section(
        laser.normal, laser.d, 0.2, scene.world_from_cam[:3, 3], 400.0
    )
    blocked = segment_blocked(scene.surfaces, laser.origin, pts)
    assert blocked.sum() > 20
    cam = cell.camera_model()
    uv = cam.project(transform_points(np.linalg.inv(scene.world_from_cam), pts))
    inside = cam.in_image(uv, 5)
    from scanner.virtual_cell.scene import first_hits

    t, idx = first_hits(
        scene.surfaces, scene.world_from_cam[:3, 3], pts - scene.world_from_cam[:3, 3]
    )
    seen = inside & (idx == table) & (t > 1 - 1e-7)
    img = image.astype(float)
    px = np.rint(uv).astype(int)
    lit_values = img[px[seen & ~blocked, 1], px[seen & ~blocked, 0]]
    shadow_values = img[px[seen & blocked, 1], px[seen & blocked, 0]]
    assert len(shadow_values) > 5
    assert np.median(shadow_values) < 0.1 * np.median(lit_values)


def test_noise_and_quantisation_are_honest():
    from scanner.virtual_cell.cell import ImagingConfig

    im = ImagingConfig(psf_sigma_px=0.0, full_well_e=10000.0, read_noise_e=5.0, black_level_dn=0.0)
    flat = np.full((200, 200), 0.5, dtype=np.float32)
    out = expose(flat, im, 16, np.random.default_rng(0)).astype(float) / 65535.0
    # Shot noise of 5000 e- plus read noise: relative std sqrt(5000 + 25) / 10000.
    assert out.mean() == pytest.approx(0.5, abs=1e-3)
    assert out.std() == pytest.approx(np.sqrt(5025.0) / 10000.0, rel=0.05)
    sat = expose(np.full((4, 4), 3.0, dtype=np.float32), im, 8, None)
    assert np.all(sat == 255)


def test_a_colour_camera_sees_white_light_grey_and_a_red_laser_clip_in_red_only():
    from scanner.virtual_cell.cell import ImagingConfig

    im = ImagingConfig(psf_sigma_px=0.8, black_level_dn=0.0)
    height, width = 64, 96
    rows = np.arange(height, dtype=np.float32)[:, None]
    ambient = np.full((height, width), 0.3, np.float32)
    line = np.exp(-0.5 * ((rows - 31.7) / 1.5) ** 2) * np.ones((1, width), np.float32)
    image = expose_colour(ambient, 3.0 * line, (1.0, 0.1, 0.05), im, 8, None)
    assert image.shape == (height, width, 3) and image.dtype == np.uint8
    # Away from the line the white light is grey: the three channels agree.
    far = image[2:12, 2:-2].astype(int)
    assert np.all(far[..., 0] == far[..., 1]) and np.all(far[..., 1] == far[..., 2])
    # On the line (BGR): red clips; green and blue, through the filters' tails, do not, and
    # rise above the ambient by the laser's response in each.
    core = image[31:33, 4:-4].astype(int)
    assert np.all(core[..., 2] == 255)
    assert core[..., 1].max() < 255
    rise_g = core[..., 1].mean() - far[..., 1].mean()
    rise_b = core[..., 0].mean() - far[..., 0].mean()
    assert rise_g == pytest.approx(2.0 * rise_b, rel=0.1)
    assert 0.08 * 3.0 * 255 < rise_g < 0.1 * 3.0 * 255


@pytest.mark.slow
def test_render_speed_is_measured(paper_exact, modern_exact, capsys):
    """Not an assertion on time: prints it (see the report of the virtual cell)."""
    for cell in (paper_exact, modern_exact):
        c_t = _tilted_view(cell.capture.working_distance_mm, (20.0, 10.0, 30.0))
        render_target_image(cell, c_t, None)  # ray map cached
        t0 = time.process_time()
        render_target_image(cell, c_t, np.random.default_rng(0))
        dt = time.process_time() - t0
        with capsys.disabled():
            print(
                f"\n{cell.name}: {cell.camera.width}x{cell.camera.height} target image {dt:.2f} s CPU"
            )
