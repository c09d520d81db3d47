"""Compiled stripe kernels: the fast mode's peaks and windows, the precise mode's Steger step.

:func:`line_peaks` does per line what :func:`scanner.stripe.fast._measure_many` does for a whole
frame with NumPy: the line's maximum (the first one, as :func:`numpy.argmax`), the window of
``2 hw + 5`` pixels around it, the linear background through the two flank pixels on each side,
and the background-subtracted centre of gravity and second moment. It also tells whether any
pixel outside the primary window clears the candidate threshold, which is all the rare
multi-peak lines need to be searched further with NumPy. Windows that reach the image border
are only marked: like every other uncommon peak they are measured by
:func:`scanner.stripe.fast._measure`.

:func:`steger_points` does per point what :func:`scanner.stripe.precise._refine_precise` does
with NumPy for all points at once: the smoothed image's gradient and Hessian at the fast
centre, the Taylor step across the stripe and the slide back onto the scan line.

Compiled with numba where it imports (:data:`HAVE_NUMBA`); without it the callers keep the
NumPy path.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanner.core.jit import HAVE_NUMBA, njit
from scanner.stripe.profile import _FWHM_PER_SIGMA

__all__ = ["HAVE_NUMBA", "line_peaks", "steger_points"]

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


# Sums may be reassociated (vectorised); NaN and infinity keep their meaning.
@njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _steger_points(img, line, pos, slope, saturated, sigma, R):  # pragma: no cover - compiled
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
        # The local background's slope along the line biases the gradient of an asymmetric
        # profile.
        ru -= slope[i]
        r1 -= slope[i]
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
    img: NDArray, line: NDArray, pos: NDArray, slope: NDArray, saturated: NDArray, sigma: float
) -> NDArray:
    """Steger's centre at each fast-mode peak, as :func:`scanner.stripe.precise._refine_precise`.

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8, uint16 or float32, C-contiguous
        Working-orientation frame (rows are scan lines).
    line, pos, slope : ndarray, shape (N,)
        Each peak's line, fast-mode centre along it (px) and local background slope (grey
        levels per px).
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
    if img.ndim != 2 or not img.flags.c_contiguous:
        raise ValueError(f"img: expected a C-contiguous 2-D frame, got shape {img.shape}")
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
        np.ascontiguousarray(saturated, np.bool_),
        float(sigma),
        R,
    )
