"""A frame's starting estimates: its noise, a robust median, the centre-of-gravity window."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from scanner.stripe.fast import _measure_lines, _measure_many
from scanner.stripe.kernels import kth_smallest
from scanner.stripe.profile import _FWHM_PER_SIGMA

__all__ = ["auto_half_window", "estimate_noise"]


def _median(values: NDArray) -> float:
    """Median: of 8/16-bit values the lower middle one, of floats as :func:`numpy.median`.

    Small samples by partitioning, large 8-bit ones by histogram (several times faster).
    """
    v = np.asarray(values).reshape(-1)
    if 0 < v.size <= 4096 and v.dtype in (np.uint8, np.uint16):  # lower median, as below
        return kth_smallest(v, (v.size - 1) // 2)
    if v.dtype.kind == "f" and v.size:  # as np.median: the two middle values' mean
        k = v.size // 2
        if v.size % 2:
            return float(np.partition(v, k)[k])
        part = np.partition(v, (k - 1, k))
        return 0.5 * (float(part[k - 1]) + float(part[k]))
    if v.dtype == np.uint8 and v.size < 2**24:  # float32 counts stay exact
        # One row: OpenCV takes a 1-D array for a column, pixel by pixel (twice as slow).
        counts = cv2.calcHist([v.reshape(1, -1)], [0], None, [256], [0, 256]).reshape(-1)
        return float(np.searchsorted(np.cumsum(counts), (v.size + 1) // 2))
    if v.dtype in (np.uint8, np.uint16) and v.size:
        counts = np.bincount(v, minlength=1)
        return float(np.searchsorted(np.cumsum(counts), (v.size + 1) // 2))
    return float(np.median(v))


def estimate_noise(image: NDArray, step: int = 32) -> float:
    """Robust standard deviation of the image noise, grey levels (at least 0.5).

    From the median absolute difference of horizontally adjacent pixels on every ``step``-th
    row, which smooth shading and a thin stripe barely touch.
    """
    rows = np.asarray(image)[::step]
    if rows.strides[1] != rows.itemsize:  # a transposed view: OpenCV reads contiguous rows
        rows = np.ascontiguousarray(rows)
    if rows.dtype in (np.uint8, np.uint16):
        diff = cv2.absdiff(rows[:, 1:], rows[:, :-1])  # |a - b| without a wider dtype
    else:
        diff = np.abs(np.diff(rows.astype(np.float32), axis=1))
    mad = _median(diff)
    return max(0.5, 1.4826 * mad / np.sqrt(2.0))


def auto_half_window(img: NDArray, noise: float, step: int = 16) -> int:
    """Noise-optimal centre-of-gravity half-window (about 2.7 sigma) from every ``step``-th line."""
    # Widths and contrasts only: no search for second maxima (it moves centres, not widths).
    compiled = _measure_lines(img, 10, float("inf"), step=step, typical=float("inf"))
    if compiled is not None:
        m = compiled[0]
    else:
        lines = np.arange(0, img.shape[0], step)
        cols = img[::step].argmax(axis=1)
        m = _measure_many(img, lines, cols, 10, float("inf"), typical=float("inf"))
    ok = m.contrast > 10.0 * noise
    if np.count_nonzero(ok) < 3:
        return 6
    # np.median's value (float32 mean of the middle two) without its overhead.
    w = m.width[ok]
    k = w.size // 2
    part = np.partition(w, (k - 1, k))
    median = float(part[k] if w.size % 2 else (part[k - 1] + part[k]) / 2)
    if w.size >= 8 and np.median(m.contrast[ok]) < 20.0 * noise:
        # A faint stripe's windowed second moment is mostly noise (0 to 10 px for a 1.7 px
        # stripe 11 noise sigmas high): widths that disagree by more than their median say
        # nothing of the stripe, and the narrowest window lets the least noise in.
        q1, q3 = np.percentile(w, [25.0, 75.0])
        if q3 - q1 > median:
            return 3
    sigma = median / _FWHM_PER_SIGMA
    return int(np.clip(np.rint(2.7 * sigma), 3, 20))
