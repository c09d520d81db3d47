from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import minimize

from metrology.fits import (
    fit_circle,
    fit_cylinder,
    fit_line,
    fit_plane,
    fit_sphere,
    min_zone_flatness,
    min_zone_sphericity,
)

REPO = Path(__file__).resolve().parents[3]
REAL = Path(os.environ.get("SCANNER_REAL_DATA", REPO.parent / "shared" / "data" / "real"))

UM = 1e-3  # one micrometre in mm


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def angle_deg(a, b) -> float:
    """Angle between two lines (sign of the vectors ignored)."""
    c = abs(float(np.dot(unit(a), unit(b))))
    return float(np.degrees(np.arccos(min(1.0, c))))


def basis(n) -> tuple[np.ndarray, np.ndarray]:
    n = unit(n)
    u = unit(np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0]))
    return u, np.cross(n, u)


def sample_plane(normal, d, n, rng, noise_mm=0.0, half_size=50.0):
    normal = unit(normal)
    u, v = basis(normal)
    st = rng.uniform(-half_size, half_size, (n, 2))
    p = -d * normal + st[:, :1] * u + st[:, 1:] * v
    return p + normal * rng.normal(0.0, noise_mm, (n, 1)) if noise_mm else p


def sample_sphere(center, radius, n, rng, noise_mm=0.0, cap=False):
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    if cap:  # the upper hemisphere only, as a scanner sees a ball on a bar
        d[:, 2] = np.abs(d[:, 2])
    r = radius + (rng.normal(0.0, noise_mm, n) if noise_mm else 0.0)
    return np.asarray(center) + d * np.atleast_1d(r)[:, None]


def sample_cylinder(axis, point, radius, n, rng, noise_mm=0.0, arc=2 * np.pi, length=60.0):
    a = unit(axis)
    u, v = basis(a)
    th = rng.uniform(0, arc, n)
    t = rng.uniform(-length / 2, length / 2, n)
    r = radius + (rng.normal(0.0, noise_mm, n) if noise_mm else np.zeros(n))
    radial = np.cos(th)[:, None] * u + np.sin(th)[:, None] * v
    return np.asarray(point) + t[:, None] * a + r[:, None] * radial


def sample_circle(center, normal, radius, n, rng, noise_mm=0.0, arc=2 * np.pi):
    u, v = basis(normal)
    th = rng.uniform(0, arc, n)
    p = np.asarray(center) + radius * (np.cos(th)[:, None] * u + np.sin(th)[:, None] * v)
    return p + rng.normal(0.0, noise_mm, p.shape) if noise_mm else p


# ---------------------------------------------------------------------------- noise-free truth


def test_plane_fit_recovers_truth():
    rng = np.random.default_rng(0)
    normal_true, d_true = unit([1.0, -2.0, 0.5]), 12.0
    fit = fit_plane(sample_plane(normal_true, d_true, 500, rng))
    assert fit
    assert angle_deg(fit.normal, normal_true) < 0.001
    d_signed = d_true if fit.normal @ normal_true > 0 else -d_true
    assert abs(fit.d_mm - d_signed) < UM
    assert fit.rms_mm < UM and fit.n_inliers == 500


def test_sphere_fit_recovers_truth_from_a_cap():
    rng = np.random.default_rng(1)
    center, radius = np.array([120.0, -40.0, 310.0]), 12.7
    fit = fit_sphere(sample_sphere(center, radius, 800, rng, cap=True))
    assert fit
    assert np.linalg.norm(fit.center_mm - center) < UM
    assert abs(fit.radius_mm - radius) < UM
    assert abs(fit.diameter_mm - 25.4) < 2 * UM


@pytest.mark.parametrize("arc", [2 * np.pi, np.pi / 2])
def test_cylinder_fit_recovers_truth_from_a_full_or_partial_surface(arc):
    rng = np.random.default_rng(2)
    axis, point, radius = unit([0.3, 0.2, 1.0]), np.array([5.0, 6.0, 7.0]), 20.0
    fit = fit_cylinder(sample_cylinder(axis, point, radius, 2000, rng, arc=arc))
    assert fit, fit.reason
    assert angle_deg(fit.axis, axis) < 0.001
    assert abs(fit.radius_mm - radius) < UM
    # the fitted axis point lies on the true axis
    q = fit.point_mm - point
    assert np.linalg.norm(q - (q @ axis) * axis) < UM


def test_short_cylinder_ring_is_found_by_the_direction_search():
    rng = np.random.default_rng(3)
    axis, point, radius = unit([-0.5, 0.1, 0.2]), np.array([0.0, 50.0, 0.0]), 40.0
    fit = fit_cylinder(sample_cylinder(axis, point, radius, 1500, rng, length=10.0))
    assert fit, fit.reason
    assert angle_deg(fit.axis, axis) < 0.001
    assert abs(fit.radius_mm - radius) < UM


def test_circle_fit_recovers_truth_from_an_arc():
    rng = np.random.default_rng(4)
    center, normal, radius = np.array([1.0, 2.0, 300.0]), unit([0.1, -0.3, 1.0]), 8.0
    fit = fit_circle(sample_circle(center, normal, radius, 300, rng, arc=np.pi))
    assert fit, fit.reason
    assert np.linalg.norm(fit.center_mm - center) < UM
    assert angle_deg(fit.normal, normal) < 0.001
    assert abs(fit.radius_mm - radius) < UM


def test_line_fit_recovers_truth():
    rng = np.random.default_rng(5)
    direction, point = unit([1.0, 1.0, -0.2]), np.array([10.0, 0.0, -3.0])
    p = point + rng.uniform(-100, 100, (200, 1)) * direction
    fit = fit_line(p)
    assert fit
    assert angle_deg(fit.direction, direction) < 0.001
    q = fit.point_mm - point
    assert np.linalg.norm(q - (q @ direction) * direction) < UM


# ---------------------------------------------------------------------------- failures


@pytest.mark.parametrize(
    ("fitter", "points", "words"),
    [
        (fit_plane, np.zeros((2, 3)), "too few points"),
        (fit_plane, np.outer(np.arange(10.0), [1.0, 2.0, 3.0]), "collinear"),
        (fit_sphere, np.zeros((3, 3)), "too few points"),
        (fit_circle, np.outer(np.arange(10.0), [1.0, 0.0, 0.0]), "collinear"),
        (fit_cylinder, np.outer(np.arange(10.0), [0.0, 1.0, 0.0]), "collinear"),
        (fit_line, np.ones((5, 3)), "coincide"),
    ],
)
def test_degenerate_input_gives_a_falsy_fit_with_a_reason(fitter, points, words):
    fit = fitter(points)
    assert not fit
    assert words in fit.reason
    assert np.all(np.isnan(fit.to_json().get("radius_mm", np.nan)))
    assert fit.to_json()["ok"] is False and words in fit.to_json()["reason"]


def test_sphere_on_coplanar_points_fails():
    rng = np.random.default_rng(6)
    fit = fit_sphere(sample_plane([0, 0, 1], 5.0, 100, rng))
    assert not fit and "coplanar" in fit.reason


def test_cylinder_on_a_plane_fails():
    rng = np.random.default_rng(7)
    fit = fit_cylinder(sample_plane([0, 1, 1], 5.0, 500, rng))
    assert not fit and "radius" in fit.reason


def test_bad_arguments_raise_value_error():
    with pytest.raises(ValueError, match=r"expected \(N, 3\)"):
        fit_plane(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="threshold_mm"):
        fit_sphere(np.zeros((5, 3)), threshold_mm=-1.0)


# ---------------------------------------------------------------------------- robust detection


def test_ransac_rejects_outliers_and_is_repeatable():
    rng = np.random.default_rng(8)
    center, radius = np.array([0.0, 0.0, 100.0]), 12.7
    good = sample_sphere(center, radius, 1500, rng, noise_mm=0.005, cap=True)
    table = sample_plane([0, 0, 1], -100.0 + radius, 1500, rng, noise_mm=0.005, half_size=40)
    clutter = rng.uniform(-40, 40, (500, 3)) + center
    p = np.vstack([good, table, clutter])
    fit = fit_sphere(p, threshold_mm=0.05, seed=3)
    assert fit
    assert np.linalg.norm(fit.center_mm - center) < 0.005
    assert abs(fit.radius_mm - radius) < 0.005
    assert fit.inliers[:1500].mean() > 0.99
    assert fit.inliers[1500:].mean() < 0.05
    again = fit_sphere(p, threshold_mm=0.05, seed=3)
    assert np.array_equal(again.inliers, fit.inliers)
    assert np.array_equal(again.center_mm, fit.center_mm)
    nominal = fit_sphere(p, threshold_mm=0.05, seed=4, radius_range_mm=(10.0, 15.0))
    assert abs(nominal.radius_mm - radius) < 0.005


@pytest.mark.parametrize("kind", ["plane", "cylinder", "circle", "line"])
def test_ransac_finds_each_primitive_among_clutter(kind):
    rng = np.random.default_rng(9)
    if kind == "plane":
        good = sample_plane([0.2, 0.1, 1.0], 3.0, 2000, rng, noise_mm=0.01)
        fit = fit_plane(np.vstack([good, rng.uniform(-50, 50, (800, 3))]), 0.05)
        assert angle_deg(fit.normal, [0.2, 0.1, 1.0]) < 0.01
    elif kind == "cylinder":
        good = sample_cylinder([0, 1, 0.2], [0, 0, 0], 15.0, 3000, rng, 0.01, arc=np.pi)
        fit = fit_cylinder(np.vstack([good, rng.uniform(-30, 30, (600, 3))]), 0.05)
        assert angle_deg(fit.axis, [0, 1, 0.2]) < 0.05
        assert abs(fit.radius_mm - 15.0) < 0.005
    elif kind == "circle":
        good = sample_circle([5, 5, 5], [0, 0, 1], 10.0, 400, rng, noise_mm=0.005)
        fit = fit_circle(np.vstack([good, rng.uniform(-10, 20, (150, 3))]), 0.03)
        assert abs(fit.radius_mm - 10.0) < 0.005
    else:
        good = np.outer(rng.uniform(-50, 50, 300), unit([1, 2, 3])) + rng.normal(0, 0.01, (300, 3))
        fit = fit_line(np.vstack([good, rng.uniform(-50, 50, (200, 3))]), 0.05)
        assert angle_deg(fit.direction, [1, 2, 3]) < 0.01
    assert fit, fit.reason
    assert fit.inliers[: len(good)].mean() > 0.95
    assert fit.inliers[len(good) :].mean() < 0.1


# ---------------------------------------------------------------------------- uncertainty


def _check_std(estimates: np.ndarray, reported: np.ndarray, what: str) -> None:
    """Empirical standard deviation over trials against the mean reported one, within 1.5x."""
    empirical = estimates.std(axis=0, ddof=1)
    predicted = reported.mean(axis=0)
    ratio = np.atleast_1d(empirical / predicted)
    assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), f"{what}: empirical/reported {ratio}"


def test_plane_reported_std_matches_repeated_trials():
    rng = np.random.default_rng(10)
    normal, d = unit([0.3, -0.2, 1.0]), -40.0
    est, rep = [], []
    for _ in range(200):
        f = fit_plane(sample_plane(normal, d, 200, rng, noise_mm=0.02))
        est.append(np.r_[f.normal, f.d_mm])
        rep.append(np.r_[f.normal_std, f.d_std_mm])
    _check_std(np.array(est), np.array(rep), "plane normal, d")


def test_sphere_reported_std_matches_repeated_trials():
    rng = np.random.default_rng(11)
    center, radius = np.array([10.0, 20.0, 300.0]), 12.7
    est, rep = [], []
    for _ in range(200):
        f = fit_sphere(sample_sphere(center, radius, 300, rng, noise_mm=0.02, cap=True))
        est.append(np.r_[f.center_mm, f.radius_mm])
        rep.append(np.r_[f.center_std_mm, f.radius_std_mm])
    _check_std(np.array(est), np.array(rep), "sphere centre, radius")


@pytest.mark.slow
def test_cylinder_reported_std_matches_repeated_trials():
    rng = np.random.default_rng(12)
    axis, point, radius = unit([0.2, 0.1, 1.0]), np.zeros(3), 15.0
    u, v = basis(axis)
    est, rep = [], []
    for _ in range(200):
        f = fit_cylinder(sample_cylinder(axis, point, radius, 400, rng, noise_mm=0.02))
        a = f.axis if f.axis @ axis > 0 else -f.axis
        # the axis where it crosses the plane through the origin perpendicular to the true axis
        crossing = f.point_mm - (f.point_mm @ axis) / (a @ axis) * a
        est.append(np.r_[a @ u, a @ v, crossing @ u, crossing @ v, f.radius_mm])
        rep.append(
            np.r_[np.sqrt(np.diag(f.cov))[:4], f.radius_std_mm]
        )  # tilts in rad ~ axis components; shifts in mm
    _check_std(np.array(est), np.array(rep), "cylinder tilt u/v, shift u/v, radius")


@pytest.mark.slow
def test_circle_reported_std_matches_repeated_trials():
    rng = np.random.default_rng(13)
    center, normal, radius = np.array([0.0, 0.0, 50.0]), unit([0.1, 0.2, 1.0]), 10.0
    est, rep = [], []
    for _ in range(200):
        f = fit_circle(sample_circle(center, normal, radius, 100, rng, noise_mm=0.02))
        est.append(np.r_[f.center_mm, f.radius_mm])
        rep.append(np.r_[f.center_std_mm, f.radius_std_mm])
    _check_std(np.array(est), np.array(rep), "circle centre, radius")


def test_line_reported_std_matches_repeated_trials():
    rng = np.random.default_rng(14)
    direction = unit([1.0, 0.5, 0.2])
    u, v = basis(direction)
    est, rep = [], []
    for _ in range(200):
        t = rng.uniform(-50, 50, (100, 1))
        p = t * direction + rng.normal(0, 0.02, (100, 3))
        f = fit_line(p)
        e = f.direction if f.direction @ direction > 0 else -f.direction
        est.append(e)
        rep.append(f.direction_std)
    est_a, rep_a = np.array(est), np.array(rep)
    # compare the components perpendicular to the true direction (the parallel one is 2nd order)
    _check_std(est_a @ np.c_[u, v], np.c_[rep_a.mean(0) @ np.abs(np.c_[u, v])].T, "line direction")


# ---------------------------------------------------------------------------- form


def _brute_flatness(p: np.ndarray) -> float:
    def zone(ang):
        n = unit([np.sin(ang[0]) * np.cos(ang[1]), np.sin(ang[0]) * np.sin(ang[1]), np.cos(ang[0])])
        return np.ptp(p @ n)

    best = min(
        (minimize(zone, x0, method="Nelder-Mead", options={"xatol": 1e-12, "fatol": 1e-14,
                                                           "maxiter": 20000})
         for x0 in ([1e-3, 0.0], [1e-3, 1.5], [2e-3, 3.0])),
        key=lambda r: r.fun,
    )  # fmt: skip
    return float(best.fun)


def test_min_zone_flatness_is_the_smallest_zone():
    rng = np.random.default_rng(15)
    st = rng.uniform(-20, 20, (60, 2))
    z = 0.01 * np.sin(st[:, 0] / 5.0) + 0.002 * st[:, 1] / 20 + rng.uniform(-0.003, 0.003, 60)
    p = np.c_[st, z]
    fit = fit_plane(p, min_zone=True)
    assert fit.min_zone_mm is not None
    assert fit.min_zone_mm <= fit.range_mm + 1e-12
    assert fit.min_zone_mm == pytest.approx(_brute_flatness(p), abs=1e-7)


def test_min_zone_sphericity_is_the_smallest_zone():
    rng = np.random.default_rng(16)
    p = sample_sphere([0.0, 0.0, 0.0], 10.0, 80, rng, cap=True)
    p *= 1 + 0.002 * np.sin(3 * p[:, :1]) + rng.uniform(-0.0005, 0.0005, (80, 1))
    fit = fit_sphere(p, min_zone=True)
    best = minimize(
        lambda c: np.ptp(np.linalg.norm(p - c, axis=1)), fit.center_mm, method="Nelder-Mead",
        options={"xatol": 1e-12, "fatol": 1e-14, "maxiter": 20000},
    )  # fmt: skip
    assert fit.min_zone_mm <= fit.range_mm + 1e-12
    assert fit.min_zone_mm == pytest.approx(min(best.fun, fit.min_zone_mm), abs=2e-6)
    assert min_zone_sphericity(p) == pytest.approx(fit.min_zone_mm, abs=2e-6)


def test_min_zone_of_an_exact_plane_is_zero():
    rng = np.random.default_rng(17)
    p = sample_plane([1, 1, 1], 2.0, 100, rng)
    assert min_zone_flatness(p) < 1e-9


# ---------------------------------------------------------------------------- real data


@pytest.mark.real_data
def test_pcl_sac_plane_reference():
    path = REAL / "pcl_plane" / "sac_plane_test.pcd"
    if not path.is_file():
        pytest.skip(f"real data not found at {path} (set SCANNER_REAL_DATA)")
    import open3d as o3d

    points_m = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    assert len(points_m) == 3283
    fit = fit_plane(points_m, threshold_mm=0.01, seed=0)  # the file is in metres: 1 cm
    assert fit, fit.reason
    coeffs = fit.normal / fit.d_mm
    assert np.allclose(coeffs, [-0.8964, -0.5868, -1.2080], atol=0.1), coeffs
    assert fit.n_inliers > 2000


def test_json_of_a_minimal_fit_has_no_nan():
    import json

    fit = fit_plane([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # no dof left
    assert fit
    data = json.loads(json.dumps(fit.to_json(), allow_nan=False))
    assert data["d_std_mm"] is None and data["n_inliers"] == 3


def test_inlier_band_follows_noise_wider_than_the_threshold():
    """A threshold below the noise must not clip the residuals (the form would read 2 t)."""
    rng = np.random.default_rng(18)
    noisy = sample_plane([0, 0, 1], 0.0, 5000, rng, noise_mm=0.2)
    clutter = rng.uniform(-50, 50, (500, 3)) + np.array([0.0, 0.0, 60.0])
    fit = fit_plane(np.vstack([noisy, clutter]), threshold_mm=0.3)
    assert fit.inliers[:5000].mean() > 0.999
    assert not fit.inliers[5000:].any()
    assert fit.rms_mm == pytest.approx(0.2, rel=0.05)
    assert fit.range_mm > 1.0  # about 7 sigma, not 0.6
    sphere = fit_sphere(sample_sphere([0, 0, 0], 12.7, 3000, rng, noise_mm=0.15, cap=True), 0.2)
    assert sphere.n_inliers > 2990 and sphere.range_mm > 0.8
