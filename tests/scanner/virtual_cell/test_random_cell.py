"""Randomised cells: another valid sensor on the same scene, the same for the same seed."""

from __future__ import annotations

import numpy as np
import pytest

from scanner.core.conventions import check_transform
from scanner.virtual_cell import load_cell
from scanner.virtual_cell.random_cell import randomised_cell


@pytest.mark.parametrize("seed", range(8))
def test_a_randomised_cell_is_a_valid_sensor_on_the_same_scene(seed):
    base = load_cell("modern")
    cell = randomised_cell(base, np.random.default_rng(seed))
    assert cell.sweep == base.sweep and cell.target == base.target
    assert 0.85 <= cell.camera.fx / base.camera.fx <= 1.15
    # the fan still comes from its origin and meets the optical axis where it did
    n, d = cell.laser.normal, cell.laser.d
    assert abs(n @ np.asarray(cell.laser.origin_mm) + d) < 1e-9
    assert -d / n[2] == pytest.approx(-base.laser.d / base.laser.normal[2], abs=1e-6)
    baseline = np.linalg.norm(cell.laser.origin) / np.linalg.norm(base.laser.origin)
    assert 0.8 <= baseline <= 1.2
    check_transform(cell.robot.flange_from_cam_matrix(), "flange_from_cam")
    assert cell.camera != base.camera and cell.laser.plane != base.laser.plane


def test_the_same_seed_gives_the_same_cell_and_another_seed_another():
    base = load_cell("modern")
    a = randomised_cell(base, np.random.default_rng(3))
    assert a == randomised_cell(base, np.random.default_rng(3))
    assert a != randomised_cell(base, np.random.default_rng(4))
