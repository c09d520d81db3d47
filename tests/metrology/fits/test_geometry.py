from __future__ import annotations

import numpy as np
import pytest

from metrology.fits.geometry import (
    circle_distance,
    circle_from_3,
    covariance,
    cylinder_from_normals,
    degenerate_rank,
    frame_std,
    orient,
    perp_basis,
    rng_from,
    sphere_algebraic,
    subsample,
    take,
)


def test_orient_makes_the_largest_component_positive_and_the_vector_unit():
    v = orient(np.array([0.1, -3.0, 0.5]))
    assert np.isclose(np.linalg.norm(v), 1.0)
    assert v[1] > 0 and v[0] < 0


@pytest.mark.parametrize("n", [[0, 0, 1], [1, 0, 0], [0.3, -0.2, 0.9]])
def test_perp_basis_is_right_handed_and_orthonormal(n):
    n = np.asarray(n, float) / np.linalg.norm(n)
    u, v = perp_basis(n)
    frame = np.column_stack([u, v, n])
    assert np.allclose(frame.T @ frame, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(frame), 1.0)


def test_subsample_draws_nothing_when_all_points_fit():
    rng = np.random.default_rng(1)
    state = rng.bit_generator.state
    assert np.array_equal(subsample(5, 10, rng), np.arange(5))
    assert rng.bit_generator.state == state  # the RANSAC sequence does not depend on it
    idx = subsample(100, 10, rng)
    assert len(idx) == 10 and np.all(np.diff(idx) > 0)


def test_rng_from_passes_a_generator_through():
    rng = np.random.default_rng(3)
    assert rng_from(rng) is rng
    assert rng_from(3).integers(1000) == np.random.default_rng(3).integers(1000)


def test_take_does_not_copy_a_full_mask():
    p = np.zeros((4, 3))
    assert take(p, np.ones(4, bool)) is p
    assert take(p, np.array([True, False, True, False])).shape == (2, 3)


@pytest.mark.parametrize(
    ("points", "rank"),
    [
        (np.ones((5, 3)), 0),
        (np.outer(np.arange(5.0), [1, 2, 3]), 1),
        (np.c_[np.random.default_rng(0).normal(size=(9, 2)), np.zeros(9)], 2),
        (np.random.default_rng(0).normal(size=(9, 3)), 3),
    ],
)
def test_degenerate_rank(points, rank):
    assert degenerate_rank(points) == rank


def test_covariance_is_nan_without_degrees_of_freedom():
    jac = np.eye(3)
    assert np.all(np.isnan(covariance(jac, np.zeros(3))))
    jac = np.vstack([np.eye(2), np.eye(2)])
    cov = covariance(jac, np.array([1.0, -1.0, 1.0, -1.0]))
    assert np.allclose(cov, np.eye(2) * (4.0 / 2) / 2)  # sigma^2 = 4 / (4 - 2), J^T J = 2 I


def test_frame_std_maps_in_plane_variances_to_components():
    b = np.column_stack([[1.0, 0, 0], [0, 1.0, 0]])
    assert np.allclose(frame_std(b, np.diag([4.0, 9.0])), [2.0, 3.0, 0.0])


def test_sphere_algebraic_recovers_an_exact_sphere():
    rng = np.random.default_rng(2)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    centre, radius = sphere_algebraic(np.array([1.0, 2.0, 3.0]) + 5.0 * d)
    assert np.allclose(centre, [1, 2, 3]) and np.isclose(radius, 5.0)


def test_circle_from_3_and_its_distance():
    a, b, c = np.array([[1.0, 0, 2], [0, 1.0, 2], [-1.0, 0, 2]])
    centre, normal, radius = circle_from_3(a, b, c)
    assert np.allclose(centre, [0, 0, 2]) and np.isclose(abs(normal[2]), 1.0)
    assert np.isclose(radius, 1.0)
    assert np.allclose(
        circle_distance(np.array([[0, 0, 2.0], [2, 0, 2.0]]), centre, normal, 1.0), 1
    )
    assert circle_from_3(a, 2 * a, 3 * a) is None


def test_cylinder_from_normals_meets_at_the_axis():
    # points on a cylinder of radius 2 about the z axis through (1, 1, 0)
    p1, n1 = np.array([3.0, 1.0, 0.5]), np.array([1.0, 0.0, 0.0])
    p2, n2 = np.array([1.0, 3.0, -2.0]), np.array([0.0, 1.0, 0.0])
    axis, point, radius = cylinder_from_normals(p1, n1, p2, n2)
    assert np.isclose(abs(axis[2]), 1.0) and np.isclose(radius, 2.0)
    assert np.allclose(point[:2], [1.0, 1.0])
    assert cylinder_from_normals(p1, n1, p2, n1) is None  # parallel normals
