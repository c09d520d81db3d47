"""The coarse stage's darkness and its threshold: learnt from the paper's own noise."""

from __future__ import annotations

import numpy as np

from calibration.detection.concentric_rays import _darkness, _lit_level, _threshold_map


def test_a_laser_stripe_filling_tiles_does_not_lower_their_threshold() -> None:
    # Over a stripe the darkness is 0 without noise (the closing follows a bright line):
    # a tile it fills would learn the floor, and the paper's noise beside it would pass.
    rng = np.random.default_rng(12)
    d = np.abs(rng.normal(0.0, 0.012, (400, 480)))
    bg = rng.uniform(0.9, 1.0, d.shape)  # lit paper (not clipped)
    hidden = np.zeros(d.shape, bool)
    hidden[150:260, :] = True
    d[hidden] = 0.0
    paper = _threshold_map(d, bg, 48, hidden)
    # the paper's own level passes almost none of its noise
    assert np.mean(d[:140] > paper[:140]) < 0.01
    assert paper[50, 240] > 0.025
    # under the stripe the whole lit area's level (no paper of its own), not the floor of a
    # noise-free tile; beside it the paper's
    assert paper[205, 240] >= 0.8 * paper[50, 240]
    assert np.mean(d[262:300] > paper[262:300]) < 0.01
    blind = _threshold_map(d, bg, 48)
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
    d, _ = _darkness(img, 9)
    assert d[101, 200] == 0.0  # taken for surroundings
    d, _ = _darkness(img, 9, hidden)
    assert abs(d[101, 200] - 0.4) < 0.03
