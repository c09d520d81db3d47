from __future__ import annotations

import math

import numpy as np
import pytest

from metrology.fits.models import PlaneModel, SphereModel
from metrology.fits.results import PlaneFit
from metrology.fits.robust import (
    BAND_SIGMAS,
    check_threshold,
    inlier_band,
    radius_bounds,
    ransac,
    robust_fit,
)


def plane_points(n: int, rng: np.random.Generator, noise: float = 0.0) -> np.ndarray:
    xy = rng.uniform(-50, 50, (n, 2))
    return np.c_[xy, 0.01 * xy[:, 0] + 2.0 + rng.normal(0, noise, n)]


def ball(n: int, rng: np.random.Generator, radius: float = 10.0) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return radius * d / np.linalg.norm(d, axis=1)[:, None]


# ---------------------------------------------------------------------------- pieces


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, math.inf])
def test_check_threshold_refuses_a_non_positive_or_non_finite_value(bad):
    with pytest.raises(ValueError, match="threshold_mm"):
        check_threshold(bad)
    check_threshold(None)
    check_threshold(0.1)


def test_radius_bounds_default_to_the_cloud_extent_and_check_a_range():
    p = np.array([[0.0, 0, 0], [4.0, 1, 0]])
    assert radius_bounds(None, p) == (0.0, 4.0)
    assert radius_bounds((1, 2), p) == (1.0, 2.0)
    with pytest.raises(ValueError, match="radius_range_mm"):
        radius_bounds((2.0, 1.0), p)


def test_inlier_band_widens_only_for_wider_noise():
    rng = np.random.default_rng(0)
    assert inlier_band(0.1, rng.normal(0, 1.0, 5)) == 0.1  # too few residuals to judge
    assert inlier_band(0.1, rng.normal(0, 0.001, 1000)) == 0.1
    wide = inlier_band(0.1, rng.normal(0, 1.0, 10_000))
    assert wide == pytest.approx(BAND_SIGMAS, rel=0.05)
    # 2-D distances of the same noise: Rayleigh, median 1.1774 sigma
    dist = np.hypot(rng.normal(0, 1.0, 10_000), rng.normal(0, 1.0, 10_000))
    assert inlier_band(0.1, dist, signed=False) == pytest.approx(BAND_SIGMAS, rel=0.05)


def test_ransac_stops_once_every_point_is_an_inlier():
    rng = np.random.default_rng(1)
    p = plane_points(200, rng)
    model = PlaneModel()
    calls = []

    def estimate(idx):
        calls.append(idx)
        return model.hypotheses(p)(idx)

    best = ransac(len(p), 3, estimate, lambda m: np.abs(model.residuals(m, p)), 0.01, rng, 1000)
    assert best is not None and len(calls) == 1
    assert np.allclose(np.abs(model.residuals(best, p)), 0, atol=1e-9)


def test_ransac_returns_none_without_a_hypothesis():
    rng = np.random.default_rng(2)
    assert ransac(10, 2, lambda idx: None, lambda m: np.zeros(10), 0.1, rng, 50) is None


# ---------------------------------------------------------------------------- the loop


class _Failing(PlaneModel):
    """A plane model whose steps can be made to fail, to reach the loop's exits."""

    def __init__(self, cloud: str = "", sample: bool = True, start: str = "") -> None:
        self.cloud, self.sample, self.start = cloud, sample, start

    def check_cloud(self, points):
        return self.cloud

    def from_sample(self, sample):
        return super().from_sample(sample) if self.sample else None

    def initial(self, points, hint, rng):
        return self.start or None


@pytest.mark.parametrize(
    ("model", "threshold", "words"),
    [
        (_Failing(cloud="degenerate: no good"), None, "degenerate: no good"),
        (_Failing(sample=False), 0.1, "RANSAC found no plane"),
        (_Failing(start="degenerate: no start"), None, "degenerate: no start"),
    ],
)
def test_each_failure_is_a_falsy_fit_of_the_model_with_its_reason(model, threshold, words):
    fit = robust_fit(model, plane_points(50, np.random.default_rng(3)), threshold)
    assert isinstance(fit, PlaneFit) and not fit
    assert words in fit.reason


class _TwoInliers(PlaneModel):
    """Whatever the plane, only the first two points lie on it."""

    def residuals(self, params, points):
        return np.r_[0.0, 0.0, np.full(len(points) - 2, 1e3)]


def test_too_few_points_and_too_few_inliers():
    fit = robust_fit(PlaneModel(), np.zeros((2, 3)))
    assert not fit and fit.reason == "too few points: expected at least 3, got 2"
    fit = robust_fit(_TwoInliers(), plane_points(20, np.random.default_rng(4)), 0.1)
    assert not fit and fit.reason == "too few inliers: expected at least 3, got 2"


def test_rounds_take_every_inlier_and_no_clutter():
    rng = np.random.default_rng(5)
    good = plane_points(1000, rng, noise=0.01)
    p = np.vstack([good, rng.uniform(-50, 50, (300, 3)) + np.array([0.0, 0.0, 60.0])])
    fit = robust_fit(PlaneModel(), p, 0.05, seed=1)
    assert fit.inliers[:1000].mean() > 0.999 and not fit.inliers[1000:].any()
    again = robust_fit(PlaneModel(), p, 0.05, seed=1)
    assert np.array_equal(again.inliers, fit.inliers) and np.array_equal(again.normal, fit.normal)


def test_a_big_cloud_is_presolved_on_a_subsample():
    class SmallSubsample(SphereModel):
        ransac_subsample = 500

    rng = np.random.default_rng(6)
    good = ball(3000, rng) + rng.normal(0, 0.005, (3000, 3))
    p = np.vstack([good, rng.uniform(-15, 15, (600, 3))])
    fit = robust_fit(SmallSubsample(), p, 0.03, seed=2)
    assert fit, fit.reason
    assert fit.inliers.size == len(p)  # the mask is of the full cloud
    assert fit.inliers[:3000].mean() > 0.99 and fit.inliers[3000:].mean() < 0.05
    assert fit.radius_mm == pytest.approx(10.0, abs=0.002)


def test_radius_range_keeps_ransac_to_the_nominal():
    rng = np.random.default_rng(7)
    small, big = ball(500, rng, 5.0), ball(500, rng, 20.0) + np.array([100.0, 0, 0])
    p = np.vstack([small, big])
    fit = robust_fit(SphereModel((15.0, 25.0)), p, 0.01)
    assert fit.radius_mm == pytest.approx(20.0) and fit.inliers[500:].all()
    with pytest.raises(ValueError, match="radius_range_mm"):
        robust_fit(SphereModel((1.0, 1.0)), p, 0.01)
