"""Compiled fast-mode kernel: every scan line's primary peak and its window in one pass.

:func:`line_peaks` does per line what :func:`scanner.stripe.fast._measure_many` does for a whole
frame with NumPy: the line's maximum (the first one, as :func:`numpy.argmax`), the window of
``2 hw + 5`` pixels around it, the linear background through the two flank pixels on each side,
and the background-subtracted centre of gravity and second moment. It also tells whether any
pixel outside the primary window clears the candidate threshold, which is all the rare
multi-peak lines need to be searched further with NumPy. Windows that reach the image border
are only marked: like every other uncommon peak they are measured by
:func:`scanner.stripe.fast._measure`.

Compiled with numba where it imports (:data:`HAVE_NUMBA`); without it the callers keep the
NumPy path.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanner.core.jit import HAVE_NUMBA, njit
from scanner.stripe.profile import _FWHM_PER_SIGMA

__all__ = ["HAVE_NUMBA", "line_peaks"]

_BLOCK = 256  # pixels whose maximum is taken in one vectorised run (a multiple of 8)
_ONES = np.uint64(0x0101010101010101)
_HIGHS = np.uint64(0x8080808080808080)


@njit(cache=True, nogil=True, inline="always")
def _run_max(seg):  # pragma: no cover - compiled
    m = seg[0]
    for j in range(seg.size):
        v = seg[j]
        if v > m:
            m = v
    return m


@njit(cache=True, nogil=True)
def _line_peaks(img, words, step, hw, thr, search_other):  # pragma: no cover - compiled
    H, W = img.shape
    n = (H + step - 1) // step
    cols = np.empty(n, np.int64)
    pos = np.empty(n, np.float64)
    peak = np.empty(n, np.float32)
    contrast = np.empty(n, np.float32)
    slope = np.empty(n, np.float32)
    width = np.empty(n, np.float32)
    near = np.zeros(n, np.bool_)
    other = np.zeros(n, np.bool_)
    n_blocks = (W + _BLOCK - 1) // _BLOCK
    block_max = np.empty(n_blocks, img.dtype)
    words_per_line = W // 8
    n_core = 2 * hw + 1
    x2 = hw * (hw + 1) * (2 * hw + 1) / 3.0  # sum of x^2, x = -hw..hw
    fwhm = _FWHM_PER_SIGMA
    for i in range(n):
        r = i * step
        row = img[r]
        # The line's first maximum: block maxima (vectorised), the first block holding the
        # largest, then its first pixel equal to it.
        best = row[0]
        best_block = 0
        for k in range(n_blocks):
            m = _run_max(row[k * _BLOCK : k * _BLOCK + _BLOCK])
            block_max[k] = m
            if m > best:
                best = m
                best_block = k
        c = best_block * _BLOCK
        if words.size:
            # 8-bit lines of whole words: eight pixels at a time (the first word with a byte
            # equal to the maximum; the zero-byte test is exact for the lowest such byte).
            pattern = np.uint64(best) * _ONES
            w = r * words_per_line + c // 8
            while True:
                y = words[w] ^ pattern
                if (y - _ONES) & ~y & _HIGHS:
                    break
                w += 1
            c = (w - r * words_per_line) * 8
        while row[c] != best:
            c += 1
        cols[i] = c

        # Anything above the threshold outside the window c - hw .. c + hw (clipped)?
        if search_other and best > thr:
            lo = max(c - hw, 0)
            hi = min(c + hw, W - 1)
            for k in range(n_blocks):
                if block_max[k] <= thr:
                    continue
                b0 = k * _BLOCK
                b1 = min(b0 + _BLOCK, W)
                if b1 <= lo or b0 > hi:  # wholly outside the window
                    other[i] = True
                    break
                if lo > b0 and _run_max(row[b0:lo]) > thr:
                    other[i] = True
                    break
                if hi + 1 < b1 and _run_max(row[hi + 1 : b1]) > thr:
                    other[i] = True
                    break

        peak[i] = best
        if c < hw + 2 or c > W - hw - 3:
            near[i] = True  # measured by _measure
            pos[i] = c
            contrast[i] = 0.0
            slope[i] = 0.0
            width[i] = np.nan
            continue
        # Linear background through the flank pairs' means at x = -/+ (hw + 1.5). Sums of
        # integer pixels stay integers (exact); x runs -hw..hw over win[2:-2].
        win = row[c - hw - 2 : c + hw + 3]
        s0 = 0
        s1 = 0
        s2 = 0
        for j in range(n_core):
            v = win[j + 2]
            x = j - hw
            s0 += v
            s1 += x * v
            s2 += x * x * v
        left = 0.5 * (np.float64(win[0]) + np.float64(win[1]))
        right = 0.5 * (np.float64(win[n_core + 2]) + np.float64(win[n_core + 3]))
        mean = 0.5 * (left + right)
        sl = (right - left) / (2 * hw + 3)
        sw = s0 - n_core * mean
        sx = s1 - x2 * sl
        sxx = s2 - x2 * mean
        con = np.float64(best) - mean
        if not sw > 0.0:
            sw = 1.0
            con = 0.0
        mu = sx / sw
        var = sxx / sw - mu * mu
        if var < 0.0:
            var = 0.0
        pos[i] = c + mu
        contrast[i] = con
        slope[i] = sl
        width[i] = fwhm * np.sqrt(var)
    return cols, pos, peak, contrast, slope, width, near, other


def line_peaks(
    img: NDArray, step: int, hw: int, thr: float
) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray, NDArray, NDArray, NDArray]:
    """The primary peak of every ``step``-th line, measured as :func:`_measure_many` does.

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8, uint16 or float32, C-contiguous
        Working-orientation frame (rows are scan lines) without NaN, ``W >= 2 hw + 5``.
    step : int
        Lines ``0, step, 2 step, ...`` are measured (``N = ceil(H / step)`` of them).
    hw : int
        Half-window of the centre of gravity (``>= 1``).
    thr : float
        Candidate level: ``other`` tells whether a pixel outside the primary window exceeds
        it (``inf``: not searched).

    Returns
    -------
    cols : ndarray, shape (N,), int64
        Each line's first maximum (as :func:`numpy.argmax`).
    pos : ndarray, shape (N,), float64
        Centre of gravity along the line, px.
    peak, contrast, slope, width : ndarray, shape (N,), float32
        Peak grey level; peak above the linear background (0 where the background-subtracted
        window sums to <= 0); background slope, grey levels per px; FWHM-equivalent width, px.
    near : ndarray, shape (N,), bool
        Windows reaching past the border (``pos``, ``contrast``, ``slope``, ``width`` are
        placeholders there: measure them with :func:`scanner.stripe.fast._measure`).
    other : ndarray, shape (N,), bool
        A pixel outside ``cols - hw .. cols + hw`` (clipped to the image) exceeds ``thr``.

    Raises
    ------
    ValueError
        A frame that is not 2-D, C-contiguous, native uint8 / uint16 / float32 and at least
        ``2 hw + 5`` wide; ``hw`` or ``step`` below 1; a negative ``thr`` for an unsigned frame.
    """
    if img.ndim != 2 or not img.flags.c_contiguous:
        raise ValueError(
            f"img: expected a C-contiguous 2-D frame, got shape {img.shape}"
            f" ({'' if img.flags.c_contiguous else 'not '}C-contiguous)"
        )
    if img.dtype not in (np.uint8, np.uint16, np.float32) or not img.dtype.isnative:
        raise ValueError(f"img: expected native uint8, uint16 or float32, got {img.dtype}")
    if hw < 1 or step < 1:
        raise ValueError(f"hw, step: expected >= 1, got {hw}, {step}")
    if img.shape[1] < 2 * hw + 5:
        raise ValueError(f"img: expected at least {2 * hw + 5} columns, got {img.shape[1]}")
    W = img.shape[1]
    words = _NO_WORDS
    if img.dtype == np.uint8 and W % 8 == 0:
        words = img.reshape(-1).view(np.uint64)
        if not words.flags.aligned:
            words = _NO_WORDS
    # The level in the frame's own type (no conversion per pixel): for integers, v > thr
    # exactly when v > floor(thr).
    thr = float(thr)
    search_other = thr < np.inf
    if img.dtype.kind == "u":
        top = 255.0 if img.dtype == np.uint8 else 65535.0
        if thr < 0:
            raise ValueError(f"thr: expected >= 0 for an unsigned frame, got {thr}")
        search_other = search_other and thr < top
        level = img.dtype.type(min(np.floor(thr), top))
    else:
        level = img.dtype.type(thr if search_other else 0.0)
    return _line_peaks(img, words, int(step), int(hw), level, search_other)


_NO_WORDS = np.zeros(0, np.uint64)
