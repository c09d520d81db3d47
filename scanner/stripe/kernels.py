"""Compiled stripe kernels: the fast mode's peaks and windows, the precise mode's Steger step.

:func:`line_peaks` does per line what :func:`scanner.stripe.fast._measure_many` does for a whole
frame with NumPy: the line's maximum (the first one, as :func:`numpy.argmax`), the window of
``2 hw + 5`` pixels around it, the linear background through the two flank pixels on each side,
and the background-subtracted centre of gravity and second moment. It also tells whether any
pixel outside the primary window clears the candidate threshold, which is all the rare
multi-peak lines need to be searched further with NumPy. Windows that reach the image border
are only marked: like every other uncommon peak they are measured by
:func:`scanner.stripe.fast._measure`. Given the transposed view of a frame (scan lines stored
as its columns), it runs a column kernel instead that sweeps the stored rows for all lines at
once: no transposition.

:func:`steger_points` does per point what :func:`scanner.stripe.precise._refine_precise` does
with NumPy for all points at once: the smoothed image's gradient and Hessian at the fast
centre, the Taylor step across the stripe and the slide back onto the scan line.

:func:`saturated_centres` is :func:`scanner.stripe.fast._saturated_centres` per peak: the
saturated run through the peak and the log-parabola of its unsaturated flanks.

:func:`kth_smallest` is ``np.partition(values, k)[k]`` for the frame's few small medians (the
typical width and contrast, the background's level), without NumPy's fixed cost per call,
which on a thousand values is most of it.

Compiled with numba where it imports (:data:`HAVE_NUMBA`); without it the callers keep the
NumPy path.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanner.core.jit import HAVE_NUMBA, njit
from scanner.stripe.profile import _FWHM_PER_SIGMA

__all__ = ["HAVE_NUMBA", "kth_smallest", "line_peaks", "saturated_centres", "steger_points"]

_REACH = 32  # px either side of the previous line's peak where the line's is sought first
_SPAN = 3 * _REACH  # px of that middle part, aligned; its offsets fit 8 bits
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


@njit(cache=True, nogil=True, inline="always")
def _first_equal(row, words, w0, c, best):  # pragma: no cover - compiled
    """The first index ``>= c`` of ``row`` holding ``best`` (there must be one)."""
    if words.size:
        # 8-bit lines of whole words: eight pixels at a time (the first word with a byte equal
        # to the maximum; the zero-byte test is exact for the lowest such byte).
        pattern = np.uint64(best) * _ONES
        w = w0 + c // 8
        while True:
            y = words[w] ^ pattern
            if (y - _ONES) & ~y & _HIGHS:
                break
            w += 1
        c = max((w - w0) * 8, c)
    while row[c] != best:
        c += 1
    return c


@njit(cache=True, nogil=True, inline="always")
def _first_equal_in_span(seg, best):  # pragma: no cover - compiled
    """The first index of ``seg`` (``_SPAN`` pixels) holding ``best`` (one must).

    A minimum over the whole span of 8-bit indices, without branches: it compiles to vector
    compares and minima (a loop that stops at the first hit cannot, and a mispredicted exit
    costs more than the search itself).
    """
    first = np.uint8(_SPAN)
    for j in range(_SPAN):
        first = min(first, np.uint8(j) if seg[j] == best else np.uint8(_SPAN))
    return np.int64(first)


@njit(cache=True, nogil=True, inline="always")
def _span_max_count(seg, level):  # pragma: no cover - compiled
    """The maximum of ``seg`` (``_SPAN`` pixels) and how many of its pixels exceed ``level``.

    One pass of vector maxima and compares (the count fits 8 bits).
    """
    m = seg[0]
    n = np.uint8(0)
    for j in range(_SPAN):
        v = seg[j]
        m = max(m, v)
        n += np.uint8(v > level)
    return m, np.int64(n)


@njit(cache=True, nogil=True, inline="always")
def _outputs(n):  # pragma: no cover - compiled
    """The kernels' output arrays for ``n`` lines (as :func:`line_peaks` returns them)."""
    return (
        np.zeros(n, np.int64),  # cols
        np.empty(n, np.float64),  # pos
        np.empty(n, np.float32),  # peak
        np.zeros(n, np.float32),  # contrast
        np.zeros(n, np.float32),  # slope
        np.empty(n, np.float32),  # width
        np.zeros(n, np.bool_),  # near
        np.zeros(n, np.bool_),  # other
    )


@njit(cache=True, nogil=True, inline="always", fastmath={"reassoc", "contract"})
def _window_sums(win, hw, thr):  # pragma: no cover - compiled
    """One window of ``2 hw + 5`` pixels around a peak (not at a border): the sums of its
    ``-hw .. hw`` pixels times ``x^0, x^1, x^2``, the sums of its two flank pixels on each
    side, and how many of ``-hw .. hw`` exceed ``thr``."""
    n_core = 2 * hw + 1
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    n_win = 0
    for j in range(n_core):
        p = win[j + 2]
        v = np.float64(p)
        x = np.float64(j - hw)
        s0 += v
        s1 += x * v
        s2 += x * x * v
        n_win += p > thr
    left = np.float64(win[0]) + np.float64(win[1])
    right = np.float64(win[n_core + 2]) + np.float64(win[n_core + 3])
    return s0, s1, s2, left, right, n_win


@njit(cache=True, nogil=True, inline="always", fastmath={"reassoc", "contract"})
def _finish_windows(sums, cols, peak, near, hw, pos, contrast, slope, width):  # pragma: no cover
    """Each window's centre of gravity, contrast, background slope and FWHM-equivalent width
    from its :func:`_window_sums` (``sums``: rows ``s0, s1, s2, left, right``), for all lines
    at once (a loop without branches: vector divisions and roots); the lines ``near`` the
    border get placeholders (``pos = cols``, width NaN) for :func:`scanner.stripe.fast._measure`.

    The background is the line through the means of the two flank pixels on each side (at
    ``x = -/+ (hw + 1.5)``); a window whose background-subtracted sum is not positive has
    contrast 0 and offset 0.
    """
    n_core = 2 * hw + 1
    x2 = hw * (hw + 1) * (2 * hw + 1) / 3.0  # sum of x^2, x = -hw..hw
    for i in range(cols.size):
        left = sums[3, i]
        right = sums[4, i]
        mean = 0.25 * (left + right)
        sl = 0.5 * (right - left) / (2 * hw + 3)
        sw = sums[0, i] - n_core * mean
        sx = sums[1, i] - x2 * sl
        sxx = sums[2, i] - x2 * mean
        ok = sw > 0.0
        contrast[i] = np.float64(peak[i]) - mean if ok else 0.0
        sw = sw if ok else 1.0
        mu = sx / sw
        slope[i] = sl
        width[i] = _FWHM_PER_SIGMA * np.sqrt(max(sxx / sw - mu * mu, 0.0))
        pos[i] = cols[i] + mu
    for i in range(cols.size):
        if near[i]:
            pos[i] = cols[i]
            contrast[i] = 0.0
            slope[i] = 0.0
            width[i] = np.nan


@njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _line_peaks(img, words, step, hw, thr, search_other):  # pragma: no cover - compiled
    H, W = img.shape
    n = (H + step - 1) // step
    cols, pos, peak, contrast, slope, width, near, other = _outputs(n)
    span_count = np.full(n, -1, np.int64)
    words_per_line = W // 8
    # The line's first maximum (as argmax). The stripe moves little from line to line, so each
    # line is split into three parts, the middle one _SPAN px around the previous line's peak
    # (aligned: the vectorised maxima run faster), and the parts' maxima taken. Where the
    # middle part holds the maximum and the first part does not, the first maximum is found by
    # a branch-free search of the middle part; otherwise by a search from the middle part's
    # start (the first part lacks the maximum) or from the line's start.
    spans = W >= _SPAN + 16
    lo_max = (W - 8 - _SPAN) // 8 * 8
    hint = W // 2
    for i in range(n):
        r = i * step
        row = img[r]
        w0 = r * words_per_line
        if spans:
            lo = min(max((hint - _REACH) // _REACH * _REACH, 8), lo_max)
            hi = lo + _SPAN
        else:
            lo = 1
            hi = W - 1
        m1 = _run_max(row[:lo])
        if spans:
            m2, n_span = _span_max_count(row[lo:hi], thr)
        else:
            m2, n_span = _run_max(row[lo:hi]), 0
        m3 = _run_max(row[hi:])
        best = max(m1, max(m2, m3))
        if spans and m1 < best and m2 == best:
            c = lo + _first_equal_in_span(row[lo:hi], best)
        else:
            c = _first_equal(row, words, w0, lo if m1 < best else 0, best)
        cols[i] = c
        hint = c
        peak[i] = best

        # Anything above the threshold outside the window c - hw .. c + hw (clipped)? Where
        # the window lies in the middle part, decided with the window's count below: a pixel
        # above it in the outer parts (then more than any count), or more in the middle part
        # than in the window.
        a = c - hw
        b = c + hw + 1
        if search_other and best > thr:
            if spans and a >= lo and b <= hi:
                span_count[i] = _SPAN + 1 if max(m1, m3) > thr else n_span
            else:
                other[i] = (a > 0 and _run_max(row[:a]) > thr) or (
                    b < W and _run_max(row[b:]) > thr
                )
        near[i] = c < hw + 2 or c > W - hw - 3  # measured by _measure

    # The windows: lines independent of each other from here on. Their sums first, then
    # the divisions and roots for all lines at once.
    sums = np.zeros((5, n))
    for i in range(n):
        if near[i]:
            continue
        c = cols[i]
        sums[0, i], sums[1, i], sums[2, i], sums[3, i], sums[4, i], n_win = _window_sums(
            img[i * step, c - hw - 2 : c + hw + 3], hw, thr
        )
        if span_count[i] >= 0:
            other[i] = span_count[i] > n_win
    _finish_windows(sums, cols, peak, near, hw, pos, contrast, slope, width)
    return cols, pos, peak, contrast, slope, width, near, other


@njit(cache=True, nogil=True, inline="always")
def _sweep_step(v, off, thr, b, a, c):  # pragma: no cover - compiled
    """One pixel ``v`` at block offset ``off`` into a line's maximum ``b``, the offset ``a``
    where it first appeared (a strict ``>``) and the count ``c`` above ``thr`` (all 8-bit)."""
    return max(b, v), off if v > b else a, np.uint8(c + np.uint8(v > thr))


@njit(cache=True, nogil=True, inline="always")
def _sweep_rows4(
    row0, row1, row2, row3, o0, o1, o2, o3, thr, b_best, b_arg, b_above
):  # pragma: no cover - compiled
    """Four stored rows (offsets ``o0 .. o3`` in the block, uint8) into the column kernel's
    block, each line's accumulators loaded and stored once."""
    for i in range(row0.size):
        b, a, c = _sweep_step(row0[i], o0, thr, b_best[i], b_arg[i], b_above[i])
        b, a, c = _sweep_step(row1[i], o1, thr, b, a, c)
        b, a, c = _sweep_step(row2[i], o2, thr, b, a, c)
        b, a, c = _sweep_step(row3[i], o3, thr, b, a, c)
        b_best[i] = b
        b_arg[i] = a
        b_above[i] = c


@njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _column_peaks(src, step, hw, thr, search_other):  # pragma: no cover - compiled
    """:func:`_line_peaks` for scan lines that are the columns of ``src`` (C-contiguous).

    Row by row down the frame, every line's first maximum (a strict ``>`` keeps the first)
    and how many of its pixels exceed ``thr``, all lines at once (vector compares along the
    stored rows, no transposition); then each line's window down its column.
    """
    L, W = src.shape  # L pixels per scan line, W // step lines
    n = (W + step - 1) // step
    cols, pos, peak, contrast, slope, width, near, other = _outputs(n)
    # Blocks of up to 255 rows: the row of each line's maximum within the block and the count
    # above the level both fit 8 bits (the widest vectors for 8-bit frames); the blocks then
    # merge in order, a later one only where it is strictly higher.
    best = src[0, ::step].copy()
    arg = np.zeros(n, np.int64)
    above = np.zeros(n, np.int64)
    b_best = best.copy()
    b_arg = np.zeros(n, np.uint8)
    b_above = np.zeros(n, np.uint8)
    for r0 in range(0, L, 255):
        b_best[:] = src[r0, ::step]
        b_arg[:] = 0
        for i in range(n):
            b_above[i] = np.uint8(b_best[i] > thr)
        r1 = min(r0 + 255, L)
        r = r0 + 1
        if step == 1:  # contiguous rows, four at a time: one load and store of the block each
            while r + 4 <= r1:
                o = r - r0
                _sweep_rows4(
                    src[r], src[r + 1], src[r + 2], src[r + 3],
                    np.uint8(o), np.uint8(o + 1), np.uint8(o + 2), np.uint8(o + 3),
                    thr, b_best, b_arg, b_above,
                )  # fmt: skip
                r += 4
        while r < r1:
            row = src[r, ::step]
            off = np.uint8(r - r0)
            for i in range(n):
                b_best[i], b_arg[i], b_above[i] = _sweep_step(
                    row[i], off, thr, b_best[i], b_arg[i], b_above[i]
                )
            r += 1
        for i in range(n):
            if r0 == 0 or b_best[i] > best[i]:
                best[i] = b_best[i]
                arg[i] = r0 + np.int64(b_arg[i])
            above[i] += np.int64(b_above[i])
    sums = np.zeros((5, n))
    for i in range(n):
        c = arg[i]
        cols[i] = c
        peak[i] = best[i]
        line = src[:, i * step]
        if c < hw + 2 or c > L - hw - 3:  # measured by _measure
            near[i] = True
            if search_other and best[i] > thr:
                n_win = 0
                for j in range(max(c - hw, 0), min(c + hw + 1, L)):
                    n_win += line[j] > thr
                other[i] = above[i] > n_win
            continue
        sums[0, i], sums[1, i], sums[2, i], sums[3, i], sums[4, i], n_win = _window_sums(
            line[c - hw - 2 : c + hw + 3], hw, thr
        )
        other[i] = search_other and best[i] > thr and above[i] > n_win
    _finish_windows(sums, cols, peak, near, hw, pos, contrast, slope, width)
    return cols, pos, peak, contrast, slope, width, near, other


def line_peaks(
    img: NDArray, step: int, hw: int, thr: float
) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray, NDArray, NDArray, NDArray]:
    """The primary peak of every ``step``-th line, measured as :func:`_measure_many` does.

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8, uint16 or float32
        Working-orientation frame (rows are scan lines) without NaN, ``W >= 2 hw + 5``:
        C-contiguous, or the transposed view of a C-contiguous frame (its columns are then the
        scan lines, read in place by a kernel that sweeps the stored rows).
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
        A frame that is not 2-D, of either layout, native uint8 / uint16 / float32 and at least
        ``2 hw + 5`` wide; ``hw`` or ``step`` below 1; a negative ``thr`` for an unsigned frame.
    """
    if img.ndim != 2 or not (img.flags.c_contiguous or img.flags.f_contiguous):
        layout = "" if img.ndim != 2 else ", neither C- nor F-contiguous"
        raise ValueError(
            f"img: expected a 2-D frame, C-contiguous or its transposed view, got shape"
            f" {img.shape}{layout}"
        )
    if img.dtype not in (np.uint8, np.uint16, np.float32) or not img.dtype.isnative:
        raise ValueError(f"img: expected native uint8, uint16 or float32, got {img.dtype}")
    if hw < 1 or step < 1:
        raise ValueError(f"hw, step: expected >= 1, got {hw}, {step}")
    if img.shape[1] < 2 * hw + 5:
        raise ValueError(f"img: expected at least {2 * hw + 5} columns, got {img.shape[1]}")
    W = img.shape[1]
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
    if not img.flags.c_contiguous:  # a transposed view: its lines are the stored columns
        return _column_peaks(img.T, int(step), int(hw), level, search_other)
    words = _NO_WORDS
    if img.dtype == np.uint8 and W % 8 == 0:
        words = img.reshape(-1).view(np.uint64)
        if not words.flags.aligned:
            words = _NO_WORDS
    return _line_peaks(img, words, int(step), int(hw), level, search_other)


_NO_WORDS = np.zeros(0, np.uint64)


@njit(cache=True, nogil=True)
def _kth_smallest(values, k):  # pragma: no cover - compiled
    n = values.size
    a = np.empty(n, values.dtype)
    m = 0  # NaN sorts last, as in np.partition: the others are selected among themselves
    for i in range(n):
        v = values[i]
        if v == v:
            a[m] = v
            m += 1
    if k >= m:  # (only with NaN in the values)
        return np.nan
    lo, hi = 0, m - 1
    while hi > lo:  # Hoare's selection, the median of three as the pivot
        x, y, z = a[lo], a[(lo + hi) >> 1], a[hi]
        if x > y:
            x, y = y, x
        if y > z:
            y = z
        if x > y:
            y = x
        i, j = lo, hi
        while i <= j:
            while a[i] < y:
                i += 1
            while a[j] > y:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return a[k]
    return a[k]


def kth_smallest(values: NDArray, k: int) -> float:
    """``np.partition(values, k)[k]``: the ``k``-th smallest of ``values`` (NaN sorts last).

    Parameters
    ----------
    values : ndarray, shape (N,)
        uint8, uint16, float32 or float64 (others: NumPy's partition).
    k : int
        ``0 <= k < N``.
    """
    if not 0 <= k < values.size:
        raise ValueError(f"k: expected 0 <= k < {values.size}, got {k}")
    if HAVE_NUMBA and values.ndim == 1 and values.dtype in _SELECT_DTYPES:
        return float(_kth_smallest(values, k))
    return float(np.partition(values.reshape(-1), k)[k])


_SELECT_DTYPES = (np.uint8, np.uint16, np.float32, np.float64)


#: Relative curvature below which the log-parabola of a saturated run's flanks is flat: far
#: above double rounding (about 1e-16 of the level's logarithm), far below any real line's
#: (a Gaussian of sigma 30 px curves by 5.6e-4 per px squared).
_FLAT_CURVATURE = 1e-9


@njit(cache=True, nogil=True)
def _saturated_centres(img, lines, cols, sat, reach, flat):  # pragma: no cover - compiled
    """:func:`saturated_centres` per peak: the run through the peak, its unsaturated flanks'
    weighted log-parabola (normal equations solved by Cramer's rule), its vertex."""
    W = img.shape[1]
    n = lines.size
    P = 2 * reach + 1
    out = np.empty(n)
    runs = np.empty(n)
    vals = np.empty(P)
    for i in range(n):
        r = lines[i]
        c = cols[i]
        for k in range(P):
            cc = c + k - reach
            vals[k] = np.float64(img[r, cc]) if 0 <= cc < W else -np.inf
        # The saturated run through the peak pixel (none when the peak pixel is not).
        b = reach - 1
        while b + 1 < P and vals[b + 1] >= sat:
            b += 1
        a = reach + 1
        while a - 1 >= 0 and vals[a - 1] >= sat:
            a -= 1
        if vals[reach] < sat:
            a, b = reach + 1, reach - 1
        centre = 0.5 * (a + b)
        run = np.float64(b - a + 1)
        # Background: the lower of the mean levels at the window's two ends (inside the image).
        bg = np.inf
        for k0 in (0, P - 6):
            total = 0.0
            m = 0
            for k in range(k0, k0 + 6):
                if vals[k] > -np.inf:
                    total += vals[k]
                    m += 1
            if m:
                bg = min(bg, total / m)
        if not np.isfinite(bg):
            bg = 0.0
        span = 3.0 * run + 4.0
        mid = centre - reach
        s = np.zeros(5)
        rr = np.zeros(3)
        left_n = 0
        right_n = 0
        for k in range(P):
            v = vals[k]
            w = v - bg
            x = np.float64(k - reach)
            if not (np.isfinite(v) and v < sat and w > 0.05 * (sat - bg)):
                continue
            if abs(x - mid) > span:
                continue
            left_n += k < a
            right_n += k > b
            wt = max(w, 1e-9) ** 2
            y = np.log(max(w, 1e-9))
            xc = x - mid
            t = wt
            for q in range(5):
                s[q] += t
                if q < 3:
                    rr[q] += t * y
                t *= xc
        refined = centre
        if left_n >= 1 and right_n >= 1 and left_n + right_n >= 3:
            m00, m01, m02, m11, m12, m22 = s[0], s[1], s[2], s[2], s[3], s[4]
            c00 = m11 * m22 - m12 * m12
            c01 = m02 * m12 - m01 * m22
            c02 = m01 * m12 - m02 * m11
            det = m00 * c00 + m01 * c01 + m02 * c02
            if abs(det) > 1e-12:
                # Cramer's rule for the symmetric system: coef = adj(M) r / det.
                c11 = m00 * m22 - m02 * m02
                c12 = m01 * m02 - m00 * m12
                k0 = (c00 * rr[0] + c01 * rr[1] + c02 * rr[2]) / det
                k1 = (c01 * rr[0] + c11 * rr[1] + c12 * rr[2]) / det
                k2 = (c02 * rr[0] + c12 * rr[1] + (m00 * m11 - m01 * m01) * rr[2]) / det
                if k2 < -flat * max(abs(k0), 1.0):  # (a curvature that is rounding: flat)
                    vertex = -k1 / (2.0 * k2)
                    if np.isfinite(vertex) and abs(vertex) <= 0.5 * run + 0.5:
                        refined = centre + vertex
        out[i] = c + refined - reach
        runs[i] = run
    return out, runs


def saturated_centres(
    img: NDArray, lines: NDArray, cols: NDArray, sat: float, reach: int = 24
) -> tuple[NDArray, NDArray]:
    """:func:`scanner.stripe.fast._saturated_centres` (the NumPy reference) compiled.

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8 or uint16
        Working-orientation frame (rows are scan lines), C-contiguous or the transposed view
        of a C-contiguous frame. (Float frames, which may hold NaN, take the NumPy path.)
    lines, cols : ndarray, shape (N,), int
        Each saturated peak's line and a pixel of its saturated run.
    sat : float
        The saturation level.
    reach : int
        Pixels either side of ``cols`` searched for the run and its flanks.

    Returns
    -------
    centre : ndarray, shape (N,), float64
        The run's centre along the line, refined with its flanks where they allow.
    run : ndarray, shape (N,), float64
        The run's length, px.
    """
    if img.ndim != 2 or not (img.flags.c_contiguous or img.flags.f_contiguous):
        raise ValueError(
            f"img: expected a 2-D frame, C-contiguous or its transposed view, got shape {img.shape}"
        )
    if img.dtype not in (np.uint8, np.uint16) or not img.dtype.isnative:
        raise ValueError(f"img: expected native uint8 or uint16, got {img.dtype}")
    return _saturated_centres(
        img,
        np.ascontiguousarray(lines, np.int64),
        np.ascontiguousarray(cols, np.int64),
        float(sat),
        int(reach),
        _FLAT_CURVATURE,
    )


# Sums may be reassociated (vectorised); NaN and infinity keep their meaning.
@njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _steger_points(
    img, line, pos, slope, level, saturated, sigma, R
):  # pragma: no cover - compiled
    H, W = img.shape
    n = line.size
    out = pos.copy()
    P = 2 * R + 1
    inv_s2 = 1.0 / (sigma * sigma)
    # Across the lines: the sampled Gaussian and its derivatives at -j, all scaled by one
    # factor (as along the line) so that the Hessian's mixed and pure terms compare.
    kv0 = np.empty(P)
    kv1 = np.empty(P)
    kv2 = np.empty(P)
    e = np.empty(P)  # exp(-j^2 / 2 sigma^2): the along-line kernel's shape at delta = 0
    for k in range(P):
        j = k - R
        e[k] = np.exp(-0.5 * j * j * inv_s2)
        x = -float(j)
        kv0[k] = e[k]
        kv1[k] = -x * inv_s2 * e[k]
        kv2[k] = (x * x * inv_s2 - 1.0) * inv_s2 * e[k]
    total = kv0.sum()
    for k in range(P):
        kv0[k] /= total
        kv1[k] /= total
        kv2[k] /= total
    # Sampled and truncated, the derivative kernels do not sum to zero: the local background
    # level is taken out of the responses through their sums (below).
    sv1 = kv1.sum()
    sv2 = kv2.sum()
    g0 = np.empty(P)
    g1 = np.empty(P)
    g2 = np.empty(P)
    for i in range(n):
        if saturated[i]:
            continue  # the saturated run's centre stays: the Taylor model of a flat top is wrong
        p = pos[i]
        c0 = int(np.rint(p))
        if c0 < R or c0 >= W - R:
            continue
        delta = p - c0
        # Along the line, the kernels at the fast estimate: x = delta - j, so
        # exp(-x^2 / 2 s^2) = exp(-delta^2 / 2 s^2) exp(delta j / s^2) exp(-j^2 / 2 s^2); the
        # first factor cancels in the normalisation, the second is a power of one exponential.
        q = np.exp(delta * inv_s2)
        q_inv = 1.0 / q
        f = 1.0
        for _ in range(R):
            f *= q_inv
        s0 = 0.0
        for k in range(P):
            g0[k] = e[k] * f
            s0 += g0[k]
            f *= q
        s0 = 1.0 / s0
        for k in range(P):
            x = delta - (k - R)
            g0[k] *= s0
            g1[k] = -x * inv_s2 * g0[k]
            g2[k] = (x * x * inv_s2 - 1.0) * inv_s2 * g0[k]
        r = line[i]
        rows_in = r >= R and r < H - R
        # Along the line with the point's kernels on each row of the patch, then across the
        # rows with the fixed ones. (Slices: indices known to be >= 0 compile to plain loads.)
        ru = ruu = rv = ruv = rvv = r1 = r2 = 0.0
        kr0, kr1 = (0, P) if rows_in else (R, R + 1)
        for kr in range(kr0, kr1):
            seg = img[r + kr - R, c0 - R : c0 + R + 1]
            a0 = a1 = a2 = 0.0
            for k in range(P):
                v = np.float64(seg[k])
                a0 += g0[k] * v
                a1 += g1[k] * v
                a2 += g2[k] * v
            ru += kv0[kr] * a1
            ruu += kv0[kr] * a2
            rv += kv1[kr] * a0
            ruv += kv1[kr] * a1
            rvv += kv2[kr] * a0
            if kr == R:
                r1 = a1
                r2 = a2
        # The local background: its level leaks through the kernels' sums (at 120 grey levels
        # 0.004 -> 0.021 px RMS), its slope along the line biases the gradient of an asymmetric
        # profile.
        b = level[i]
        sg1 = 0.0
        sg2 = 0.0
        for k in range(P):
            sg1 += g1[k]
            sg2 += g2[k]
        ru -= b * sg1 + slope[i]
        ruu -= b * sg2
        rv -= b * sv1
        ruv -= b * sv1 * sg1
        rvv -= b * sv2
        r1 -= b * sg1 + slope[i]
        r2 -= b * sg2
        if rows_in:
            # Cross direction: the eigenvector of the Hessian's most negative eigenvalue.
            disc = np.sqrt(0.25 * (ruu - rvv) ** 2 + ruv * ruv)
            lam = 0.5 * (ruu + rvv) - disc
            nu = ruv
            nv = lam - ruu
            if abs(nu) + abs(nv) < 1e-12:  # the other form where this one degenerates
                nu = lam - rvv
                nv = ruv
            norm = np.sqrt(nu * nu + nv * nv)
            if norm > 0.0:
                nu /= norm
                nv /= norm
            if lam < 0.0 and abs(nu) > 0.3:
                # Taylor step along the normal, then slid along the stripe (tangent (-nv, nu))
                # back onto the scan line.
                t = -(ru * nu + rv * nv) / lam
                on_line = t / nu  # t nu + (t nv / nu) nv, with nu^2 + nv^2 = 1
                if abs(on_line) < 1.5:
                    out[i] = p + on_line
                    continue
        # 1-D estimate along the centre row (lines at the image's top and bottom, or where
        # the 2-D step does not apply).
        if r2 < 0.0:
            t1 = -r1 / r2
            if abs(t1) < 1.5:
                out[i] = p + t1
    return out


def steger_points(
    img: NDArray,
    line: NDArray,
    pos: NDArray,
    slope: NDArray,
    level: NDArray,
    saturated: NDArray,
    sigma: float,
) -> NDArray:
    """Steger's centre at each fast-mode peak, as :func:`scanner.stripe.precise._refine_precise`.

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8, uint16 or float32
        Working-orientation frame (rows are scan lines), C-contiguous or the transposed view
        of a C-contiguous frame.
    line, pos, slope, level : ndarray, shape (N,)
        Each peak's line, fast-mode centre along it (px), local background slope (grey
        levels per px) and the background's level at the peak (grey levels).
    saturated : ndarray, shape (N,), bool
        Peaks that keep their fast-mode centre.
    sigma : float
        The smoothing Gaussian's standard deviation, px (``> 0``).

    Returns
    -------
    ndarray, shape (N,), float64
        The refined centres along the lines; the fast ones where neither the 2-D nor the 1-D
        step applies.
    """
    if img.ndim != 2 or not (img.flags.c_contiguous or img.flags.f_contiguous):
        raise ValueError(
            f"img: expected a 2-D frame, C-contiguous or its transposed view, got shape {img.shape}"
        )
    if img.dtype not in (np.uint8, np.uint16, np.float32) or not img.dtype.isnative:
        raise ValueError(f"img: expected native uint8, uint16 or float32, got {img.dtype}")
    if not sigma > 0:
        raise ValueError(f"sigma: expected > 0, got {sigma}")
    R = int(np.ceil(2.5 * sigma))
    return _steger_points(
        img,
        np.ascontiguousarray(line, np.int64),
        np.ascontiguousarray(pos, np.float64),
        np.ascontiguousarray(slope, np.float64),
        np.ascontiguousarray(level, np.float64),
        np.ascontiguousarray(saturated, np.bool_),
        float(sigma),
        R,
    )
