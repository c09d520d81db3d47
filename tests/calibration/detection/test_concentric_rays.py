"""The coarse stage's darkness and its threshold: learnt from the paper's own noise."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.detection.concentric_rays import (
    BrightMasks,
    _bright_mask,
    _darkness,
    _grey_morphology,
    _lit_level,
    _threshold_map,
    starts_hidden,
)


def test_a_laser_stripe_filling_tiles_does_not_lower_their_threshold() -> None:
    # Over a stripe the darkness is 0 without noise (the closing follows a bright line):
    # a tile it fills would learn the floor, and the paper's noise beside it would pass.
    rng = np.random.default_rng(12)
    d = np.abs(rng.normal(0.0, 0.012, (400, 480)))
    bg = rng.uniform(0.9, 1.0, d.shape)  # lit paper (not clipped)
    hidden = np.zeros(d.shape, bool)
    hidden[150:260, :] = True
    d[hidden] = 0.0
    paper, _ = _threshold_map(d, bg, 48, hidden)
    # the paper's own level passes almost none of its noise
    assert np.mean(d[:140] > paper[:140]) < 0.01
    assert paper[50, 240] > 0.025
    # under the stripe the whole lit area's level (no paper of its own), not the floor of a
    # noise-free tile; beside it the paper's
    assert paper[205, 240] >= 0.8 * paper[50, 240]
    assert np.mean(d[262:300] > paper[262:300]) < 0.01
    blind, _ = _threshold_map(d, bg, 48)
    assert blind[205, 240] <= 0.021  # what it was without the hidden mask


def test_the_lit_level_is_the_papers_not_a_laser_stripes() -> None:
    # A stripe far brighter than the paper, in a frame that dark surroundings half fill: the
    # Otsu split put the stripe alone in the bright class, and the whole card below 30 % of
    # its level was taken for unlit surroundings (its printed lines then had no darkness).
    rng = np.random.default_rng(4)
    bg = np.full((300, 400), 0.2) + rng.normal(0, 0.003, (300, 400))
    bg[:, :150] = 0.02  # dark surroundings
    hidden = np.zeros(bg.shape, bool)
    hidden[:, 250:290] = True
    bg[hidden] = 1.0
    assert _lit_level(bg) > 0.9  # the stripe's
    assert abs(_lit_level(bg, hidden) - 0.2) < 0.01
    img = bg.copy()
    img[100:103, 160:240] *= 0.6  # a printed line on the card
    d, _, _ = _darkness(img, 9)
    assert d[101, 200] == 0.0  # taken for surroundings
    d, _, _ = _darkness(img, 9, hidden)
    assert abs(d[101, 200] - 0.4) < 0.03


def test_a_faint_print_on_quiet_paper_clears_its_threshold() -> None:
    # Issue #15: 20 grey levels of contrast under a 1 px line on paper at 200 give a darkness
    # of 0.01-0.03 after the blur; a fixed floor of 0.02 refused such views. The threshold is
    # the paper's own noise over a floor of one grey level.
    rng = np.random.default_rng(7)
    lit = 200.0 / 255.0
    d = np.abs(rng.normal(0.0, 0.002, (300, 400)))
    bg = np.full(d.shape, lit) + rng.uniform(-0.01, 0.0, d.shape)
    lines = np.zeros(d.shape, bool)
    lines[:, 50::40] = True
    d[lines] = 0.015
    thr, floor = _threshold_map(d, bg, 48)
    assert floor < 0.02
    assert np.all(d[lines] > thr[lines])
    assert np.mean(d[~lines] > thr[~lines]) < 0.01


def test_a_threshold_never_goes_below_one_grey_level() -> None:
    # Noise under the quantisation: the MAD is 0 and only the floor holds noise out.
    lit = 100.0 / 255.0
    bg = np.full((200, 200), lit) - np.linspace(0, 0.01, 200)[None, :]
    d = np.zeros(bg.shape)
    thr, floor = _threshold_map(d, bg, 48)
    assert floor == pytest.approx((1.0 / 255.0) / lit, rel=0.05)
    assert np.allclose(thr, floor)
    # on dim paper one grey level is more than the old fixed floor, and wins
    dim = bg * 0.15
    _, floor = _threshold_map(d, dim, 48)
    assert floor == pytest.approx((1.0 / 255.0) / (0.15 * lit), rel=0.05)
    assert floor > 0.02


def test_a_smaller_closing_keeps_the_first_scales_floor() -> None:
    # A closing that follows the noise leaves most of the paper's darkness at 0: its own
    # statistics would set no threshold at all.
    rng = np.random.default_rng(3)
    bg = np.full((200, 200), 0.8)
    d = np.where(rng.random(bg.shape) < 0.7, 0.0, np.abs(rng.normal(0, 0.004, bg.shape)))
    thr, floor = _threshold_map(d, bg, 48, floor=0.015)
    assert floor == 0.015
    assert thr.min() >= 0.015 * (1 - 1e-6)  # (a float32 map)
    assert np.mean(d > thr) < 0.01


def test_noisy_paper_a_third_of_whose_darkness_is_zero_keeps_its_noise_out() -> None:
    # Randomised view 21:39 (issue #15): paper at 8 grey levels of noise under a 5 px closing,
    # a third of its darkness exactly 0. Every tile's low quantiles were 0, each learnt the
    # floor (0.02), and a third of the paper passed it: rays from clutter crossed "lines" in
    # order everywhere and outranked the target's O. Such tiles take the whole paper's level.
    rng = np.random.default_rng(21)
    bg = np.full((240, 320), 0.4) - np.linspace(0, 0.01, 320)[None, :]
    d = np.where(rng.random(bg.shape) < 0.35, 0.0, np.abs(rng.normal(0, 0.04, bg.shape)))
    lines = np.zeros(d.shape, bool)
    lines[:, 40::60] = True
    d[lines] = 0.3
    thr, floor = _threshold_map(d, bg, 20, floor=0.02)
    assert floor == 0.02
    assert np.mean(d[~lines] > thr[~lines]) < 0.01  # (a third of it over the floor)
    assert np.all(d[lines] > thr[lines])


def test_dense_print_at_the_first_scale_keeps_the_floor() -> None:
    # Randomised view 18:57: 8 rings 6 px apart under the first (widest) closing, the paper
    # between the lines its own closing. Those tiles are censored too, but the whole area's
    # level, raised by the lines themselves, would lose them: at the first scale they keep
    # the floor; only a smaller scale's censored tiles (noise) take the whole level.
    rng = np.random.default_rng(57)
    bg = np.full((240, 320), 0.5) - np.linspace(0, 0.01, 320)[None, :]
    d = np.abs(rng.normal(0.02, 0.012, bg.shape))
    dense = np.zeros(bg.shape, bool)
    dense[:, :160] = True
    lines = dense & (np.arange(320)[None, :] % 6 < 2)
    d[dense] = 0.0
    d[lines] = 0.09
    thr, floor = _threshold_map(d, bg, 48)
    assert np.all(d[lines] > thr[lines])
    assert np.mean(d[~dense] > thr[~dense]) < 0.01
    smaller, _ = _threshold_map(d, bg, 48, floor=floor)
    assert np.mean(d[lines] > smaller[lines]) < 0.5


def test_a_first_scale_with_mostly_zero_darkness_learns_its_floor_from_the_rest() -> None:
    # A closing that follows the noise even at the first scale: over half of the paper's
    # darkness is exactly 0, its median and MAD are 0, and a floor of one grey level would
    # let the noise's tail through.
    rng = np.random.default_rng(5)
    bg = np.full((240, 320), 0.8) - np.linspace(0, 0.01, 320)[None, :]  # (lit, not clipped)
    d = np.where(rng.random(bg.shape) < 0.6, 0.0, np.abs(rng.normal(0, 0.002, bg.shape)))
    thr, floor = _threshold_map(d, bg, 48)
    assert 0.005 < floor < 0.02
    assert np.mean(d > thr) < 0.001


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint8, np.uint16])
def test_grey_morphology_is_opencvs_to_half_a_16_bit_level(dtype) -> None:
    rng = np.random.default_rng(34)
    scale = {np.uint8: 255, np.uint16: 65535}.get(dtype, 3.7)
    img = (rng.random((90, 120)) * scale).astype(dtype)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (9, 9))
    box = cv2.getStructuringElement(cv2.MORPH_RECT, (15, 15))
    got = _grey_morphology(img, (cv2.MORPH_CLOSE, disc), (cv2.MORPH_OPEN, box))
    want = cv2.morphologyEx(
        cv2.morphologyEx(img.astype(np.float32), cv2.MORPH_CLOSE, disc), cv2.MORPH_OPEN, box
    )
    assert got.dtype == np.float32 and got.shape == img.shape
    if dtype in (np.uint8, np.uint16):
        np.testing.assert_array_equal(got, want)  # integer images: exactly
    else:
        np.testing.assert_allclose(got, want, rtol=0, atol=float(np.ptp(img)) / 65535)
        # a pixel the morphology leaves as it is keeps its own value, exactly
        assert np.count_nonzero(got == img.astype(np.float32)) >= np.count_nonzero(want == img)
    assert np.ptp(got) > 0  # not flattened


@pytest.mark.parametrize("span", [0.0, 1e-38, 3e38])
def test_grey_morphology_of_a_range_without_levels_is_opencvs_in_float(span) -> None:
    # flat, narrower than float32 can split into 65535 levels, or wider than float32 holds
    rng = np.random.default_rng(37)
    img = ((rng.random((20, 30)) - 0.5) * 2.0 * span).astype(np.float32)  # +-span
    assert np.all(np.isfinite(img))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    want = cv2.morphologyEx(img, cv2.MORPH_CLOSE, disc)
    np.testing.assert_array_equal(_grey_morphology(img, (cv2.MORPH_CLOSE, disc)), want)


def test_bright_masks_find_a_stripe_and_are_made_once_per_element_size() -> None:
    # Paper with grain and printed rings' stand-ins (dark lines), a laser stripe 1.6 times as
    # bright across it.
    rng = np.random.default_rng(41)
    img = np.full((240, 320), 0.55) + rng.normal(0, 0.01, (240, 320))
    img[::17, :] *= 0.5
    img[:, 150:156] = 0.9
    masks = BrightMasks(img)
    got = masks(12)
    assert got.dtype == np.uint8 and set(np.unique(got)) == {0, 1}
    assert got[:, 150:156].all()  # the stripe
    assert not got[:, :140].any() and not got[:, 166:].any()  # neither grain nor lines
    np.testing.assert_array_equal(got, _bright_mask(img, 12))
    # kernels up to 7 px share the 15 px element: one mask; another size is made anew
    assert masks(5) is masks(7)
    assert masks(12) is got and masks(9) is not got
    np.testing.assert_array_equal(masks(9), _bright_mask(img, 9))


def test_rays_start_hidden_where_the_print_within_a_pixel_of_their_centre_is_hidden() -> None:
    # A stripe 6 px wide (rows 20-25) hidden in the map: the first samples of rays from a
    # centre read the pixels around it.
    d = np.ones((50, 60))
    d[20:26] = -1.0
    assert starts_hidden(d, np.array([30.0, 22.5]))
    assert starts_hidden(d, np.array([30.0, 26.5]))  # (its first samples reach row 25)
    assert not starts_hidden(d, np.array([30.0, 28.5]))
    assert not starts_hidden(d, np.array([30.0, 10.0]))
    assert not starts_hidden(d, np.array([-5.0, -5.0]))  # (outside the map: nothing read)
