from __future__ import annotations

import numpy as np
import pytest

from metrology.fits.models import LineModel, PlaneModel, SphereModel

RNG = np.random.default_rng(0)


def test_plane_from_three_points_and_its_residuals():
    model = PlaneModel()
    sample = np.array([[0.0, 0, 1], [1.0, 0, 1], [0.0, 1, 1]])
    n, d = model.from_sample(sample)
    assert np.allclose(np.abs(n), [0, 0, 1]) and np.isclose(abs(d), 1.0)
    assert np.allclose(model.residuals((n, d), sample), 0)
    assert model.from_sample(np.array([[0.0, 0, 0], [1.0, 1, 1], [2.0, 2, 2]])) is None


def test_plane_refine_is_the_least_squares_plane_or_a_reason():
    model = PlaneModel()
    p = np.c_[RNG.uniform(-1, 1, (20, 2)), np.full(20, 3.0)]
    n, d, c = model.refine(p, None, RNG)
    assert np.allclose(n, [0, 0, 1]) and np.isclose(d, -3.0)
    assert np.allclose(c, p.mean(axis=0))
    assert "collinear" in model.refine(np.outer(np.arange(5.0), [1, 2, 3]), None, RNG)


def test_line_from_two_points_and_its_distances():
    model = LineModel()
    a, e = model.from_sample(np.array([[1.0, 0, 0], [3.0, 0, 0]]))
    assert np.allclose(a, [1, 0, 0]) and np.allclose(e, [1, 0, 0])
    assert np.allclose(model.residuals((a, e), np.array([[5.0, 3, 4]])), 5.0)
    assert model.from_sample(np.ones((2, 3))) is None


def test_line_result_of_coincident_points_fails():
    model = LineModel()
    p = np.ones((4, 3))
    fit = model.result(model.refine(p, None, RNG), p, np.ones(4, bool))
    assert not fit and "coincide" in fit.reason


def test_sphere_from_four_points():
    model = SphereModel()
    d = RNG.normal(size=(4, 3))
    sample = np.array([1.0, -2.0, 3.0]) + 7.0 * d / np.linalg.norm(d, axis=1)[:, None]
    c, r = model.from_sample(sample)
    assert np.allclose(c, [1, -2, 3]) and np.isclose(r, 7.0)
    coplanar = np.c_[RNG.normal(size=(4, 2)), np.zeros(4)]
    assert model.from_sample(coplanar) is None


@pytest.mark.parametrize(
    ("points", "words"),
    [(np.ones((5, 3)), "coincident"), (np.c_[RNG.normal(size=(9, 2)), np.zeros(9)], "coplanar")],
)
def test_sphere_initial_refuses_a_degenerate_set(points, words):
    reason = SphereModel().initial(points, None, RNG)
    assert isinstance(reason, str) and words in reason


def test_sphere_refine_and_result():
    model = SphereModel()
    d = RNG.normal(size=(300, 3))
    p = 12.7 * d / np.linalg.norm(d, axis=1)[:, None] + RNG.normal(0, 0.01, (300, 3))
    params = model.refine(p, (np.array([0.5, 0, 0]), 12.0), RNG)
    fit = model.result(params, p, np.ones(len(p), bool))
    assert fit and fit.radius_mm == pytest.approx(12.7, abs=0.005)
    assert np.all(fit.center_std_mm > 0) and fit.radius_std_mm > 0
    huge = model.result((np.array([0.0, 0, 1e9]), 1e9), p, np.ones(len(p), bool))
    assert not huge and "nearly planar" in huge.reason
