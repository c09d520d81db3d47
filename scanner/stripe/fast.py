"""Fast mode: the windowed centre of gravity of every scan line's peak.

A window gathered around each integer peak column, a linear local background (from two flank
pixels on each side) subtracted, and the centre of gravity of what remains. The sums are
linear in the window's pixels, so a whole frame's peaks take one matrix product
(:func:`_measure_many`); the uncommon peaks (a window at the image border, saturation, two
maxima in one window) are measured one by one (:func:`_measure`), with the three-point
Gaussian estimator or the saturated run's centre. Where numba imports, a frame's primary peaks
come from the compiled kernel instead (:func:`_measure_lines`, :mod:`scanner.stripe.kernels`):
the same measurement in one pass per line, without the intermediate arrays; and the choice of
the uncommon peaks, the low-contrast flag and the saturated runs' centres are compiled too
(:func:`_uncommon_lines`, :func:`flag_low_contrast`,
:func:`scanner.stripe.kernels.saturated_centres`), each beside the NumPy path it equals.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
from numpy.typing import NDArray

from scanner.core.jit import njit
from scanner.stripe.kernels import (
    _FLAT_CURVATURE,
    HAVE_NUMBA,
    _kth_smallest,
    kth_smallest,
    line_peaks,
    saturated_centres,
)
from scanner.stripe.profile import _FWHM_PER_SIGMA, StripeFlag, StripeOptions, _Peaks


def _saturation_level(img: NDArray, options: StripeOptions) -> float:
    if options.saturation is not None:
        return float(options.saturation)
    if img.dtype == np.uint8:
        return 255.0
    if img.dtype == np.uint16:
        return 65535.0
    return float("inf")


def _contiguous(img: NDArray) -> NDArray:
    """``img`` with contiguous rows: itself, or a copy of a transposed view (by OpenCV's
    blocked transposition of the stored frame: several times faster than NumPy's copy)."""
    if img.flags.c_contiguous:
        return img
    if img.flags.f_contiguous and img.dtype in (np.uint8, np.uint16, np.float32):
        return cv2.transpose(img.T)
    return np.ascontiguousarray(img)


def _gather(img: NDArray, rows: NDArray, cols: NDArray) -> NDArray:
    """``img[rows, cols]`` (broadcast index arrays inside the image), from the flat buffer of a
    C-contiguous frame; a transposed view is read in place, not copied whole."""
    if img.flags.c_contiguous:
        return img.reshape(-1).take(rows * img.shape[1] + cols)
    return img[rows, cols]


def _measure(
    img: NDArray,
    lines: NDArray,
    cols: NDArray,
    hw: int,
    sat: float,
    count_above: float | None = None,
    typical: float | None = None,
) -> tuple[_Peaks, NDArray | None]:
    """Centre of gravity around integer peak columns ``cols`` on ``lines`` (vectorised).

    Returns the peaks and, when ``count_above`` is given, how many window pixels exceed it.
    ``typical``: the batch's typical width (windows wider than 1.3 times it are searched for a
    second maximum); ``None``: the median width of this batch.
    """
    W = img.shape[1]
    off = np.arange(-hw - 2, hw + 3)
    c = cols[:, None] + off
    near = np.flatnonzero((cols < hw + 2) | (cols >= W - hw - 2))
    if near.size:
        inside_near = (c[near] >= 0) & (c[near] < W)
        np.clip(c, 0, W - 1, out=c)
    vals = _gather(img, lines[:, None], c).astype(np.float32)
    ones = np.ones(2 * hw + 1, np.float32)
    counts = None
    if count_above is not None:
        counts = (vals[:, 2:-2] > count_above).astype(np.float32) @ ones
    peak = vals[:, hw + 2].copy()

    # Linear background from two flank pixels each side (a missing side: the other one, flat).
    left = 0.5 * (vals[:, 0] + vals[:, 1])
    right = 0.5 * (vals[:, -1] + vals[:, -2])
    if near.size:
        lf_ok = inside_near[:, 0] & inside_near[:, 1]
        rf_ok = inside_near[:, -1] & inside_near[:, -2]
        ln, rn = left[near], right[near]
        left[near] = np.where(lf_ok, ln, rn)
        right[near] = np.where(rf_ok, rn, ln)
    xc = off[2:-2].astype(np.float32)
    slope = (right - left) * np.float32(1.0 / (2 * hw + 3))
    mean = 0.5 * (left + right)
    w = vals[:, 2:-2]
    w -= mean[:, None]
    w -= slope[:, None] * xc[None, :]
    border = np.zeros(len(cols), bool)
    if near.size:
        # Symmetric window about the peak pixel where the border cuts it.
        core_in = inside_near[:, 2:-2]
        sym_near = core_in & core_in[:, ::-1]
        w[near] = np.where(sym_near, w[near], 0.0)
        border[near] = ~np.all(core_in, axis=1)
    contrast = peak - mean

    sw = w @ ones
    ok = sw > 0
    safe = np.where(ok, sw, 1.0)
    mu = (w @ xc) / safe
    var = (w @ (xc * xc)) / safe - mu * mu
    width = _FWHM_PER_SIGMA * np.sqrt(np.maximum(var, 0.0))
    pos = cols + mu.astype(np.float64)
    flags = np.zeros(len(cols), np.uint8)

    # A second maximum inside the window (a reflection or another segment a few pixels away)
    # would pull the centre of gravity between the two: measure those on the peak alone. Only
    # windows wider than usual can hold two maxima, so only those are searched.
    double = np.zeros(len(cols), bool)
    if len(cols) > 2 or typical is not None:
        if typical is None:
            typical = np.partition(width, width.size // 2)[width.size // 2]
        wide = np.flatnonzero(width > 1.3 * typical)
        if wide.size:
            ww = w[wide]
            inner = ww[:, 1:-1]
            level = (0.3 * np.maximum(contrast[wide], 0.0))[:, None]
            local_max = (inner > ww[:, :-2]) & (inner >= ww[:, 2:]) & (inner > level)
            double[wide] = np.count_nonzero(local_max, axis=1) > 1
    else:
        inner = w[:, 1:-1]
        level = (0.3 * np.maximum(contrast, 0.0))[:, None]
        local_max = (inner > w[:, :-2]) & (inner >= w[:, 2:]) & (inner > level)
        double = np.count_nonzero(local_max, axis=1) > 1
    if np.any(double):
        flags[double] |= np.uint8(StripeFlag.AMBIGUOUS)

    use3 = border | double
    if np.any(use3):
        # Three-point Gaussian (log-parabola) on background-subtracted values: unbiased for a
        # Gaussian profile whatever the window, needs only the two neighbours.
        b = np.flatnonzero(use3)
        k = hw  # index of the peak pixel inside w
        a0 = w[b, k - 1].astype(np.float64)
        a1 = w[b, k].astype(np.float64)
        a2 = w[b, k + 1].astype(np.float64)
        good = (a0 > 0) & (a1 > 0) & (a2 > 0)
        la0, la1, la2 = (np.log(np.where(good, a, 1.0)) for a in (a0, a1, a2))
        den = la0 - 2 * la1 + la2
        delta = np.where(good & (den < 0), 0.5 * (la0 - la2) / np.where(den < 0, den, -1.0), 0.0)
        pos[b] = np.where(good & (np.abs(delta) <= 1.0), cols[b] + delta, pos[b])
        flags[b[border[b]]] |= np.uint8(StripeFlag.BORDER)

    saturated = peak >= sat
    if np.any(saturated):
        s_idx = np.flatnonzero(saturated)
        pos[s_idx], width[s_idx] = _saturated(img, lines[s_idx], cols[s_idx], sat)
        flags[s_idx] |= np.uint8(StripeFlag.SATURATED)
    contrast = np.where(ok, contrast, 0.0).astype(np.float32)
    peaks = _Peaks(
        lines.astype(np.int64, copy=False),
        pos,
        peak,
        contrast,
        width.astype(np.float32),
        flags,
        slope,
    )
    return peaks, counts


@functools.lru_cache(maxsize=32)
def _window_matrix(hw: int) -> NDArray:
    """``(6, 2 hw + 5)`` rows giving, from a window's pixels, quantities linear in them.

    Peak pixel; contrast (peak minus the linear background's level at the peak); background
    slope; and the background-subtracted window's sum and first and second moments about the
    peak pixel (``x = -hw..hw``). The background is the line through the means of the two
    flank pixels on each side (at ``x = -/+ (hw + 1.5)``).
    """
    n = 2 * hw + 5
    x = np.arange(-hw, hw + 1, dtype=np.float64)
    left = np.zeros(n)
    left[:2] = 0.5
    right = left[::-1]
    mean = 0.5 * (left + right)
    slope = (right - left) / (2 * hw + 3)
    core = np.zeros(n)
    core[2:-2] = 1.0
    peak = np.zeros(n)
    peak[hw + 2] = 1.0
    xw = np.zeros(n)
    xw[2:-2] = x
    x2 = float(np.sum(x * x))
    m = np.stack(
        [
            peak,
            peak - mean,
            slope,
            core - (2 * hw + 1) * mean,  # sum x^0 (w - mean - slope x); sum x = 0
            xw - x2 * slope,  # sum x (w - mean - slope x)
            xw * xw - x2 * mean,  # sum x^2 (w - mean - slope x); sum x^3 = 0
        ]
    ).astype(np.float32)
    m.flags.writeable = False
    return m


def _row_windows(img: NDArray, size: int, length: int | None = None) -> NDArray:
    """Every run of ``size`` consecutive pixels of the flat image, as rows of a view."""
    flat = img.reshape(-1)
    rows = flat.size - size + 1 if length is None else length
    step = flat.strides[0]
    return np.ndarray((rows, size), flat.dtype, flat, 0, (step, step))


def _measure_many(
    img: NDArray,
    lines: NDArray,
    cols: NDArray,
    hw: int,
    sat: float,
    clear: NDArray | None = None,
    typical: float | None = None,
) -> _Peaks:
    """:func:`_measure` for a whole frame's peaks, the common case by one matrix product.

    The background-subtracted centre of gravity's sums are linear in the window's pixels, so
    those of every peak come from one product of the gathered windows with a fixed matrix
    (:func:`_window_matrix`). The uncommon peaks (a window reaching the border, saturation, a
    window wider than usual that may hold two maxima) are measured again by :func:`_measure`,
    with the same typical width, and replace those. ``clear``: an array of the image's shape
    whose pixels in each peak's window ``cols - hw .. cols + hw`` (clipped to the image) are
    set to 0. ``typical``: the typical width; ``None``: the median over the windows inside the
    image.
    """
    img = _contiguous(img)  # a transposed view: copied (runs of pixels are read below)
    n = cols.size
    W = img.shape[1]
    if n <= 2 or W < 2 * hw + 5:
        if clear is not None:
            _clear_windows(clear, lines, cols, hw)
        return _measure(img, lines, cols, hw, sat)[0]
    # Windows reaching past the border (two reductions decide the common case: none).
    any_near = bool(cols.min() < hw + 2 or cols.max() > W - hw - 3)
    near = (cols < hw + 2) | (cols > W - hw - 3) if any_near else None
    start = lines * W + (np.clip(cols, hw + 2, W - hw - 3) if any_near else cols)
    start -= hw + 2
    vals = _row_windows(img, 2 * hw + 5)[start]  # one gather of n runs of pixels
    if clear is not None:
        if any_near:
            _clear_windows(clear, lines, cols, hw)
        else:
            _row_windows(clear, 2 * hw + 1)[start + 2] = 0  # cols - hw .. cols + hw
    # float32 product: exact for 8-bit frames (integer sums below 2**24).
    res = _window_matrix(hw) @ vals.T.astype(np.float32)
    peak, contrast, slope, s0 = res[0], res[1], res[2], res[3]
    if not s0.min() > 0:  # also when NaN
        ok = s0 > 0
        s0 = np.where(ok, s0, np.float32(1.0))
        contrast[~ok] = 0.0
    mu, var = res[4:] / s0
    var -= mu * mu
    np.maximum(var, 0.0, out=var)
    width = np.sqrt(var, out=var)
    width *= np.float32(_FWHM_PER_SIGMA)
    peaks = _Peaks(
        lines.astype(np.int64, copy=False),
        cols + mu,
        peak,
        contrast,
        width,
        np.zeros(n, np.uint8),
        slope,
    )
    return _remeasure_uncommon(img, peaks, cols, near, hw, sat, typical)


def _remeasure_uncommon(
    img: NDArray,
    peaks: _Peaks,
    cols: NDArray,
    near: NDArray | None,
    hw: int,
    sat: float,
    typical: float | None,
) -> _Peaks:
    """Measure the uncommon ones of a batch's peaks again with :func:`_measure` (in place).

    ``peaks``: the common-case measurement of every peak; ``near``: windows reaching past the
    border (``None``: none does); ``typical``: the typical width (``None``: the median over the
    windows inside the image). Uncommon: near the border, saturated, or wider than 1.3 times
    the typical width.
    """
    lines, width, peak = peaks.line, peaks.width, peaks.peak
    if HAVE_NUMBA and width.dtype == np.float32 and peak.dtype == np.float32:
        near_or_none = near if near is not None else np.zeros(width.size, np.bool_)
        any_far, typical, special = _uncommon_lines(
            width, peak, near_or_none, np.nan if typical is None else float(typical), float(sat)
        )
        if not any_far:  # no window inside the image
            return _measure(img, lines, cols, hw, sat)[0]
    else:
        if typical is None:
            far_w = width[~near] if near is not None else width
            if far_w.size == 0:
                return _measure(img, lines, cols, hw, sat)[0]
            typical = kth_smallest(far_w, far_w.size // 2)
        odd = width > 1.3 * typical
        if peak.max() >= sat:
            odd |= peak >= sat
        if near is not None:
            odd |= near
        special = np.flatnonzero(odd)
    if special.size:
        sub, _ = _measure(img, lines[special], cols[special], hw, sat, typical=typical)
        for k in _Peaks.__dataclass_fields__:
            getattr(peaks, k)[special] = getattr(sub, k)
    return peaks


@njit(cache=True, nogil=True)
def _uncommon_lines(width, peak, near, typical, sat):  # pragma: no cover - compiled
    """:func:`_remeasure_uncommon`'s choice in one pass: whether a window lies inside the
    image (``False``: nothing else is decided), the typical width (NaN ``typical``: the median
    of the widths not ``near``, NaN sorting last) and the indices of the peaks near the
    border, saturated, or wider than 1.3 times it. The limits are compared in float32, as
    NumPy compares a float32 array with a Python float."""
    n = width.size
    if typical != typical:
        far = np.empty(n, np.float32)
        m = 0
        for i in range(n):
            if not near[i]:
                far[m] = width[i]
                m += 1
        if m == 0:
            return False, np.nan, np.empty(0, np.int64)
        typical = np.float64(_kth_smallest(far[:m], m // 2))
    wide = np.float32(1.3 * typical)
    top = np.float32(sat)
    special = np.empty(n, np.int64)
    k = 0
    for i in range(n):
        if width[i] > wide or peak[i] >= top or near[i]:
            special[k] = i
            k += 1
    return True, typical, special[:k]


@njit(cache=True, nogil=True)
def _flag_low_contrast(contrast, flags, ratio, bit):  # pragma: no cover - compiled
    """OR ``bit`` into ``flags`` where ``contrast`` is below ``ratio`` times its median (the
    upper middle value; NaN sorts last, as in ``np.partition``), compared in float32."""
    typical = _kth_smallest(contrast, contrast.size // 2)
    low = np.float32(ratio * np.float64(typical))
    for i in range(contrast.size):
        if contrast[i] < low:
            flags[i] |= bit


def flag_low_contrast(contrast: NDArray, flags: NDArray, ratio: float, bit: int) -> None:
    """OR ``bit`` into ``flags`` (in place) where ``contrast`` is below ``ratio`` times the
    median contrast.

    Parameters
    ----------
    contrast : ndarray, shape (N,), float32
        The peaks' contrasts, ``N >= 1``.
    flags : ndarray, shape (N,), uint8
        Their flags, changed in place.
    ratio : float
        Fraction of the median below which a peak is of low contrast.
    bit : int
        The flag to set.
    """
    if HAVE_NUMBA and contrast.dtype == np.float32 and flags.dtype == np.uint8:
        _flag_low_contrast(contrast, flags, float(ratio), np.uint8(bit))
        return
    typical = kth_smallest(contrast, contrast.size // 2)
    if not contrast.min() >= ratio * typical:  # NaN: look
        flags[contrast < ratio * typical] |= np.uint8(bit)


def _measure_lines(
    img: NDArray,
    hw: int,
    sat: float,
    thr: float = float("inf"),
    step: int = 1,
    typical: float | None = None,
) -> tuple[_Peaks, NDArray, NDArray] | None:
    """The primary peak of every ``step``-th line by the compiled kernel, or ``None``.

    The same peaks as :func:`_measure_many` of ``img[::step].argmax(axis=1)`` (the kernel
    measures the common windows, :func:`_measure` the uncommon ones), with the peak columns and
    whether each line holds a pixel above ``thr`` outside its primary window ``cols - hw ..
    cols + hw``. ``img``: C-contiguous, or the transposed view of a C-contiguous frame (its
    lines are the stored columns: read in place). ``None`` where the kernel does not apply:
    numba missing, a dtype other than uint8, uint16 or float32, another layout, NaN in the
    frame, a frame narrower than a window, at most two lines, or a negative ``thr`` for an
    unsigned frame.
    """
    H, W = img.shape
    if (
        not HAVE_NUMBA
        or img.dtype not in (np.uint8, np.uint16, np.float32)
        or not (img.flags.c_contiguous or img.flags.f_contiguous)
        or W < 2 * hw + 5
        or (H + step - 1) // step <= 2
        or (img.dtype.kind == "u" and thr < 0)
    ):
        return None
    if img.dtype == np.float32 and np.isnan(img.max()):
        return None
    cols, pos, peak, contrast, slope, width, near, other = line_peaks(img, step, hw, thr)
    lines = np.arange(0, H, step)
    peaks = _Peaks(lines, pos, peak, contrast, width, np.zeros(lines.size, np.uint8), slope)
    peaks = _remeasure_uncommon(img, peaks, cols, near, hw, sat, typical)
    return peaks, cols, other


def _clear_windows(clear: NDArray, lines: NDArray, cols: NDArray, hw: int) -> None:
    W = clear.shape[1]
    c = np.clip(cols[:, None] + np.arange(-hw, hw + 1), 0, W - 1)
    clear.reshape(-1)[c + (lines * W)[:, None]] = 0


def _saturated(img: NDArray, lines: NDArray, cols: NDArray, sat: float) -> tuple[NDArray, NDArray]:
    """:func:`_saturated_centres` by the compiled kernel where it applies (numba, an 8- or
    16-bit frame stored either way), by NumPy otherwise."""
    if (
        HAVE_NUMBA
        and img.dtype in (np.uint8, np.uint16)
        and (img.flags.c_contiguous or img.flags.f_contiguous)
    ):
        return saturated_centres(img, lines, cols, sat)
    return _saturated_centres(img, lines, cols, sat)


def _saturated_centres(
    img: NDArray, lines: NDArray, cols: NDArray, sat: float, reach: int = 24
) -> tuple[NDArray, NDArray]:
    """Centre of the saturated run through ``cols`` and the run's length (the NumPy reference
    of :func:`scanner.stripe.kernels.saturated_centres`).

    The run's midpoint is refined with the unsaturated flanks: the logarithm of a Gaussian is a
    parabola, fitted by weighted least squares (weights ``w**2``, Caruana's weighting) to the
    unsaturated pixels above 5 % of the saturation contrast on both sides, and its vertex taken.
    Where that fit is not possible (one flank missing, a flat profile), the midpoint stays.
    """
    W = img.shape[1]
    off = np.arange(-reach, reach + 1)
    c = cols[:, None] + off
    inside = (c >= 0) & (c < W)
    vals = _gather(img, lines[:, None], np.clip(c, 0, W - 1)).astype(np.float64)
    vals = np.where(inside, vals, -np.inf)
    on = vals >= sat
    mid = reach
    # Run length to the right and to the left of the peak pixel (cumulative product trick).
    n_right = np.cumprod(on[:, mid:], axis=1).sum(axis=1) - 1
    n_left = np.cumprod(on[:, mid::-1], axis=1).sum(axis=1) - 1
    a = mid - n_left  # first saturated index
    b = mid + n_right  # last saturated index
    centre = 0.5 * (a + b)
    run = (b - a + 1).astype(np.float64)

    # Background: the lower of the mean levels at the window's two ends (inside the image).
    ends = []
    for sl in (slice(0, 6), slice(-6, None)):
        fin = inside[:, sl]
        n_fin = fin.sum(axis=1)
        level = np.where(fin, vals[:, sl], 0.0).sum(axis=1) / np.maximum(n_fin, 1)
        ends.append(np.where(n_fin > 0, level, np.inf))
    bg = np.minimum(ends[0], ends[1])
    bg = np.where(np.isfinite(bg), bg, 0.0)
    w = vals - bg[:, None]
    x = off[None, :].astype(np.float64)
    # Flank pixels: unsaturated, inside, above 5 % of the contrast, within 3 run-lengths + 4 px.
    span = (3 * run + 4)[:, None]
    dist = np.abs(x - (centre - mid)[:, None])
    use = np.isfinite(vals) & ~on & (w > 0.05 * (sat - bg)[:, None]) & (dist <= span)
    left_n = np.count_nonzero(use & (x < (a - mid)[:, None]), axis=1)
    right_n = np.count_nonzero(use & (x > (b - mid)[:, None]), axis=1)
    wt = np.where(use, np.maximum(w, 1e-9) ** 2, 0.0)
    y = np.log(np.maximum(w, 1e-9))
    xc = x - (centre - mid)[:, None]  # centred for conditioning
    m = np.empty((len(cols), 3, 3))
    r = np.empty((len(cols), 3))
    sums = []
    term = wt
    for k in range(5):  # sum w x^k, k = 0..4: the normal equations' distinct entries
        if k:
            term = term * xc
        sums.append(term.sum(axis=1))
    for i in range(3):
        for j in range(3):
            m[:, i, j] = sums[i + j]
    wy = wt * y
    r[:, 0] = wy.sum(axis=1)
    r[:, 1] = (wy * xc).sum(axis=1)
    r[:, 2] = (wy * xc * xc).sum(axis=1)
    fit_ok = (left_n >= 1) & (right_n >= 1) & (left_n + right_n >= 3)
    refined = centre.copy()
    if np.any(fit_ok):
        k = np.flatnonzero(fit_ok)
        det = np.linalg.det(m[k])
        good = np.abs(det) > 1e-12
        coef = np.zeros((k.size, 3))
        coef[good] = np.linalg.solve(m[k][good], r[k][good][:, :, None])[:, :, 0]
        # A parabola whose curvature is rounding (flanks all at one level: a saturated run on
        # paper about as bright) has no vertex.
        c2 = coef[:, 2]
        curved = c2 < -_FLAT_CURVATURE * np.maximum(np.abs(coef[:, 0]), 1.0)
        vertex = np.where(curved, -coef[:, 1] / (2 * np.where(curved, c2, -1.0)), np.nan)
        plausible = good & np.isfinite(vertex) & (np.abs(vertex) <= 0.5 * run[k] + 0.5)
        refined[k] = np.where(plausible, centre[k] + vertex, centre[k])
    return cols + refined - mid, run
