"""The planner's sensor model against the virtual cell's physics (stripe truth)."""

from __future__ import annotations

import manifold3d
import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from scanner.formats.meshes import MeshRaycaster, TriangleMesh
from scanner.scanning.coverage import (
    CoverageLimits,
    LinearSweep,
    SensorGeometry,
    sweep_coverage,
    visible_from_above,
)
from scanner.scanning.planning import nadir_rotation
from scanner.virtual_cell import load_cell
from scanner.virtual_cell.parts import SAMPLE_PARTS, box_mesh
from scanner.virtual_cell.render import Laser, Scene, stripe_truth
from scanner.virtual_cell.scene import MeshSurface, object_from_euler


def _sweep_over(sensor: SensorGeometry, centre, tilt_deg: float, yaw_deg: float, step: float):
    rot = (
        Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
        @ Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix()
        @ nadir_rotation(sensor)
    )
    direction = rot @ sensor.travel_direction_cam()
    start = np.eye(4)
    start[:3, :3] = rot
    start[:3, 3] = centre - sensor.working_distance_mm() * rot[:, 2] - 90.0 * direction
    return LinearSweep(start, direction, 180.0, step)


@pytest.mark.parametrize(("tilt", "yaw"), [(0.0, 0.0), (30.0, 60.0)])
def test_predicted_coverage_matches_what_the_renderer_lights_and_sees(tilt, yaw):
    """Every frame's exact stripe (visible, lit) lies on points the model calls measured, and
    the model's measured points are those the stripes pass."""
    cell = load_cell("modern")
    sensor = cell.sensor_geometry()
    centre = np.array([600.0, 100.0, 0.0])
    part = SAMPLE_PARTS["bracket"]()
    lo, hi = part.bounds()
    pose = object_from_euler(centre - np.r_[(lo + hi)[:2] / 2, 0.0], np.zeros(3))
    part_base = part.transformed(pose)
    surface = MeshSurface(part, pose, id="part")
    step = 1.0
    sweep = _sweep_over(sensor, centre + np.array([0.0, 0.0, 25.0]), tilt, yaw, step)
    # No incidence limit: the renderer lights and sees up to grazing.
    limits = CoverageLimits(89.0, 89.0, image_margin_px=0.0)
    rng = np.random.default_rng(5)
    pts, nrm = part_base.sample_surface(20_000, rng)
    predicted = sweep_coverage(sensor, sweep, pts, nrm, MeshRaycaster(part_base), limits)
    assert 0.2 < predicted.mean() < 0.9
    truth = []
    for b_c in sweep.base_from_cam():
        scene = Scene([surface], b_c)
        st = stripe_truth(cell.camera, scene, Laser.from_cell(cell, b_c), step_px=2.0)
        truth.append(st.points_world)
    truth_pts = np.concatenate(truth)
    # A sample is passed by a stripe when a truth point lies within a frame step of it.
    near, _ = cKDTree(truth_pts).query(pts, distance_upper_bound=1.2 * step)
    passed = np.isfinite(near)
    cos_graze = np.abs(np.einsum("ij,j->i", nrm, np.linalg.inv(sweep.base_from_cam_start)[2, :3]))
    clear = cos_graze > 0.2  # leave out grazing views, where both sides round differently
    agree = (predicted == passed)[clear]
    assert agree.mean() > 0.95, agree.mean()
    assert np.mean(passed[predicted & clear]) > 0.97


def test_a_nadir_sweep_measures_a_box_top_and_not_its_walls_or_bottom():
    cell = load_cell("modern")
    sensor = cell.sensor_geometry()
    box = box_mesh((60.0, 40.0, 30.0)).transformed(
        object_from_euler(np.array([570.0, 80.0, 0.0]), np.zeros(3))
    )
    sweep = _sweep_over(sensor, np.array([600.0, 100.0, 30.0]), 0.0, 0.0, 0.5)
    rng = np.random.default_rng(6)
    pts, nrm = box.sample_surface(5000, rng)
    got = sweep_coverage(sensor, sweep, pts, nrm, MeshRaycaster(box), CoverageLimits())
    top, bottom = nrm[:, 2] > 0.99, nrm[:, 2] < -0.99
    assert got[top].all()
    assert not got[bottom].any()
    # The walls stand at 90 deg to the optical axis: only their share within 70 deg of the
    # laser and the camera at the field's edge could count, and a 30 mm box is near the centre.
    assert got[~top & ~bottom].mean() < 0.2


def test_visible_from_above_leaves_out_the_bottom_and_the_depth_of_a_narrow_bore():
    """A 4 mm bore 30 deep in a 40 mm cube: deeper than 15 mm its wall is seen only beyond
    75 deg from its normal (tan 75 = 15 / 4), past the 70 deg limit."""
    cube = manifold3d.Manifold.cube((40.0, 40.0, 40.0))
    bore = manifold3d.Manifold.cylinder(31.0, 2.0, 2.0, 64).translate((20.0, 20.0, 10.0))
    body = (cube - bore).to_mesh()
    part = TriangleMesh(
        np.asarray(body.vert_properties, dtype=np.float64)[:, :3],
        np.asarray(body.tri_verts, dtype=np.int32),
    )
    rng = np.random.default_rng(7)
    pts, nrm = part.sample_surface(40_000, rng)
    seen = visible_from_above(pts, nrm, MeshRaycaster(part), max_incidence_deg=70.0)
    assert not seen[nrm[:, 2] < -0.99].any()
    assert seen[(nrm[:, 2] > 0.99) & (pts[:, 2] > 39.9)].all()
    r = np.hypot(pts[:, 0] - 20.0, pts[:, 1] - 20.0)
    wall = (r < 2.05) & (np.abs(nrm[:, 2]) < 0.01)
    bottom = (r < 2.0) & (nrm[:, 2] > 0.99) & (pts[:, 2] < 10.1)
    assert wall.sum() > 50 and bottom.sum() > 3
    assert seen[bottom].all()
    assert seen[wall & (pts[:, 2] > 39.0)].mean() > 0.9
    assert not seen[wall & (pts[:, 2] < 25.0)].any()
