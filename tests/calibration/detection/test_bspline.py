"""The compiled cubic B-spline prefilter against SciPy's, to the bit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from calibration.detection.bspline import STRIP, spline_filter


def test_the_coefficients_are_scipys_to_the_bit() -> None:
    rng = np.random.default_rng(20261202)
    shapes = [(1, 1), (1, 7), (7, 1), (2, 2), (STRIP, STRIP + 1), (3, 900), (900, 3)]
    shapes += [tuple(int(v) for v in rng.integers(1, 3 * STRIP, 2)) for _ in range(60)]
    for shape in shapes:
        img = rng.normal(size=shape) * rng.choice([1e-3, 1.0, 1e6])
        np.testing.assert_array_equal(spline_filter(img), ndimage.spline_filter(img, order=3))


def test_a_line_longer_than_the_poles_underflow_is_scipys_too() -> None:
    # |z| ** 566 underflows to zero: the causal start's sum stops there.
    img = np.random.default_rng(5).random((700, 1300))
    np.testing.assert_array_equal(spline_filter(img), ndimage.spline_filter(img, order=3))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_other_dtypes_are_filtered_in_float64(dtype: type) -> None:
    img = (np.random.default_rng(6).random((50, 70)) * 200).astype(dtype)
    got = spline_filter(img)
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got, ndimage.spline_filter(img, order=3))


def test_values_that_are_not_finite_or_overflow_are_scipys() -> None:
    rng = np.random.default_rng(7)
    img = rng.random((40, 60))
    img[10, 20] = np.inf
    img[30, 5] = np.nan
    np.testing.assert_array_equal(spline_filter(img), ndimage.spline_filter(img, order=3))
    far = np.ones((700, 3))
    far[650, 1] = np.inf  # (beyond where the causal start's sum stops: SciPy's NaN there)
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(spline_filter(far), ndimage.spline_filter(far, order=3))
    for shape in ((40, 60), (700, 1), (1, 700)):  # (a column or a row: one pass only)
        big = rng.random(shape) * 1.7e308  # (the gain takes it beyond float64's range)
        with np.errstate(over="ignore", invalid="ignore"):
            np.testing.assert_array_equal(spline_filter(big), ndimage.spline_filter(big, order=3))


@pytest.mark.parametrize("shape", [(0, 40), (40, 0), (0, 0), (0, 1), (1, 0)])
def test_an_empty_image_gives_empty_coefficients(shape: tuple[int, int]) -> None:
    got = spline_filter(np.zeros(shape))
    assert got.shape == shape and got.dtype == np.float64


def test_the_input_is_left_as_it_was() -> None:
    img = np.random.default_rng(8).random((20, 30))
    before = img.copy()
    spline_filter(img)
    np.testing.assert_array_equal(img, before)


def test_spline_filter_refuses_what_is_not_an_image() -> None:
    with pytest.raises(ValueError, match=r"expected shape \(H, W\)"):
        spline_filter(np.zeros(10))
