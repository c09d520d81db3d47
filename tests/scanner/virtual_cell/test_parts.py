"""Simulated part scans carry their truth: pose, form error, strays."""

from __future__ import annotations

import numpy as np
import pytest

from metrology.inspect.surface import NominalSurface
from scanner.virtual_cell.parts import boss_part, pinned_block, scan_part


@pytest.mark.parametrize("make,top_mm", [(boss_part, 30.0), (pinned_block, 25.0)])
def test_a_scan_mapped_by_its_truth_lies_on_the_nominal(make, top_mm: float) -> None:
    rng = np.random.default_rng(4)
    mesh = make()
    bump = (np.array([30.0, 30.0, top_mm]), 0.2, 5.0)
    scan = scan_part(mesh, rng, count=30_000, noise_mm=0.01, stray_share=0.01, bumps=[bump])
    r, t = scan.nominal_from_cloud[:3, :3], scan.nominal_from_cloud[:3, 3]
    points_nominal = scan.points_cloud @ r.T + t
    signed = NominalSurface(mesh).closest(points_nominal).signed_mm
    good = ~scan.stray
    residual = signed[good] - scan.true_deviation_mm[good]
    assert np.std(residual) == pytest.approx(0.01, rel=0.1)
    assert abs(np.mean(residual)) < 0.001
    assert scan.true_deviation_mm.max() == pytest.approx(0.2, abs=0.01)
    assert scan.stray.sum() == int(0.01 * len(scan.stray))
    # Moved 0.5-3 mm out along the normal: off the surface unless another face is near.
    assert np.mean(np.abs(signed[scan.stray]) > 0.4) > 0.95
