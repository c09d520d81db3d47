from __future__ import annotations

import numpy as np
import pytest

from metrology.fits.min_zone import min_zone_flatness, min_zone_sphericity


def test_flatness_is_at_most_the_least_squares_range():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-10, 10, (300, 2))
    z = 0.02 * np.sin(xy[:, 0]) + 0.001 * xy[:, 1] + rng.uniform(-0.005, 0.005, 300)
    p = np.c_[xy, z]
    n = np.linalg.svd(p - p.mean(axis=0))[2][2]
    assert min_zone_flatness(p) <= np.ptp((p - p.mean(axis=0)) @ n) + 1e-12
    assert min_zone_flatness(p, [0, 0, 1]) == pytest.approx(min_zone_flatness(p), abs=1e-7)


def test_sphericity_of_an_exact_sphere_is_zero_and_a_degenerate_set_raises():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(100, 3))
    p = 5.0 * d / np.linalg.norm(d, axis=1)[:, None]
    assert min_zone_sphericity(p) < 1e-9
    with pytest.raises(ValueError):
        min_zone_sphericity(np.ones((10, 3)))
