"""Grey morphology by rows and 16-bit levels: OpenCV's and NumPy's values, to the bit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.detection.morphology import (
    _by_rows,
    _plan,
    dilate,
    erode,
    from_levels,
    grey_morphology,
    row_half_widths,
    to_levels,
)

_SHAPES = (cv2.MORPH_ELLIPSE, cv2.MORPH_RECT, cv2.MORPH_CROSS)


def _image(rng: np.random.Generator, shape: tuple[int, int], dtype: type) -> np.ndarray:
    if dtype is np.uint8:
        return rng.integers(0, 256, shape).astype(np.uint8)
    if dtype is np.uint16:
        return rng.integers(0, 65536, shape).astype(np.uint16)
    return rng.normal(0.5, 0.2, shape).astype(np.float32)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_the_rows_dilation_and_erosion_are_opencvs(dtype: type) -> None:
    # Every odd size from 1 to 61 px, images smaller and larger than the element (a row, a
    # column), each element shape whose rows are centred segments: the rows' way directly,
    # whichever way the dispatcher would have chosen.
    rng = np.random.default_rng(3)
    for k in range(1, 62, 2):
        for shape in _SHAPES:
            se = cv2.getStructuringElement(shape, (k, k))
            half_widths = row_half_widths(se)
            assert half_widths is not None
            radii, rows = _plan(half_widths)
            for h, w in ((1, 1), (1, 37), (29, 1), (int(rng.integers(2, 90)), 83)):
                img = _image(rng, (h, w), dtype)
                for take_max, op in ((True, cv2.dilate), (False, cv2.erode)):
                    got = _by_rows(np.ascontiguousarray(img), radii, rows, take_max)
                    assert got.dtype == img.dtype
                    np.testing.assert_array_equal(got, op(img, se), err_msg=f"{k} {shape} {h}x{w}")


def test_the_closing_and_opening_are_opencvs_on_a_detector_sized_image() -> None:
    rng = np.random.default_rng(5)
    img = cv2.GaussianBlur(_image(rng, (300, 420), np.uint16), (0, 0), 2.0)
    for k in (9, 25, 51):
        for shape in _SHAPES:
            se = cv2.getStructuringElement(shape, (k, k))
            for op in (cv2.MORPH_CLOSE, cv2.MORPH_OPEN):
                want = cv2.morphologyEx(img, op, se)
                np.testing.assert_array_equal(grey_morphology(img, op, se), want)
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (25, 25))
    np.testing.assert_array_equal(dilate(img, se), cv2.dilate(img, se))
    np.testing.assert_array_equal(erode(img, se), cv2.erode(img, se))


def test_elements_not_made_of_centred_rows_go_to_opencv() -> None:
    rng = np.random.default_rng(8)
    img = _image(rng, (60, 70), np.uint8)
    even = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (8, 8))  # rows off centre
    assert row_half_widths(even) is None
    off = np.zeros((5, 5), np.uint8)
    off[2, :] = 1
    off[1, 3:] = 1  # a row not centred
    assert row_half_widths(off) is None
    hollow = np.ones((5, 5), np.uint8)
    hollow[2, 2] = 0  # a broken row
    assert row_half_widths(hollow) is None
    for se in (even, off, hollow):
        np.testing.assert_array_equal(dilate(img, se), cv2.dilate(img, se))
        np.testing.assert_array_equal(erode(img, se), cv2.erode(img, se))


def test_the_plan_reaches_every_half_width_by_three_shifted_copies() -> None:
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (51, 51))
    half_widths = row_half_widths(se)
    radii, rows = _plan(half_widths)
    assert radii[0] == 0
    assert np.all(np.diff(radii) > 0)
    assert np.all(np.diff(radii) <= 2 * radii[:-1] + 1)  # the copies overlap or touch
    np.testing.assert_array_equal(radii[rows], half_widths)


def test_the_16_bit_levels_are_numpys_arithmetic() -> None:
    rng = np.random.default_rng(11)
    img = rng.normal(0.4, 0.3, (97, 131)).astype(np.float32)
    lo, hi = float(img.min()), float(img.max())
    scale = (hi - lo) / 65535.0
    # half-level values (rint's ties to even), the range's ends, values beyond them
    img[0, :8] = np.float32(lo) + np.float32(scale) * np.arange(8, dtype=np.float32) * 0.5
    img[1, :2] = (np.float32(lo - 1.0), np.float32(hi + 1.0))
    lo32, inv32 = np.float32(lo), np.float32(1.0 / scale)
    scaled = (img - lo32) * inv32
    want = np.rint(np.clip(scaled, 0.0, 65535.0)).astype(np.uint16)
    own = to_levels(img, lo32, inv32)
    np.testing.assert_array_equal(own, want)
    levels = cv2.morphologyEx(own, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    back = levels.astype(np.float32) * np.float32(scale) + lo32
    same = levels == own
    back[same] = img[same]
    got = from_levels(levels, own, img, np.float32(scale), lo32)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, back)
    assert 0 < same.mean() < 1  # both kinds of pixel were there
    with pytest.raises(ValueError, match="expected one"):
        from_levels(levels, own[:5, :5], img, np.float32(scale), lo32)


def test_the_dispatcher_keeps_opencvs_values_for_every_type_and_odd_input() -> None:
    # Every type through the public calls; a float image holding values that are not finite
    # (OpenCV's border, the largest float, then takes part), an empty image and a 1-D array
    # go to OpenCV and come back as OpenCV gives them (or fail as it fails).
    rng = np.random.default_rng(13)
    for dtype in (np.uint8, np.uint16, np.float32):
        img = _image(rng, (97, 120), dtype)
        for k in (7, 15, 31):
            se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
            for op in (cv2.MORPH_CLOSE, cv2.MORPH_OPEN):
                np.testing.assert_array_equal(
                    grey_morphology(img, op, se), cv2.morphologyEx(img, op, se)
                )
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (25, 25))
    for bad in (np.inf, -np.inf, np.nan):
        img = _image(rng, (60, 64), np.float32)
        img[10:14, 20:30] = bad
        for op in (cv2.MORPH_CLOSE, cv2.MORPH_OPEN):
            np.testing.assert_array_equal(
                grey_morphology(img, op, se), cv2.morphologyEx(img, op, se)
            )
    with pytest.raises(cv2.error):
        dilate(np.zeros((0, 5), np.float32), se)
