"""Sweep planning: the sample parts covered on two different sensors, and honest refusals."""

from __future__ import annotations

import numpy as np
import pytest

from scanner.scanning.planning import PlanConfig, plan_sweeps
from scanner.virtual_cell import load_cell
from scanner.virtual_cell.parts import SAMPLE_PARTS
from scanner.virtual_cell.scene import object_from_euler


def _placed(name: str, xy=(600.0, 100.0), yaw_deg: float = 0.0):
    part = SAMPLE_PARTS[name]()
    lo, hi = part.bounds()
    shift = object_from_euler(np.r_[-(lo + hi)[:2] / 2, 0.0], np.zeros(3))
    return part.transformed(object_from_euler(np.r_[xy, 0.0], [0, 0, yaw_deg]) @ shift)


@pytest.mark.parametrize("cell_name", ["modern", "paper"])
@pytest.mark.parametrize("name", sorted(SAMPLE_PARTS))
def test_the_sample_parts_are_planned_to_95_percent(cell_name, name):
    cell = load_cell(cell_name)
    plan = plan_sweeps(cell.sensor_geometry(), _placed(name, yaw_deg=17.0), PlanConfig(step_mm=1.0))
    assert plan, plan.reason
    assert plan.coverage >= 0.95
    assert len(plan.sweeps) <= 8
    # The bookkeeping adds up: gains sum to the coverage, each sweep is labelled.
    assert sum(plan.gains) == pytest.approx(plan.coverage)
    measured = plan.measured_by >= 0
    assert np.all(plan.visible[measured])
    assert np.count_nonzero(measured) / plan.visible.sum() == pytest.approx(plan.coverage)
    # Chosen sweeps are trimmed to where they measure: shorter than the candidates' span.
    lo, hi = _placed(name).bounds()
    assert all(s.length_mm < 2 * np.linalg.norm(hi - lo) for s in plan.sweeps)


def test_a_plan_that_cannot_reach_its_target_is_falsy_and_says_why():
    cell = load_cell("modern")
    plan = plan_sweeps(cell.sensor_geometry(), _placed("flange"), PlanConfig(max_sweeps=2))
    assert not plan
    assert "max_sweeps (2)" in plan.reason
    far = plan_sweeps(cell.sensor_geometry(), _placed("bracket"), PlanConfig(reach_mm=(0.0, 100.0)))
    assert not far and far.sweeps == ()
    assert far.reason == "no candidate sweep within reach"
