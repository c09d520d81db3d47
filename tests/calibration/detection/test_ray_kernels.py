"""The compiled ray labelling against a plain per-ray reference, and on a drawn target; the
tile thresholds against numpy's statistics."""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

from calibration.detection.ray_kernels import (
    CENSORED_SPREAD,
    FIT_TOL_FRACTION,
    FIT_TOL_PX,
    _fit_labels,
    label_rays,
    tile_thresholds,
)


def _reference(d: np.ndarray, c: np.ndarray, angle: float, radii: np.ndarray, thr: float):
    """One ray the slow, obvious way: the whole profile, run maxima (not the run at the
    start), the first ones fitted with lstsq."""
    h, w = d.shape
    t = np.arange(1.0, float(np.hypot(w, h)))
    u, v = c[0] + t * np.cos(angle), c[1] + t * np.sin(angle)
    profile = ndimage.map_coordinates(d, [v, u], order=1, mode="constant")
    profile[~((u >= 1) & (u <= w - 2) & (v >= 1) & (v <= h - 2))] = 0.0
    above = profile > thr
    edges = np.flatnonzero(np.diff(np.concatenate([[0], above.astype(np.int8), [0]])))
    peaks = [int(s + np.argmax(profile[s:e])) for s, e in zip(edges[::2], edges[1::2]) if s > 0]
    m = min(len(peaks), len(radii))
    tp = []
    for j in peaks[:m]:
        y0, y1, y2 = profile[j - 1 : j + 2] if 0 < j < len(t) - 1 else (0.0, 1.0, 0.0)
        tp.append(t[j] + (0.5 * (y0 - y2) / (y0 - 2 * y1 + y2) if y0 - 2 * y1 + y2 < 0 else 0.0))
    tp = np.asarray(tp)
    if m < 3:
        return m, tp, np.inf
    r = radii[:m]
    (a, b), *_ = np.linalg.lstsq(np.column_stack([r, -r * tp]), tp, rcond=None)
    den = 1 + b * r
    if np.any(den <= 0.05) or a <= 0:
        return m, tp, np.inf
    return m, tp, float(np.max(np.abs(a * r / den - tp)))


def _rings_image(rng: np.random.Generator, radii_px: np.ndarray, centre: tuple[int, int]):
    """A darkness map: ellipses around ``centre`` (a tilted target), noise and clutter."""
    d = np.zeros((300, 400))
    for r in radii_px:
        axes = (int(r), int(0.8 * r))
        cv2.ellipse(d, centre, axes, 20.0, 0.0, 360.0, 1.0, 2)
    cv2.line(d, (0, centre[1]), (399, centre[1] + 40), 1.0, 2)  # through the centre
    cv2.circle(d, (350, 40), 12, 0.8, -1)  # clutter
    # (a darkness is never negative: negative marks hidden print)
    return np.maximum(cv2.GaussianBlur(d, (0, 0), 1.0) + rng.normal(0.0, 0.05, d.shape), 0.0)


def test_each_ray_is_labelled_as_the_per_ray_reference_labels_it():
    rng = np.random.default_rng(3)
    radii = np.array([10.0, 20.0, 30.0, 40.0, 55.0])
    centre = np.array([190.0, 160.0])
    d = _rings_image(rng, 2.2 * radii, (190, 160))
    angles = np.linspace(0, 2 * np.pi, 96, endpoint=False) + 0.013
    count, peaks, err = label_rays(d, centre, angles, radii, 0.3)
    fitted = 0
    for i, ang in enumerate(angles):
        m, tp, e = _reference(d, centre, ang, radii, 0.3)
        assert count[i] == m
        np.testing.assert_allclose(peaks[i, :m], tp, atol=1e-9)
        assert np.all(np.isnan(peaks[i, m:]))
        if np.isfinite(e):
            fitted += 1
            assert abs(err[i] - e) < 1e-6 * max(1.0, e)
        else:
            assert not np.isfinite(err[i])
    assert fitted > 48  # most rays cross the rings cleanly


def test_rays_from_the_centre_of_a_target_fit_its_radii_and_others_do_not():
    rng = np.random.default_rng(4)
    radii = np.array([10.0, 20.0, 30.0, 40.0])
    d = _rings_image(rng, 2.2 * radii, (190, 160))
    angles = np.linspace(0, 2 * np.pi, 96, endpoint=False) + 0.013
    count, _, err = label_rays(d, np.array([190.0, 160.0]), angles, radii, 0.3)
    good = (count == 4) & (err < 2.0)
    assert good.sum() > 60
    # from a point off the centre the crossings are not a projectivity of these radii
    count, _, err = label_rays(d, np.array([230.0, 130.0]), angles, radii, 0.3)
    assert ((count >= 3) & (err < 2.0)).sum() < 15
    # a centre in a blank image: no crossings
    count, _, err = label_rays(np.zeros((50, 60)), np.array([30.0, 20.0]), angles, radii, 0.3)
    assert np.all(count == 0) and np.all(np.isinf(err))


def test_a_ray_ends_where_the_print_is_hidden_and_starts_where_it_leaves_it():
    rng = np.random.default_rng(5)
    radii = np.array([10.0, 20.0, 30.0, 40.0])
    d = _rings_image(rng, 2.2 * radii, (190, 160))
    angles = np.array([0.3, np.pi + 0.3])
    centre = np.array([190.0, 160.0])
    count, peaks, _ = label_rays(d, centre, angles, radii, 0.3)
    assert np.all(count == 4)
    # a stripe (hidden) across the rays between the second and third ring: two crossings left
    hidden = d.copy()
    t_mid = 0.5 * (peaks[0, 1] + peaks[0, 2])
    u, v = centre + t_mid * np.array([np.cos(0.3), np.sin(0.3)])
    cv2.circle(hidden, (int(u), int(v)), 4, -1.0, -1)
    count_h, peaks_h, err_h = label_rays(hidden, centre, angles[:1], radii, 0.3)
    assert count_h[0] == 2 and np.isinf(err_h[0])
    np.testing.assert_allclose(peaks_h[0, :2], peaks[0, :2])
    # a centre under a small hidden spot: the rays start beyond it and keep their labels
    spot = d.copy()
    cv2.circle(spot, (190, 160), 3, -1.0, -1)
    count_s, peaks_s, _ = label_rays(spot, centre, angles, radii, 0.3)
    assert np.all(count_s == 4)
    np.testing.assert_allclose(peaks_s, peaks)
    # ... but not when the spot reaches past half the first ring's distance
    cv2.circle(spot, (190, 160), int(0.7 * peaks[0, 0]), -1.0, -1)
    count_s, _, _ = label_rays(spot, centre, angles, radii, 0.3)
    assert np.all(count_s == 0)


def test_rays_in_bundles_find_a_faint_print_single_rays_miss():
    # A darkness map in the detector's units (threshold 1 at 6 MAD of the paper: noise 0.25)
    # whose printed lines peak just under the threshold: single rays miss crossings of nearly
    # every ray; the median of a bundle of five parallel rays 2 px apart, at the bundle's
    # threshold, labels most rays, near the diameters too.
    rng = np.random.default_rng(6)
    radii = np.array([10.0, 20.0, 30.0, 40.0, 55.0])
    centre = np.array([190.0, 160.0])
    clean = np.zeros((300, 400))
    for r in 2.2 * radii:
        cv2.ellipse(clean, (190, 160), (int(r), int(0.8 * r)), 20.0, 0.0, 360.0, 1.0, 2)
    axes_deg = np.array([20.0, 110.0])
    for a in np.radians(axes_deg):
        ends = centre + 150 * np.array([[np.cos(a), np.sin(a)], [-np.cos(a), -np.sin(a)]])
        cv2.line(clean, tuple(ends[0].astype(int)), tuple(ends[1].astype(int)), 1.0, 2)
    clean = cv2.GaussianBlur(clean, (0, 0), 1.0)
    clean *= 0.9 / np.median(clean[clean > 0.5 * clean.max()])  # a line's peak: 0.9
    noise = cv2.GaussianBlur(rng.normal(0.0, 1.0, clean.shape), (0, 0), 0.7)
    faint = np.maximum(clean + 0.25 * noise / noise.std(), 0.0)
    angles = np.linspace(0, 2 * np.pi, 96, endpoint=False) + 0.013
    off_axes = np.abs((np.degrees(angles)[:, None] - axes_deg + 90) % 180 - 90).min(axis=1)
    rays = off_axes > 6  # as the detector's rays

    def labelled(d: np.ndarray, thr: float, step_px: float) -> tuple[np.ndarray, np.ndarray]:
        count, peaks, err = label_rays(
            d, centre, angles, radii, thr, FIT_TOL_PX, FIT_TOL_FRACTION, False, step_px
        )
        tol = FIT_TOL_PX + FIT_TOL_FRACTION * np.nanmax(np.nan_to_num(peaks), axis=1)
        return (count == len(radii)) & (err <= tol), peaks

    single, _ = labelled(faint, 1.0, 0.0)
    bundled, peaks = labelled(faint, 0.7, 2.0)
    assert single[rays].mean() < 0.1
    assert bundled[rays].mean() > 0.6
    assert bundled[rays & (off_axes < 15)].mean() > 0.6  # side rays over a diameter
    # a bundle crosses each ring where a single ray does without the noise
    clean_single, clean_peaks = labelled(clean, 0.7, 0.0)
    assert clean_single[rays].mean() > 0.9
    offsets = (peaks - clean_peaks)[bundled & clean_single & rays]
    assert np.median(np.abs(offsets)) < 0.3
    assert np.max(np.abs(offsets)) < 2.0  # (1.2-1.8 px over seeds 6-9)
    # and without noise a bundle moves a crossing little
    clean_bundled, bundled_peaks = labelled(clean, 0.7, 2.0)
    both = clean_bundled & clean_single & rays
    assert both.mean() > 0.9 * rays.mean()
    assert np.max(np.abs(bundled_peaks - clean_peaks)[both]) < 0.6  # a tilted ring across it


def _rays_fitting_from_ring_1(radii: np.ndarray, peaks: np.ndarray, ring0_within_px: float) -> int:
    """How many rays' first three crossings (``peaks``, rings from 0) also fit rings 1-3 with
    ring 0 predicted within ``ring0_within_px`` of the centre (the premise of the ambiguity
    tests)."""
    fits = 0
    for row in peaks:
        a, b, worst = _fit_labels(radii, row, 1, 3)
        fits += (
            worst <= FIT_TOL_PX + FIT_TOL_FRACTION * row[2]
            and a * radii[0] / (1 + b * radii[0]) < ring0_within_px
        )
    return fits


def test_a_ring_merged_with_the_centre_is_skipped_only_when_asked():
    # A small, steep target: the innermost ring's image (4.4 px) merges with the diameters'
    # crossing at O into one dark run from the centre. By default the first crossing seen is
    # named ring 0 and the fit refuses the ray; with ``ring0_hidden`` the crossings are
    # rings 1-3 and column 0 stays empty.
    rng = np.random.default_rng(6)
    radii = np.array([2.0, 10.0, 20.0, 30.0])
    d = np.zeros((300, 400))
    cv2.circle(d, (190, 160), 5, 1.0, -1)
    for r in 2.2 * radii[1:]:
        cv2.circle(d, (190, 160), int(r + 0.5), 1.0, 2)
    d = np.maximum(cv2.GaussianBlur(d, (0, 0), 1.0) + rng.normal(0.0, 0.05, d.shape), 0.0)
    centre = np.array([190.0, 160.0])
    angles = np.linspace(0, 2 * np.pi, 48, endpoint=False) + 0.013
    count, _, err = label_rays(d, centre, angles, radii, 0.3)
    assert np.all((count < 3) | (err > FIT_TOL_PX + FIT_TOL_FRACTION * 66.0))
    count, peaks, err = label_rays(d, centre, angles, radii, 0.3, ring0_hidden=True)
    labelled = (count == 3) & (err < 1.5)
    assert labelled.sum() > 40
    assert np.all(np.isnan(peaks[labelled, 0]))
    np.testing.assert_allclose(
        peaks[labelled, 1:], np.tile([22.0, 44.0, 66.0], (labelled.sum(), 1)), atol=1.0
    )


def test_a_hidden_start_does_not_let_a_ray_that_fits_from_ring_0_be_labelled_from_ring_1():
    # A stripe over the centre hides the rays' first 9 px; the crossings at 16, 32, 48 px fit
    # rings 0-2 exactly, and rings 1-3 within the tolerance with ring 0 under the stripe.
    # Which one is true cannot be told: the ray is not labelled (it was, from ring 1, in a
    # first version of the ring-1 labelling).
    rng = np.random.default_rng(8)
    radii = np.array([10.0, 20.0, 30.0, 40.0, 55.0])
    d = np.zeros((300, 400))
    for r in (16, 32, 48):
        cv2.circle(d, (190, 160), r, 1.0, 2)
    d = np.maximum(cv2.GaussianBlur(d, (0, 0), 1.0) + rng.normal(0.0, 0.02, d.shape), 0.0)
    cv2.circle(d, (190, 160), 9, -1.0, -1)
    centre = np.array([190.0, 160.0])
    angles = np.linspace(0, 2 * np.pi, 48, endpoint=False) + 0.013
    count, _, err = label_rays(d, centre, angles, radii, 0.3)
    assert np.all(count == 0)  # the hidden start may hide ring 0
    count, _, _ = label_rays(d, centre, angles, radii, 0.3, ring0_hidden=True)
    assert np.all(count == 0)
    # (the premise: rings 1-3 fit the crossings too, with ring 0 under the stripe)
    d_seen = np.where(d < 0, 0.0, d)
    _, peaks_seen, _ = label_rays(d_seen, centre, angles, radii, 0.3)
    assert _rays_fitting_from_ring_1(radii, peaks_seen, 10.5) > 40
    # with the centre in view the same crossings are rings 0-2
    d[d < 0] = 0.0
    count, peaks, err = label_rays(d, centre, angles, radii, 0.3)
    assert np.all(count == 3) and np.all(err < 1.0)
    np.testing.assert_allclose(peaks[:, :3], np.tile([16.0, 32.0, 48.0], (48, 1)), atol=1.0)


def test_clutter_beyond_the_outer_ring_does_not_let_a_ray_be_labelled_from_ring_1():
    # All four rings' worth of crossings: 16, 32, 48 px (rings 0-2 exactly, or rings 1-3
    # within the tolerance with ring 0 in the dark run at the centre) and clutter at 90 px.
    # From ring 0 the clutter spoils the fit of all four; ring 1's fit leaves it out. The
    # ray is ambiguous all the same: the first three fit from ring 0.
    rng = np.random.default_rng(9)
    radii = np.array([10.0, 20.0, 30.0, 40.0])
    d = np.zeros((300, 400))
    cv2.circle(d, (190, 160), 7, 1.0, -1)
    for r in (16, 32, 48, 90):
        cv2.circle(d, (190, 160), r, 1.0, 2)
    d = np.maximum(cv2.GaussianBlur(d, (0, 0), 1.0) + rng.normal(0.0, 0.02, d.shape), 0.0)
    centre = np.array([190.0, 160.0])
    angles = np.linspace(0, 2 * np.pi, 48, endpoint=False) + 0.013
    count, peaks, err = label_rays(d, centre, angles, radii, 0.3)
    assert np.all(count == 4) and np.all(err > FIT_TOL_PX + FIT_TOL_FRACTION * 90.0)
    # (the premise: rings 1-3 fit the first three crossings, ring 0 inside the dark run)
    assert _rays_fitting_from_ring_1(radii, peaks, 9.5) > 40
    count, _, _ = label_rays(d, centre, angles, radii, 0.3, ring0_hidden=True)
    assert np.all(count == 0)


def test_asking_for_a_hidden_ring_0_leaves_rays_that_see_it_as_they_were():
    rng = np.random.default_rng(7)
    radii = np.array([10.0, 20.0, 30.0, 40.0, 55.0])
    centre = np.array([190.0, 160.0])
    d = _rings_image(rng, 2.2 * radii, (190, 160))
    angles = np.linspace(0, 2 * np.pi, 96, endpoint=False) + 0.013
    count, peaks, err = label_rays(d, centre, angles, radii, 0.3)
    last = np.max(np.nan_to_num(peaks), axis=1)
    fits = (count >= 3) & (err <= FIT_TOL_PX + FIT_TOL_FRACTION * last)
    assert fits.sum() > 48
    count_h, peaks_h, err_h = label_rays(d, centre, angles, radii, 0.3, ring0_hidden=True)
    np.testing.assert_array_equal(count_h[fits], count[fits])
    np.testing.assert_array_equal(peaks_h[fits], peaks[fits])
    np.testing.assert_array_equal(err_h[fits], err[fits])
    # no ray is labelled from ring 1 here: ring 0 is seen 22 px out, beyond the blind start
    assert not np.any(np.isnan(peaks_h[:, 0]) & np.isfinite(peaks_h[:, 1]))


def test_tile_thresholds_give_numpys_statistics_with_nans_and_empty_tiles():
    rng = np.random.default_rng(11)
    blocks = rng.normal(0.05, 0.01, (3, 4, 301))
    blocks[..., :90] += rng.uniform(0.1, 0.5, (3, 4, 90))  # printed lines: dark outliers
    blocks[rng.random(blocks.shape) < 0.2] = np.nan
    blocks[2, 3] = np.nan  # a tile with no lit pixel
    p5, p25 = np.nanpercentile(blocks[:2], [5.0, 25.0], axis=2)
    sig = (p25 - p5) / 0.97
    kept = np.where(blocks[:2] > (p25 + 0.674 * sig + 4.0 * sig)[:, :, None], np.nan, blocks[:2])
    med = np.nanmedian(kept, axis=2)
    mad = 1.4826 * np.nanmedian(np.abs(kept - med[:, :, None]), axis=2)
    got = tile_thresholds(blocks)
    np.testing.assert_allclose(got[:2], med + 6.0 * mad, rtol=1e-12)
    assert np.isnan(got[2, 3])
    # against the truth: the paper's noise level, the lines clipped out
    assert np.all(np.abs(got[:2] - (0.05 + 6 * 0.01)) < 0.015)


def test_a_tile_whose_low_quantiles_are_censored_at_zero_learns_no_threshold():
    # A closing that follows the noise leaves a third of the paper's darkness exactly 0: the
    # 5th and 25th percentiles are both 0, the spread they give is nothing, and every
    # positive sample was clipped as a printed line (the tile learnt a threshold of 0). Such a
    # tile is left to its caller (NaN); a tile with a few zeros still learns its own.
    rng = np.random.default_rng(4)
    noise = np.abs(rng.normal(0.0, 0.04, (1, 3, 400)))
    blocks = noise.copy()
    blocks[0, 0, rng.random(400) < 0.35] = 0.0  # censored
    blocks[0, 1, :12] = 0.0  # 3 % zeros
    blocks[0, 2, :] = 0.0  # no noise at all
    got = tile_thresholds(blocks)
    assert np.isnan(got[0, 0]) and np.isnan(got[0, 2])
    p5, p25 = np.percentile(blocks[0, 1], [5.0, 25.0])
    assert p25 - p5 > CENSORED_SPREAD
    assert np.mean(noise[0, 1] > got[0, 1]) < 0.01
