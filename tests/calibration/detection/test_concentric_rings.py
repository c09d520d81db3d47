"""Naming coarse ring conics by their sizes when the rays' labels are off."""

from __future__ import annotations

import numpy as np

from calibration.detection.concentric_rings import _relabel_by_ratios


def _circle(radius_px: float, centre=(320.0, 240.0)) -> np.ndarray:
    cx, cy = centre
    return np.array([[1.0, 0, -cx], [0, 1.0, -cy], [-cx, -cy, cx * cx + cy * cy - radius_px**2]])


def test_labels_shifted_by_a_missed_ring_are_put_right() -> None:
    radii = np.array([10.0, 20.0, 30.0, 40.0, 50.0])
    scale = 3.7  # px per mm
    # Rings 1..4 seen, but counted from 0 (the innermost ring was missed).
    conics = {k: _circle(scale * radii[k + 1]) for k in range(4)}
    renamed = _relabel_by_ratios(conics, radii)
    assert sorted(renamed) == [1, 2, 3, 4]
    for n, conic in renamed.items():
        np.testing.assert_allclose(conic, _circle(scale * radii[n]))


def test_a_spurious_outer_conic_does_not_decide() -> None:
    radii = np.array([10.0, 20.0, 30.0, 40.0, 50.0])
    scale = 2.0
    conics = {0: _circle(scale * 20), 1: _circle(scale * 30), 2: _circle(scale * 40)}
    conics[3] = _circle(scale * 50)
    conics[4] = _circle(scale * 80)  # the card's edge
    renamed = _relabel_by_ratios(conics, radii)
    assert sorted(renamed) == [1, 2, 3, 4]
    np.testing.assert_allclose(renamed[4], _circle(scale * 50))


def test_sizes_that_fit_no_spec_give_nothing() -> None:
    radii = np.array([10.0, 20.0, 30.0])
    conics = {0: _circle(10.0), 1: _circle(10.0 * 1.17)}
    assert _relabel_by_ratios(conics, radii) == {}
