"""The radix-selection median against ``np.median``, to the bit."""

from __future__ import annotations

import numpy as np
import pytest

from scanner.core.selection import SMALL_SAMPLE, median


def _samples(rng: np.random.Generator, n: int, kind: int) -> np.ndarray:
    if kind == 0:  # smooth
        return rng.normal(size=n)
    if kind == 1:  # a few levels, many ties (quantised noise)
        return np.round(rng.normal(size=n) * 3) / 7
    if kind == 2:  # tiny magnitudes (float32 subnormals among them)
        return np.abs(rng.normal(size=n)) * 1e-40
    if kind == 3:  # zeros of both signs
        return rng.integers(-3, 3, n).astype(float) * 0.0
    if kind == 4:  # half the values one number, both signs
        return np.where(rng.random(n) < 0.5, 1.0, rng.random(n)) * rng.choice([-1.0, 1.0], n)
    return rng.exponential(size=n) * 1e20  # (beyond float32's range: inf in float32)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_median_is_numpys_to_the_bit(dtype: type) -> None:
    rng = np.random.default_rng(20261202)
    for t in range(300):
        n = int(rng.integers(SMALL_SAMPLE, 3 * SMALL_SAMPLE))  # even and odd counts
        with np.errstate(over="ignore"):
            x = _samples(rng, n, t % 6).astype(dtype)
        got, want = median(x), float(np.median(x))
        # (compared by bits: -0.0 == 0.0 would pass)
        assert np.float64(got).tobytes() == np.float64(want).tobytes(), (t, n, got, want)


def test_median_of_a_sample_whose_middle_pair_straddles_a_gap() -> None:
    # The two middle values apart, the upper one the only one of its value.
    x = np.concatenate([np.zeros(5000), [1.0], np.full(4999, 7.0)]).astype(np.float32)
    np.random.default_rng(1).shuffle(x)
    assert median(x) == float(np.median(x)) == 0.5
    x[x == 1.0] = 0.0  # the middle pair now both zero
    assert median(x) == 0.0
    x = np.concatenate([np.zeros(5000), np.full(5000, 3.0)])
    assert median(x) == 1.5


@pytest.mark.parametrize("n", [SMALL_SAMPLE, SMALL_SAMPLE + 1])
def test_a_zero_median_is_positive_zero_as_numpys(n: int) -> None:
    for dtype in (np.float32, np.float64):
        x = np.full(n, -0.0, dtype=dtype)
        assert not np.signbit(median(x)) and not np.signbit(np.median(x))
        x[: n // 2] = 0.0  # both zeros in the middle pair
        assert not np.signbit(median(x))


def test_median_gives_nan_where_the_sample_holds_nan() -> None:
    x = np.random.default_rng(2).normal(size=10_000).astype(np.float32)
    x[1234] = np.nan
    assert np.isnan(median(x))


def test_small_samples_and_other_dtypes_go_to_numpy() -> None:
    rng = np.random.default_rng(3)
    for x in (rng.normal(size=7), rng.integers(0, 9, 10_001), rng.normal(size=1)):
        assert median(x) == float(np.median(x))


def test_median_refuses_what_is_not_a_sample() -> None:
    with pytest.raises(ValueError, match="expected a non-empty 1-D array"):
        median(np.zeros((100, 100)))
    with pytest.raises(ValueError, match="expected a non-empty 1-D array"):
        median(np.zeros(0))
