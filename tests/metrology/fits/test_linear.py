from __future__ import annotations

import numpy as np
import pytest

from metrology.fits import fit_circle, fit_cylinder, fit_plane, fit_sphere
from metrology.fits.linear import linearise

UM = 1e-3  # one micrometre in mm


def _cap(rng: np.random.Generator, n: int, radius: float, noise: float) -> np.ndarray:
    """Points on the upper 60 deg cap of a sphere at (500, 60, 40): what a sweep sees."""
    polar = np.arccos(rng.uniform(np.cos(np.radians(60)), 1.0, n))
    azim = rng.uniform(0, 2 * np.pi, n)
    d = np.column_stack([np.sin(polar) * np.cos(azim), np.sin(polar) * np.sin(azim), np.cos(polar)])
    return np.array([500.0, 60.0, 40.0]) + d * (radius + rng.normal(0, noise, n))[:, None]


def _tilted_plane(rng: np.random.Generator, n: int, noise: float) -> np.ndarray:
    uv = rng.uniform(-40, 40, (n, 2))
    z = 0.01 * uv[:, 0] - 0.02 * uv[:, 1] + rng.normal(0, noise, n)
    return np.column_stack([uv[:, 0] + 600.0, uv[:, 1] - 30.0, z + 5.0])


def _half_cylinder(rng: np.random.Generator, n: int, radius: float, noise: float) -> np.ndarray:
    along = rng.uniform(-40, 40, n)
    angle = rng.uniform(0, np.pi, n)  # the upper half: what one sweep sees of a bar
    r = radius + rng.normal(0, noise, n)
    local = np.column_stack([along, r * np.cos(angle), r * np.sin(angle)])
    c, s = np.cos(0.3), np.sin(0.3)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return local @ rot.T + np.array([520.0, 10.0, 30.0])


CASES = {
    "sphere": (lambda rng: _cap(rng, 3000, 12.7, 0.02), fit_sphere, ("center_mm", "radius_mm")),
    "plane": (lambda rng: _tilted_plane(rng, 5000, 0.02), fit_plane, ("normal", "d_mm")),
    "cylinder": (
        lambda rng: _half_cylinder(rng, 4000, 4.0, 0.02),
        fit_cylinder,
        ("axis", "radius_mm"),
    ),
}


@pytest.mark.parametrize("kind", sorted(CASES))
@pytest.mark.parametrize("move", ["flip residuals", "rigid shift", "smooth warp"])
def test_the_linearised_fit_agrees_with_a_refit(kind, move):
    make, fit, fields = CASES[kind]
    rng = np.random.default_rng(7)
    points = make(rng)
    ref = fit(points)
    lin = linearise(ref, points)
    assert lin is not None
    if move == "flip residuals":  # the bootstrap's move: half the points across the surface
        sign = rng.choice([-1.0, 1.0], len(points))
        moved = points + ((sign - 1.0) * lin.residuals)[:, None] * lin.normals
    elif move == "rigid shift":
        moved = points + np.array([0.02, -0.03, 0.015])
    else:  # a calibration's sigma: a smooth warp of tens of micrometres
        moved = points + 1e-3 * np.column_stack(
            [np.sin(points[:, 1] / 20.0), points[:, 0] / 50.0 - 10.0, np.cos(points[:, 0] / 15.0)]
        )
    refit = fit(moved)
    approx = lin.moved(moved)
    # first order: the error is a small part of the change (or below 0.1 um / 1e-7 rad)
    for name in fields:
        if name in ("axis", "normal"):
            change = np.linalg.norm(np.cross(getattr(refit, name), getattr(ref, name)))
            error = np.linalg.norm(np.cross(getattr(approx, name), getattr(refit, name)))
            assert error < max(0.02 * change, 1e-7), f"{kind} {name}: {change}, {error}"
        else:
            change = np.atleast_1d(getattr(refit, name) - getattr(ref, name))
            error = np.atleast_1d(getattr(approx, name) - getattr(refit, name))
            assert np.abs(error).max() < max(0.02 * np.abs(change).max(), 0.1 * UM), (
                f"{kind} {name}: change {change}, error {error}"
            )
    if kind == "cylinder":  # the axis line itself, and its point where a fit puts it
        shift = _off_axis(refit.point_mm, ref)
        assert _off_axis(approx.point_mm, refit) < max(0.02 * shift, 0.1 * UM)
        assert np.linalg.norm(approx.point_mm - refit.point_mm) < 1.0 * UM
    for name in ("range_mm", "rms_mm"):
        change = abs(getattr(refit, name) - getattr(ref, name))
        error = abs(getattr(approx, name) - getattr(refit, name))
        assert error < max(0.02 * change, 0.1 * UM), f"{kind} {name}: {change}, {error}"
    if move == "flip residuals":  # the bootstrap's path: the residuals' changes alone
        along = np.einsum("ij,ij->i", lin.normals, moved - points)
        again = lin.shifted(along)
        for name in (*fields, "range_mm", "rms_mm"):
            assert np.allclose(getattr(again, name), getattr(approx, name), rtol=0, atol=1e-12)


def _off_axis(point: np.ndarray, cylinder) -> float:
    """Distance of ``point`` from ``cylinder``'s axis line."""
    q = point - cylinder.point_mm
    return float(np.linalg.norm(q - (q @ cylinder.axis) * cylinder.axis))


def test_a_plane_keeps_its_distances_where_the_points_are():
    rng = np.random.default_rng(3)
    points = _tilted_plane(rng, 2000, 0.01)
    ref = fit_plane(points)
    lin = linearise(ref, points)
    moved = points + np.array([0.0, 0.0, 0.05])  # the plane lifted by 50 um
    approx = lin.moved(moved)
    assert np.allclose(approx.signed_distance(moved), ref.signed_distance(points), atol=1e-9)
    assert np.allclose(approx.centroid_mm, moved.mean(axis=0))


def test_kinds_without_a_linearisation_and_wrong_shapes_are_refused():
    rng = np.random.default_rng(0)
    t = rng.uniform(0, 2 * np.pi, 200)
    circle = fit_circle(np.column_stack([10 * np.cos(t), 10 * np.sin(t), np.zeros(200)]))
    assert circle
    assert linearise(circle, np.zeros((200, 3))) is None
    points = _cap(rng, 500, 12.7, 0.01)
    lin = linearise(fit_sphere(points), points)
    with pytest.raises(ValueError, match=r"expected shape \(500, 3\), got \(499, 3\)"):
        lin.moved(points[:-1])


@pytest.mark.parametrize("kind", sorted(CASES))
def test_group_flips_give_what_the_moved_residuals_give(kind):
    make, fit, fields = CASES[kind]
    rng = np.random.default_rng(11)
    points = make(rng)
    lin = linearise(fit(points), points)
    group = rng.integers(5, 45, len(points))  # 40 stops, ids not from 0
    flips = lin.groups(group)
    for scale in (1.0, 1.1):
        sign = rng.choice([-1.0, 1.0], 60)
        exact = lin.shifted((scale * sign[group] - 1.0) * lin.residuals)
        fast = flips.flipped(sign, scale)
        for name in (*fields, "rms_mm", "range_mm"):
            assert np.allclose(getattr(fast, name), getattr(exact, name), rtol=1e-9, atol=1e-9), (
                name
            )
        if kind == "plane":
            assert np.allclose(fast.centroid_mm, exact.centroid_mm, rtol=0, atol=1e-9)
