"""The alignment finds a part's pose without a guess and says when the pose is ambiguous."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from metrology.inspect.align import (
    AlignOptions,
    apply,
    best_fit,
    pose_distance_mm,
    rps_frame,
)
from metrology.inspect.surface import NominalSurface
from scanner.virtual_cell.parts import boss_part, box_mesh, pinned_block, scan_part


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_best_fit_recovers_the_pose_within_10_um_at_the_extremities(seed: int) -> None:
    rng = np.random.default_rng(seed)
    mesh = boss_part()
    scan = scan_part(mesh, rng, count=80_000, stray_share=0.005)
    surface = NominalSurface(mesh)
    found = best_fit(scan.points_cloud, surface, AlignOptions(seed=seed))
    assert found, found.warnings
    error = pose_distance_mm(found.nominal_from_cloud, scan.nominal_from_cloud, surface.corners())
    assert error < 0.01
    assert found.rms_mm == pytest.approx(0.02, rel=0.2)
    # The stated pose uncertainty is of the order of the error, not orders above or below it.
    assert found.pose_u_mm < 0.01
    assert found.runner_up_rms_mm is not None and found.runner_up_rms_mm > 10 * found.rms_mm


def test_a_box_is_ambiguous_and_says_so() -> None:
    rng = np.random.default_rng(5)
    mesh = box_mesh((100.0, 60.0, 30.0))
    scan = scan_part(mesh, rng, count=40_000)
    found = best_fit(scan.points_cloud, NominalSurface(mesh), AlignOptions(seed=5))
    assert found.ambiguous
    assert not found
    assert any("ambiguous" in w for w in found.warnings)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_small_pin_tells_the_right_pose_of_a_nearly_symmetric_block(seed: int) -> None:
    rng = np.random.default_rng(10 + seed)
    mesh = pinned_block()
    scan = scan_part(mesh, rng, count=80_000)
    surface = NominalSurface(mesh)
    found = best_fit(scan.points_cloud, surface, AlignOptions(seed=seed))
    assert found, found.warnings
    error = pose_distance_mm(found.nominal_from_cloud, scan.nominal_from_cloud, surface.corners())
    assert error < 0.01


def test_best_fit_from_a_given_start_is_a_local_fit() -> None:
    rng = np.random.default_rng(3)
    mesh = boss_part()
    scan = scan_part(mesh, rng, count=30_000)
    surface = NominalSurface(mesh)
    start = scan.nominal_from_cloud.copy()
    start[:3, 3] += [0.8, -0.5, 0.3]
    start[:3, :3] = Rotation.from_rotvec([0.004, 0.0, -0.006]).as_matrix() @ start[:3, :3]
    found = best_fit(scan.points_cloud, surface, AlignOptions(), initial=[start])
    assert found.method.startswith("robust icp")
    assert (
        pose_distance_mm(found.nominal_from_cloud, scan.nominal_from_cloud, surface.corners())
        < 0.01
    )


def test_rps_frame_maps_measured_datums_onto_nominal() -> None:
    rng = np.random.default_rng(0)
    planes = [
        (np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 30.0])),
        (np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, 0.0])),
        (np.array([-1.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0])),
    ]
    moved_from_nominal = np.eye(4)
    moved_from_nominal[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix()
    moved_from_nominal[:3, 3] = rng.normal(0, 50, 3)
    r = moved_from_nominal[:3, :3]
    measured = [(r @ n, apply(moved_from_nominal, p[None])[0]) for n, p in planes]
    nominal_from_moved = rps_frame(planes) @ np.linalg.inv(rps_frame(measured))
    np.testing.assert_allclose(nominal_from_moved @ moved_from_nominal, np.eye(4), atol=1e-9)
