"""The darkness and bright maps' compiled steps: the array expressions' values, to the bit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.detection.map_kernels import (
    bright_seeds,
    darkness_maps,
    every_nth_selected,
    kept_components,
    line_maps,
)


def test_the_darkness_maps_are_the_array_expressions() -> None:
    rng = np.random.default_rng(2)
    img = rng.uniform(0.0, 1.0, (80, 90)).astype(np.float32)
    bg = np.maximum(cv2.dilate(img, np.ones((7, 7), np.uint8)), img)
    bg[:5, :5] = 0.0  # 1e-6 floor under a black background
    thr = float(np.median(bg))
    bg[10, :4] = np.float32(thr)  # on the threshold (compared in float32)
    bg[11, :4] = np.nextafter(np.float32(thr), np.float32(0.0))
    d_want = 1.0 - img / np.maximum(bg, 1e-6)
    d_want[bg < thr] = 0.0
    d, bg64 = darkness_maps(img, bg, thr)
    assert d.dtype == bg64.dtype == np.float64
    np.testing.assert_array_equal(d, np.clip(d_want, 0.0, 1.0).astype(np.float64))
    np.testing.assert_array_equal(bg64, bg.astype(np.float64))
    assert 0 < np.mean(d == 0.0) < 1


def test_the_bright_seeds_are_the_array_expressions() -> None:
    rng = np.random.default_rng(6)
    paper = rng.uniform(0.3, 0.9, (70, 110)).astype(np.float32)
    smooth = (paper + rng.normal(0.0, 0.08, paper.shape)).astype(np.float32)
    # over the noise, not 12 % over the paper: cores only where the image clips
    paper[0, :3], smooth[0, :3] = np.float32(0.9), np.float32(0.95)
    for img in (rng.uniform(0.0, 1.0, paper.shape), rng.uniform(0, 1, paper.shape).astype("f4")):
        clip = 0.99 * float(img.max())
        img[0, :3] = img.dtype.type(clip)  # on the clip level, in the image's type
        gain, offset, core_min, weak_min = 0.12, 0.02 * 0.61, 3.5 * 0.011, 2.0 * 0.011
        above = smooth - paper
        core = above > np.maximum(paper * gain + offset, core_min)
        core |= (img >= clip) & (above > core_min)
        weak = (above > weak_min) | core
        got_core, got_weak = bright_seeds(
            smooth, paper, img, gain, offset, core_min, clip, weak_min
        )
        np.testing.assert_array_equal(got_core, core)
        assert core[0, :3].all()
        np.testing.assert_array_equal(got_weak, weak.astype(np.uint8))
        assert 0 < core.mean() < weak.mean() < 1


def test_kept_components_are_those_holding_a_core() -> None:
    weak = np.zeros((40, 50), np.uint8)
    weak[5:10, 5:20] = 1  # holds a core
    weak[20:30, 30:35] = 1  # no core
    weak[35:38, 2:48] = 1  # holds a core at its far end
    core = np.zeros(weak.shape, bool)
    core[7, 6] = core[36, 47] = True
    core[0, 0] = True  # a core on the background (label 0) keeps nothing
    n, labels = cv2.connectedComponents(weak, connectivity=8)
    got = kept_components(labels, core, n)
    want = np.zeros(weak.shape, np.uint8)
    want[5:10, 5:20] = 1
    want[35:38, 2:48] = 1
    np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="expected labels"):
        kept_components(labels, core, n - 1)  # (a label beyond the table)


def test_the_line_maps_are_the_array_expressions_with_either_threshold_type() -> None:
    rng = np.random.default_rng(9)
    d = np.abs(rng.normal(0.0, 0.05, (60, 75)))
    thr = rng.uniform(0.01, 0.03, d.shape).astype(np.float32)
    hidden = rng.random(d.shape) < 0.1
    z_line = 2.0
    d[0, 0] = z_line * float(thr[0, 0])  # on the line's level: not over it
    thr[1, 1] = 0.0  # (never from the threshold map: its floor is above 0) inf, not an error
    with np.errstate(divide="ignore"):
        z = d / thr.astype(np.float64)
    assert np.isinf(z[1, 1])
    for t in (thr, thr.astype(np.float64)):
        mask, z_rays = line_maps(d, t, hidden, z_line)
        np.testing.assert_array_equal(mask, (z > z_line).astype(np.uint8) * 255)
        np.testing.assert_array_equal(z_rays, np.where(hidden, -1.0, z))
    assert 0 < np.mean(mask > 0) < 1


def test_every_nth_selected_is_the_strided_selection() -> None:
    rng = np.random.default_rng(1)
    values = rng.normal(size=(37, 41))
    selected = rng.random(values.shape) < 0.6
    for step in (1, 2, 7, 10_000):
        np.testing.assert_array_equal(
            every_nth_selected(values, selected, step), values[selected][::step]
        )
    assert every_nth_selected(values, np.zeros(values.shape, bool), 3).shape == (0,)
