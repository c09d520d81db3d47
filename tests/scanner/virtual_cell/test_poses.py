"""Robot stops and target placements: where the truth says they are."""

from __future__ import annotations

import numpy as np
import pytest

from scanner.core.conventions import angle_between_rotations_deg, invert_transform, transform_points
from scanner.virtual_cell import load_cell
from scanner.virtual_cell.poses import perturb_pose, sweep_poses
from scanner.virtual_cell.simulate import plan_cell


@pytest.fixture(scope="module", params=["paper", "modern"])
def planned(request):
    cell = load_cell(request.param)
    return cell, plan_cell(cell, seed=7)


def _light_plane_distance(cell, cam_from_target, point_t):
    p = transform_points(cam_from_target, np.asarray(point_t, dtype=float)[None])[0]
    return float(cell.laser.normal @ p + cell.laser.d)


def test_light_plane_rows_put_the_diameter_in_the_plane(planned):
    cell, plans = planned
    named = cell.target_spec().named_points()
    rows = [p for p in plans["calibration"] if p.stage == "light_plane"]
    assert len(rows) == cell.capture.light_plane_frames
    for p in rows:
        for key in ("A", "O", "B"):
            assert abs(_light_plane_distance(cell, p.cam_from_target, named[key])) < 1e-9


def test_aimed_rows_put_the_point_on_the_true_plane_up_to_repeatability(planned):
    cell, plans = planned
    named = cell.target_spec().named_points()
    b_t = cell.robot.base_from_target()
    aimed = [p for p in plans["calibration"] + plans["check"] if p.aim]
    assert {p.aim for p in aimed} == {"O", "A", "C"}
    for p in aimed:
        cam_from_target = invert_transform(p.base_from_cam_true) @ b_t
        dist = _light_plane_distance(cell, cam_from_target, named[p.aim])
        assert abs(dist) < 0.3  # the robot's repeatability moves the stripe a little
        reported = (
            invert_transform(p.base_from_flange_reported @ cell.robot.flange_from_cam_matrix())
            @ b_t
        )
        assert abs(_light_plane_distance(cell, reported, named[p.aim])) < 1e-6


def test_check_rows_cross_the_centre_at_varied_orientations(planned):
    cell, plans = planned
    rows = plans["check"]
    assert len(rows) == cell.capture.check_frames
    rots = [p.base_from_flange_reported for p in rows]
    angles = [angle_between_rotations_deg(rots[0], r) for r in rots[1:]]
    assert max(angles) > 10.0


def test_hand_held_views_are_varied_and_realistic(planned):
    cell, plans = planned
    rows = [p for p in plans["calibration"] if p.stage == "hand_held"]
    assert len(rows) == cell.capture.hand_held_frames
    assert all(p.base_from_flange_reported is None for p in rows)
    # Tilt against the line of sight to the target's centre (the view aims within 0.3 radii
    # of it, which moves the line of sight by up to about 8 degrees at the nearest distance).
    tilts = [
        np.degrees(
            np.arccos(
                -p.cam_from_target[:3, 2]
                @ p.cam_from_target[:3, 3]
                / np.linalg.norm(p.cam_from_target[:3, 3])
            )
        )
        for p in rows
    ]
    assert max(tilts) <= cell.capture.max_tilt_deg + 8.0
    assert max(tilts) - min(tilts) > 10.0
    near, far = cell.capture.hand_held_distance
    wd = cell.capture.working_distance_mm
    for p in rows:
        # The target's centre sits off the optical axis, so its depth is below its distance.
        # The aimed point lies within 0.3 radii of the centre.
        distance = np.linalg.norm(p.cam_from_target[:3, 3])
        slack = 0.3 * np.sqrt(2.0) * cell.target_spec().radius_mm
        assert near * wd - slack < distance < far * wd + slack
    # The views reach the image's periphery, not only its centre (distortion needs it).
    cam = cell.camera_model()
    centres = cam.project(np.array([p.cam_from_target[:3, 3] for p in rows]))
    off_centre = np.abs(centres - [cam.width / 2, cam.height / 2]) / [cam.width, cam.height]
    assert np.max(off_centre) > 0.3


def test_repeatability_error_separates_true_and_reported_poses(planned):
    cell, plans = planned
    rows = plans["sweep"] + [
        p for p in plans["calibration"] if p.base_from_flange_reported is not None
    ]
    dt = np.array(
        [
            (invert_transform(p.base_from_flange_reported) @ p.base_from_flange_true)[:3, 3]
            for p in rows
        ]
    )
    ang = np.array(
        [
            angle_between_rotations_deg(p.base_from_flange_reported, p.base_from_flange_true)
            for p in rows
        ]
    )
    sigma, sigma_deg = cell.robot.repeatability_mm, cell.robot.repeatability_deg
    assert np.all(np.linalg.norm(dt, axis=1) > 0)
    assert np.std(dt) == pytest.approx(sigma, rel=0.15)
    # The angle of a rotation vector with per-axis sigma: RMS sqrt(3) sigma.
    assert np.sqrt(np.mean(ang**2)) == pytest.approx(np.sqrt(3) * sigma_deg, rel=0.15)


def test_perturb_pose_is_small_and_seeded():
    pose = np.eye(4)
    a = perturb_pose(pose, np.random.default_rng(1), 0.02, 0.005)
    b = perturb_pose(pose, np.random.default_rng(1), 0.02, 0.005)
    np.testing.assert_array_equal(a, b)
    assert 0 < np.linalg.norm(a[:3, 3]) < 0.2


@pytest.mark.parametrize("name", ["paper", "modern"])
def test_sweep_is_linear_and_crosses_the_line_over_the_centre(name):
    cell = load_cell(name)
    b_cams, direction = sweep_poses(cell)
    assert len(b_cams) == cell.sweep.frames
    steps = np.diff(b_cams[:, :3, 3], axis=0)
    np.testing.assert_allclose(
        steps, np.tile(direction * cell.sweep.step_mm, (len(steps), 1)), atol=1e-9
    )
    mid = b_cams[len(b_cams) // 2]
    centre = np.array(cell.sweep.center_mm)
    p = transform_points(invert_transform(mid), centre[None])[0]
    # The middle frame's light plane runs (within half a step) through the sweep centre.
    assert abs(cell.laser.normal @ p + cell.laser.d) < cell.sweep.step_mm
    # The camera looks down onto the table from the standoff.
    assert mid[2, 2] == pytest.approx(-1.0)
    assert mid[2, 3] - cell.sweep.table_z_mm == pytest.approx(cell.sweep.standoff_mm)


def test_check_rows_keep_e_and_f_in_view(planned):
    cell, plans = planned
    spec = cell.target_spec()
    cam = cell.camera_model()
    b_t = cell.robot.base_from_target()
    for p in plans["check"]:
        c_t = invert_transform(p.base_from_cam_true) @ b_t
        n_t = c_t[:3, :3].T @ cell.laser.normal
        along = np.array([n_t[1], -n_t[0], 0.0]) / np.hypot(n_t[0], n_t[1])
        ef = np.array([along, -along]) * spec.radius_mm
        assert np.all(cam.in_image(cam.project(transform_points(c_t, ef))))


def test_another_frame_count_thins_the_same_sweep():
    # The README's tour asks for 120 frames: the objects must stay inside the sweep.
    cell = load_cell("paper")
    full, direction = sweep_poses(cell)
    thin, _ = sweep_poses(cell, 120)
    assert len(thin) == 120
    np.testing.assert_allclose(thin[[0, -1]], full[[0, -1]], atol=1e-9)
    steps = np.diff(thin[:, :3, 3], axis=0) @ direction
    np.testing.assert_allclose(steps, (cell.sweep.frames - 1) / 119 * cell.sweep.step_mm)
