from __future__ import annotations

import numpy as np
import pytest

from metrology.fits.axial import CircleModel, CylinderModel

RNG = np.random.default_rng(0)


def cylinder_points(n: int, radius: float = 15.0) -> np.ndarray:
    th = RNG.uniform(0, 2 * np.pi, n)
    return np.c_[radius * np.cos(th), radius * np.sin(th), RNG.uniform(-20, 20, n)]


def test_cylinder_from_two_points_with_normals():
    model = CylinderModel()
    sample = np.array([[15.0, 0, 3, 1, 0, 0], [0, 15.0, -4, 0, 1, 0]])
    axis, point, radius = model.from_sample(sample)
    assert np.isclose(abs(axis[2]), 1.0) and np.isclose(radius, 15.0)
    p = cylinder_points(50)
    assert np.allclose(model.residuals((axis, point, radius), p), 0, atol=1e-9)


def test_cylinder_refuses_collinear_points():
    assert "collinear" in CylinderModel().check_cloud(np.outer(np.arange(9.0), [0, 1, 0]))
    assert CylinderModel().check_cloud(cylinder_points(20)) == ""


def test_cylinder_hypotheses_use_normals_and_the_radius_range():
    p = cylinder_points(400)
    inside = CylinderModel((10.0, 20.0)).hypotheses(p)
    outside = CylinderModel((30.0, 40.0)).hypotheses(p)
    found = [inside(RNG.choice(len(p), 2, replace=False)) for _ in range(20)]
    assert any(m is not None and abs(m[2] - 15.0) < 0.5 for m in found)
    assert all(outside(RNG.choice(len(p), 2, replace=False)) is None for _ in range(20))


def test_cylinder_start_from_an_axis_hint_leaves_the_hint_alone():
    hint = np.array([0.0, 0.0, 2.0])
    model = CylinderModel(axis_hint=hint)
    axis, _, radius = model.initial(cylinder_points(300), None, RNG)
    assert np.isclose(abs(axis[2]), 1.0, atol=1e-9) and radius == pytest.approx(15.0)
    assert np.array_equal(hint, [0.0, 0.0, 2.0])


def test_cylinder_result_of_a_plane_is_refused():
    p = np.c_[RNG.uniform(-10, 10, (50, 2)), np.zeros(50)]
    fit = CylinderModel().result((np.array([1.0, 0, 0]), np.array([0, 0, -1e8]), 1e8), p,
                                 np.ones(50, bool))  # fmt: skip
    assert not fit and "planar points" in fit.reason


def test_circle_from_three_points_and_its_distances():
    model = CircleModel()
    centre, normal, radius = model.from_sample(np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0]]))
    assert np.allclose(centre, 0) and np.isclose(radius, 1.0)
    assert np.allclose(model.residuals((centre, normal, radius), np.array([[0, 0, 1.0]])),
                       np.sqrt(2))  # fmt: skip


def test_circle_refine_and_result():
    model = CircleModel()
    th = RNG.uniform(0, np.pi, 200)
    p = np.c_[8 * np.cos(th), 8 * np.sin(th), np.full(200, 5.0)] + RNG.normal(0, 0.01, (200, 3))
    params = model.initial(p, None, RNG)
    for _ in range(2):
        params = model.refine(p, params, RNG)
    fit = model.result(params, p, np.ones(len(p), bool))
    assert fit and fit.radius_mm == pytest.approx(8.0, abs=0.01)
    assert np.allclose(fit.normal, [0, 0, 1], atol=1e-3) and fit.out_of_plane_mm.shape == (200,)
    assert "collinear" in model.initial(np.outer(np.arange(6.0), [1, 1, 0]), None, RNG)
