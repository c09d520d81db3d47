"""The fine stage's profile kernels: the compiled spline sampler against SciPy's, the line
centres against drawn lines, the lazily sampled centres against the whole profiles' to the
bit, the windows' mask test against the plain way."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from calibration.detection.profile_kernels import (
    line_centres,
    profile_line_centres,
    spline_along,
    window_touches,
)


@pytest.mark.parametrize("shape", [(60, 80), (5, 7), (1, 9)])
def test_spline_along_gives_scipys_values_inside_at_the_edges_and_outside(shape):
    rng = np.random.default_rng(31)
    coef = ndimage.spline_filter(rng.random(shape), order=3)
    h, w = shape
    v = rng.uniform(-3, h + 2, 4998)
    u = rng.uniform(-3, w + 2, 4998)
    # The edges exactly, just inside and just outside, and NaN.
    v = np.concatenate([v, [0.0, h - 1.0, -1e-12, h - 1 + 1e-12, 0.5 * h, 0.5 * h, np.nan]])
    u = np.concatenate([u, [0.5 * w, 0.5 * w, 1.0, 1.0, 0.0, w - 1.0, 1.0]])
    want = ndimage.map_coordinates(coef, [v, u], order=3, prefilter=False, cval=0.0)
    # each point as a line of one sample, at the point itself
    got = spline_along(coef, np.column_stack([u, v]), np.zeros((len(u), 2)), np.zeros(1))
    assert got.shape == (len(v), 1)
    np.testing.assert_allclose(got[:, 0], want, rtol=0, atol=1e-12)
    assert np.count_nonzero(want != 0.0) > 1000 or h < 10  # not all outside


def test_spline_along_samples_each_line_at_its_positions():
    rng = np.random.default_rng(32)
    coef = ndimage.spline_filter(rng.random((50, 70)), order=3)
    points = rng.uniform(-5, 75, (300, 2))
    angle = rng.uniform(0, 2 * np.pi, 300)
    normals = np.column_stack([np.cos(angle), np.sin(angle)])
    tau = np.arange(-6.0, 6.0 + 0.0625, 0.125)
    u = points[:, 0:1] + normals[:, 0:1] * tau[None, :]
    v = points[:, 1:2] + normals[:, 1:2] * tau[None, :]
    got = spline_along(coef, points, normals, tau)
    assert got.shape == (300, len(tau))
    want = ndimage.map_coordinates(coef, [v, u], order=3, prefilter=False, cval=0.0)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)  # 0 outside included
    assert np.count_nonzero(got == 0.0) > 100 and np.count_nonzero(got) > 10_000
    with pytest.raises(ValueError, match="expected shapes"):
        spline_along(coef, points, normals[:-1], tau)


@pytest.mark.parametrize("dtype", [np.uint8, bool, np.float64])
def test_window_touches_finds_a_mask_pixel_within_the_window_only(dtype):
    rng = np.random.default_rng(33)
    h, w = 40, 60
    mask = (rng.random((h, w)) > 0.97).astype(dtype)
    points = rng.uniform(-3, 63, (500, 2))
    angle = rng.uniform(0, 2 * np.pi, 500)
    normals = np.column_stack([np.cos(angle), np.sin(angle)])
    tau = np.arange(-8.0, 8.0 + 0.0625, 0.125)
    centre = rng.uniform(-4, 4, 500)
    centre[:5] = np.nan
    reach = 2.5
    # The plain way: every sample, nearest pixel, within the reach of the centre.
    u = np.rint(points[:, 0:1] + normals[:, 0:1] * tau[None, :]).astype(int)
    v = np.rint(points[:, 1:2] + normals[:, 1:2] * tau[None, :]).astype(int)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    on = inside & (mask[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)] > 0)
    near = np.abs(tau[None, :] - centre[:, None]) <= reach
    want = (on & near).any(axis=1)
    got = window_touches(mask, points, normals, tau, centre, reach)
    np.testing.assert_array_equal(got, want)
    assert 50 < got.sum() < 450  # neither all nor none
    assert not got[:5].any()  # no centre: meets nothing
    with pytest.raises(ValueError, match="expected shapes"):
        window_touches(mask, points, normals, tau, centre[:-1], reach)


def test_line_centres_find_a_drawn_line_and_its_depth():
    rng = np.random.default_rng(3)
    tau = np.arange(-8.0, 8.0 + 0.125, 0.25)
    true_c = rng.uniform(-3.0, 3.0, 200)
    width = rng.uniform(0.8, 2.0, 200)
    depth = rng.uniform(0.2, 0.9, 200)
    paper = rng.uniform(0.0, 0.05, 200)
    prof = paper[:, None] + depth[:, None] * np.exp(
        -0.5 * ((tau[None, :] - true_c[:, None]) / width[:, None]) ** 2
    )
    centre, contrast = line_centres(prof, tau, half_window=3.0 * 2.0, search=4.0)
    assert np.abs(centre - true_c).max() < 0.01
    # the window ends lie 3 widths out or beyond: the contrast is nearly the whole depth
    assert np.all(contrast > 0.85 * depth) and np.all(contrast <= depth + 1e-12)


def test_line_centres_take_the_line_within_the_search_not_a_darker_one_beyond():
    tau = np.arange(-8.0, 8.0 + 0.125, 0.25)
    near = 0.3 * np.exp(-0.5 * ((tau + 0.7) / 0.8) ** 2)  # the line sought, 0.7 px off
    far = 0.9 * np.exp(-0.5 * ((tau - 6.0) / 0.8) ** 2)  # a darker neighbour beyond
    centre, contrast = line_centres((near + far)[None, :], tau, half_window=2.5, search=3.0)
    assert abs(centre[0] + 0.7) < 0.01
    assert abs(contrast[0] - 0.3) < 0.03
    with pytest.raises(ValueError, match="expected shapes"):
        line_centres(near[None, :], tau[:-1], 2.0, 2.0)


def _lined_coefficients(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """The spline of a darkness map with dark lines across it, blur and noise."""
    h, w = shape
    v, u = np.mgrid[0:h, 0:w].astype(float)
    d = rng.normal(0.0, 0.03, shape)
    for _ in range(6):
        a = rng.uniform(0, np.pi)
        rho = rng.uniform(0, 0.5 * (h + w))
        d += rng.uniform(0.2, 1.0) * np.exp(
            -0.5 * ((u * np.cos(a) + v * np.sin(a) - rho) / rng.uniform(0.6, 2.0)) ** 2
        )
    return ndimage.spline_filter(d, order=3)


@pytest.mark.parametrize("seed", range(6))
def test_profile_line_centres_are_the_whole_profiles_centres_to_the_bit(seed):
    rng = np.random.default_rng([35, seed])
    shape = [(80, 120), (40, 30), (9, 200), (120, 90), (60, 60), (5, 8)][seed]
    coef = _lined_coefficients(rng, shape)
    n = 400
    # Points inside, near the edges (the spline folds) and outside (its zeros).
    points = rng.uniform(-8, 8, (n, 2)) + rng.uniform(0, 1, (n, 2)) * shape[::-1]
    angle = rng.uniform(0, 2 * np.pi, n)
    normals = np.column_stack([np.cos(angle), np.sin(angle)])
    half_window = rng.uniform(0.8, 6.0)
    search = rng.uniform(1.0, 3.0 * half_window)
    step = [0.125, 0.25, 0.1][seed % 3]
    span = search + half_window + 1.0
    tau = np.arange(-span, span + step / 2, step)
    origin = (int(rng.integers(0, 50)), int(rng.integers(0, 50)))
    points_img = points + origin
    whole = spline_along(coef, points_img, normals, tau, origin)
    want = line_centres(whole, tau, half_window, search)
    got = profile_line_centres(coef, points_img, normals, tau, half_window, search, origin)
    for g, w in zip(got, want):
        assert g.shape == (n,)
        np.testing.assert_array_equal(g.view(np.int64), w.view(np.int64))  # bit for bit
    # Lines were found (the centres moved off the grid) and some profiles left the spline.
    assert np.count_nonzero(got[0] % step) > n // 4
    assert np.count_nonzero(whole == 0.0) > 0


def test_profile_line_centres_refuse_mismatched_shapes():
    coef = np.zeros((10, 10))
    tau = np.arange(-3.0, 3.0, 0.5)
    with pytest.raises(ValueError, match="expected shapes"):
        profile_line_centres(coef, np.zeros((4, 2)), np.zeros((3, 2)), tau, 1.0, 1.0)
    with pytest.raises(ValueError, match="at least 2 positions, got 1"):
        profile_line_centres(coef, np.zeros((4, 2)), np.zeros((4, 2)), tau[:1], 1.0, 1.0)
