"""Compiled kernels of the ring detector's fine stage: profiles across the printed lines.

The fine stage measures each ring along short profiles normal to it, sampled every 0.125 px
on the cubic spline of the darkness map.

:func:`spline_along` samples a cubic-spline coefficient image along lines, as
:func:`scipy.ndimage.map_coordinates` does (``order=3, prefilter=False``, ``mode="constant"``)
to rounding, without building the samples' points.

:func:`line_centres` finds the centre of the dark line in each of those profiles: the
centroid, over a window about it, of the darkness above the window ends' mean, iterated.

:func:`spline_along` and :func:`line_centres` are the plain definitions (every sample of
every profile); the detector calls :func:`profile_line_centres`, which gives what
``line_centres(spline_along(...))`` gives, to the bit, sampling only what the centres
read: the samples within the search (for the starting maximum) and those the centroid
windows reach. The profiles span a search and a window on
each side, and the window about a centre found near 0 stays within the search, so about
half of the samples are never read (on the modern cell's views 53 % are not). That takes
the profiles' share of a detection from about 88 to 76 ms per view on the forty-second
session's host (``benchmarks/RESULTS.md``).

:func:`window_touches` tells which of those profiles' windows meet a mask (a laser stripe,
glare).

Compiled with numba where it imports (:data:`HAVE_NUMBA`); without it the same code runs as
Python (slowly, but with the same results).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanner.core.jit import HAVE_NUMBA, njit

__all__ = [
    "HAVE_NUMBA",
    "line_centres",
    "profile_line_centres",
    "spline_along",
    "window_touches",
]


@njit(cache=True, nogil=True, inline="always")
def _mirror(i, n):  # pragma: no cover - compiled
    """Index ``i`` folded into ``0 .. n - 1`` by mirroring about the end samples."""
    if n == 1:
        return 0
    period = 2 * n - 2
    i = abs(i) % period
    return period - i if i >= n else i


@njit(cache=True, nogil=True, inline="always")
def _bspline3_weights(f):  # pragma: no cover - compiled
    """The cubic B-spline's weights of the samples at offsets -1, 0, 1, 2 from ``floor``."""
    f2 = f * f
    f3 = f2 * f
    return (
        (1.0 - f) ** 3 / 6.0,
        (3.0 * f3 - 6.0 * f2 + 4.0) / 6.0,
        (-3.0 * f3 + 3.0 * f2 + 3.0 * f + 1.0) / 6.0,
        f3 / 6.0,
    )


@njit(cache=True, nogil=True, inline="always")
def _fill(coef, flat, ys, xs, wy, wx, out, j_lo, j_hi):  # pragma: no cover - compiled
    """Samples ``j_lo:j_hi`` of a profile into ``out``: the spline at its points ``(xs[j],
    ys[j])`` in the coefficients' pixels, with their weights ``wx[j]``, ``wy[j]``; 0 outside
    (NaN too). (One loop with the branches inside: LLVM vectorises it; a function per sample
    compiles to code three times slower.)"""
    h, w = coef.shape
    for j in range(j_lo, j_hi):
        y = ys[j]
        x = xs[j]
        if not (y >= 0.0 and y <= h - 1.0 and x >= 0.0 and x <= w - 1.0):
            out[j] = 0.0
            continue
        iy = int(np.floor(y))
        ix = int(np.floor(x))
        wx0 = wx[j, 0]
        wx1 = wx[j, 1]
        wx2 = wx[j, 2]
        wx3 = wx[j, 3]
        if iy >= 1 and iy <= h - 3 and ix >= 1 and ix <= w - 3:
            # All 16 coefficients inside (the common case): no folding.
            k = (iy - 1) * w + ix - 1
            s0 = wx0 * flat[k] + wx1 * flat[k + 1] + wx2 * flat[k + 2] + wx3 * flat[k + 3]
            k += w
            s1 = wx0 * flat[k] + wx1 * flat[k + 1] + wx2 * flat[k + 2] + wx3 * flat[k + 3]
            k += w
            s2 = wx0 * flat[k] + wx1 * flat[k + 1] + wx2 * flat[k + 2] + wx3 * flat[k + 3]
            k += w
            s3 = wx0 * flat[k] + wx1 * flat[k + 1] + wx2 * flat[k + 2] + wx3 * flat[k + 3]
            out[j] = wy[j, 0] * s0 + wy[j, 1] * s1 + wy[j, 2] * s2 + wy[j, 3] * s3
        else:
            c0 = _mirror(ix - 1, w)
            c1 = _mirror(ix, w)
            c2 = _mirror(ix + 1, w)
            c3 = _mirror(ix + 2, w)
            s = 0.0
            for a in range(4):
                row = coef[_mirror(iy - 1 + a, h)]
                s += wy[j, a] * (wx0 * row[c0] + wx1 * row[c1] + wx2 * row[c2] + wx3 * row[c3])
            out[j] = s


@njit(cache=True, nogil=True, inline="always")
def _profile_points(r, px, py, nx, ny, tau, u0, v0, ys, xs, wy, wx, j_lo, j_hi):  # pragma: no cover
    """Points ``j_lo:j_hi`` of profile ``r`` and their weights, in loops without a branch
    (they vectorise). (The points: the same arithmetic as ``p + n * tau`` broadcast in
    NumPy; the origin's whole pixels taken off after it leave the spline's fractions as they
    were.)"""
    for j in range(j_lo, j_hi):
        ys[j] = (py[r] + ny[r] * tau[j]) - v0
        xs[j] = (px[r] + nx[r] * tau[j]) - u0
    for j in range(j_lo, j_hi):
        wy[j, 0], wy[j, 1], wy[j, 2], wy[j, 3] = _bspline3_weights(ys[j] - np.floor(ys[j]))
        wx[j, 0], wx[j, 1], wx[j, 2], wx[j, 3] = _bspline3_weights(xs[j] - np.floor(xs[j]))


@njit(cache=True, nogil=True)
def _spline_along(coef, px, py, nx, ny, tau, u0, v0):  # pragma: no cover - compiled
    n = px.size
    m = tau.size
    flat = coef.ravel()
    out = np.empty((n, m))
    ys = np.empty(m)
    xs = np.empty(m)
    wy = np.empty((m, 4))
    wx = np.empty((m, 4))
    for r in range(n):
        _profile_points(r, px, py, nx, ny, tau, u0, v0, ys, xs, wy, wx, 0, m)
        _fill(coef, flat, ys, xs, wy, wx, out[r], 0, m)
    return out


def _profile_arguments(
    coef: NDArray, points: NDArray, normals: NDArray, tau: NDArray, origin_px: tuple[int, int]
) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray, NDArray, float, float]:
    """The profile kernels' arguments, checked: the coefficients, the points' and normals'
    ``u`` and ``v`` apart, the positions (contiguous float64), the origin's whole pixels."""
    c = np.ascontiguousarray(coef, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    t = np.ascontiguousarray(tau, dtype=np.float64)
    if c.ndim != 2 or p.ndim != 2 or p.shape[1:] != (2,) or n.shape != p.shape or t.ndim != 1:
        raise ValueError(
            "coef, points, normals, tau: expected shapes (H, W), (N, 2), (N, 2), (M,), got "
            f"{c.shape}, {p.shape}, {n.shape}, {t.shape}"
        )
    return (
        c,
        np.ascontiguousarray(p[:, 0]),
        np.ascontiguousarray(p[:, 1]),
        np.ascontiguousarray(n[:, 0]),
        np.ascontiguousarray(n[:, 1]),
        t,
        float(int(origin_px[0])),
        float(int(origin_px[1])),
    )


def spline_along(
    coef: NDArray,
    points: NDArray,
    normals: NDArray,
    tau: NDArray,
    origin_px: tuple[int, int] = (0, 0),
) -> NDArray:
    """The cubic spline with coefficients ``coef`` along lines: profile ``r`` at
    ``points[r] + tau * normals[r]`` (0 outside the coefficients).

    The values of :func:`scipy.ndimage.map_coordinates` (``order=3, prefilter=False``,
    ``cval=0``) at those points, to rounding, without their ``(N, M)`` arrays.
    ``coef`` may be a window of an image whose first pixel is at ``origin_px`` ``(u, v)``
    (whole pixels): the points are in the image's pixels, and where the window's spline
    equals the image's, so do the values, to the last bit.

    Parameters
    ----------
    coef : ndarray, shape (H, W)
        Spline coefficients (:func:`scipy.ndimage.spline_filter` of an image, order 3).
    points, normals : ndarray, shape (N, 2)
        Each line's origin and direction ``(u, v)``, px.
    tau : ndarray, shape (M,)
        Positions along the lines, px.

    Returns
    -------
    ndarray, shape (N, M), float64
    """
    return _spline_along(*_profile_arguments(coef, points, normals, tau, origin_px))


@njit(cache=True, nogil=True)
def _at(prof, r, tau0, step, x):  # pragma: no cover - compiled
    """Row ``r`` of ``prof`` linearly interpolated at ``x`` (clamped to the samples)."""
    f = (x - tau0) / step
    i0 = min(max(int(np.floor(f)), 0), prof.shape[1] - 2)
    w1 = min(max(f - i0, 0.0), 1.0)
    return prof[r, i0] * (1.0 - w1) + prof[r, i0 + 1] * w1


@njit(cache=True, nogil=True)
def _centres(prof, tau, half_window, search):  # pragma: no cover - compiled
    n, m = prof.shape
    tau0 = tau[0]
    step = tau[1] - tau[0]
    c = np.empty(n)
    for r in range(n):
        best = -np.inf
        j_best = 0
        for j in range(m):
            if abs(tau[j]) <= search and prof[r, j] > best:
                best = prof[r, j]
                j_best = j
        c[r] = tau[j_best]
    # Each centre iterated until it moves by less than 1e-4 px (at most 12 times).
    for r in range(n):
        for _ in range(12):
            lo = c[r] - half_window
            hi = c[r] + half_window
            base = 0.5 * (_at(prof, r, tau0, step, lo) + _at(prof, r, tau0, step, hi))
            s = 0.0
            st = 0.0
            j0 = max(int(np.ceil((lo - tau0) / step)) - 1, 0)
            j1 = min(int(np.floor((hi - tau0) / step)) + 2, m)
            for j in range(j0, j1):
                if tau[j] >= lo and tau[j] <= hi:
                    wgt = prof[r, j] - base
                    if wgt > 0.0:
                        s += wgt
                        st += wgt * tau[j]
            x = st / s if s > 0.0 else c[r]
            x = min(max(x, -search), search)
            moved = abs(x - c[r])
            c[r] = x
            if moved < 1e-4:
                break
    contrast = np.empty(n)
    for r in range(n):
        contrast[r] = _at(prof, r, tau0, step, c[r]) - 0.5 * (
            _at(prof, r, tau0, step, c[r] - half_window)
            + _at(prof, r, tau0, step, c[r] + half_window)
        )
    return c, contrast


def line_centres(
    prof: NDArray, tau: NDArray, half_window: float, search: float
) -> tuple[NDArray, NDArray]:
    """Sub-pixel centre of the dark line in each profile, and its contrast.

    Each centre starts at the profile's maximum within ``search`` of 0 and is moved to the
    centroid of the profile above its baseline (the mean of the profile at the window's two
    ends) over ``c - half_window ... c + half_window``, until it moves by less than 1e-4 px
    (at most 12 times); it stays within ``search``.

    Parameters
    ----------
    prof : ndarray, shape (N, M)
        Darkness along each of N profiles, sampled at ``tau``.
    tau : ndarray, shape (M,)
        Evenly spaced, increasing sample positions, px.
    half_window, search : float
        The centroid's half window and the farthest centre from 0, px.

    Returns
    -------
    centre : ndarray, shape (N,)
        Position along the profile, px.
    contrast : ndarray, shape (N,)
        The profile at the centre above the mean at ``centre -+ half_window``.
    """
    prof = np.ascontiguousarray(prof, dtype=np.float64)
    tau = np.ascontiguousarray(tau, dtype=np.float64)
    if prof.ndim != 2 or tau.shape != (prof.shape[1],) or len(tau) < 2:
        raise ValueError(
            f"prof, tau: expected shapes (N, M) and (M,), got {prof.shape}, {tau.shape}"
        )
    return _centres(prof, tau, float(half_window), float(search))


@njit(cache=True, nogil=True, inline="always")
def _extend(prof_in, ys, xs, wy, wx, val, a, b, j_lo, j_hi):  # pragma: no cover - compiled
    """The samples of profile ``r`` made so far are ``val[a:b]``: make those of ``j_lo:j_hi``
    too (clipped to the profile), their points and weights first, so that ``val[a:b]``
    covers both; returns the new ``a, b``. ``prof_in`` is ``(coef, flat, r, px, py, nx, ny,
    tau, u0, v0)``."""
    coef, flat, r, px, py, nx, ny, tau, u0, v0 = prof_in
    j_lo = max(j_lo, 0)
    j_hi = min(j_hi, val.size)
    if j_lo >= j_hi:
        return a, b
    if a >= b:  # nothing made yet
        a = j_lo
        b = j_lo
    if j_lo < a:  # (most windows need no sample more)
        _profile_points(r, px, py, nx, ny, tau, u0, v0, ys, xs, wy, wx, j_lo, a)
        _fill(coef, flat, ys, xs, wy, wx, val, j_lo, a)
    if b < j_hi:
        _profile_points(r, px, py, nx, ny, tau, u0, v0, ys, xs, wy, wx, b, j_hi)
        _fill(coef, flat, ys, xs, wy, wx, val, b, j_hi)
    return min(a, j_lo), max(b, j_hi)


@njit(cache=True, nogil=True, inline="always")
def _at_index(m, tau0, step, x):  # pragma: no cover - compiled
    """The first of the two samples :func:`_at` reads at ``x``."""
    return min(max(int(np.floor((x - tau0) / step)), 0), m - 2)


@njit(cache=True, nogil=True)
def _profile_centres(
    coef, px, py, nx, ny, tau, u0, v0, half_window, search
):  # pragma: no cover - compiled
    """:func:`_centres` of :func:`_spline_along`'s profiles, each sample made before
    :func:`_centres` would read it (the samples made form one run along the profile, grown
    as the window moves): the same arithmetic in the same order."""
    n = px.size
    m = tau.size
    flat = coef.ravel()
    ys = np.empty(m)
    xs = np.empty(m)
    wy = np.empty((m, 4))
    wx = np.empty((m, 4))
    prof = np.empty((1, m))  # (one row, so that _at reads it as _centres does)
    val = prof[0]
    tau0 = tau[0]
    step = tau[1] - tau[0]
    c = np.empty(n)
    contrast = np.empty(n)
    # The samples within the search (one run: tau increases).
    s_lo = 0
    while s_lo < m and not abs(tau[s_lo]) <= search:
        s_lo += 1
    s_hi = s_lo
    while s_hi < m and abs(tau[s_hi]) <= search:
        s_hi += 1
    for r in range(n):
        prof_in = (coef, flat, r, px, py, nx, ny, tau, u0, v0)
        a, b = _extend(prof_in, ys, xs, wy, wx, val, 0, 0, s_lo, s_hi)
        best = -np.inf
        j_best = 0
        for j in range(s_lo, s_hi):
            if val[j] > best:
                best = val[j]
                j_best = j
        cr = tau[j_best]
        for _ in range(12):
            lo = cr - half_window
            hi = cr + half_window
            i_lo = _at_index(m, tau0, step, lo)
            i_hi = _at_index(m, tau0, step, hi)
            j0 = max(int(np.ceil((lo - tau0) / step)) - 1, 0)
            j1 = min(int(np.floor((hi - tau0) / step)) + 2, m)
            a, b = _extend(prof_in, ys, xs, wy, wx, val, a, b, min(i_lo, j0), max(i_hi + 2, j1))
            base = 0.5 * (_at(prof, 0, tau0, step, lo) + _at(prof, 0, tau0, step, hi))
            s = 0.0
            st = 0.0
            for j in range(j0, j1):
                if tau[j] >= lo and tau[j] <= hi:
                    wgt = val[j] - base
                    if wgt > 0.0:
                        s += wgt
                        st += wgt * tau[j]
            x = st / s if s > 0.0 else cr
            x = min(max(x, -search), search)
            moved = abs(x - cr)
            cr = x
            if moved < 1e-4:
                break
        c[r] = cr
        i_lo = _at_index(m, tau0, step, cr - half_window)
        i_hi = _at_index(m, tau0, step, cr + half_window)
        a, b = _extend(prof_in, ys, xs, wy, wx, val, a, b, i_lo, i_hi + 2)
        contrast[r] = _at(prof, 0, tau0, step, cr) - 0.5 * (
            _at(prof, 0, tau0, step, cr - half_window) + _at(prof, 0, tau0, step, cr + half_window)
        )
    return c, contrast


def profile_line_centres(
    coef: NDArray,
    points: NDArray,
    normals: NDArray,
    tau: NDArray,
    half_window: float,
    search: float,
    origin_px: tuple[int, int] = (0, 0),
) -> tuple[NDArray, NDArray]:
    """``line_centres(spline_along(coef, points, normals, tau, origin_px), tau, half_window,
    search)``, to the bit, without the profiles: each sample is made only where the centres
    read it.

    Parameters
    ----------
    coef : ndarray, shape (H, W)
        Spline coefficients of the darkness map (or of its window at ``origin_px``).
    points, normals : ndarray, shape (N, 2)
        Each profile's origin and direction ``(u, v)``, px.
    tau : ndarray, shape (M,)
        Evenly spaced, increasing sample positions along the profiles, px (M >= 2).
    half_window, search : float
        The centroid's half window and the farthest centre from 0, px
        (:func:`line_centres`).
    origin_px : tuple of int
        The coefficients' first pixel ``(u, v)`` in the image (:func:`spline_along`).

    Returns
    -------
    centre : ndarray, shape (N,)
        Position of the dark line along each profile, px.
    contrast : ndarray, shape (N,)
        The profile at the centre above the mean at ``centre -+ half_window``.
    """
    args = _profile_arguments(coef, points, normals, tau, origin_px)
    if len(args[5]) < 2:
        raise ValueError(f"tau: expected at least 2 positions, got {len(args[5])}")
    return _profile_centres(*args, float(half_window), float(search))


@njit(cache=True, nogil=True)
def _touches(mask, px, py, nx, ny, tau, centre, reach):  # pragma: no cover - compiled
    h, w = mask.shape
    m = tau.size
    step = tau[1] - tau[0]
    n_win = int(2 * reach / step) + 2
    out = np.zeros(px.size, dtype=np.bool_)
    for r in range(px.size):
        if not np.isfinite(centre[r]):
            continue
        j0 = min(max(int(np.ceil((centre[r] - reach - tau[0]) / step)), 0), m - 1)
        for q in range(n_win):
            j = min(j0 + q, m - 1)
            if abs(tau[j] - centre[r]) > reach:
                continue
            x = np.rint(px[r] + nx[r] * tau[j])
            y = np.rint(py[r] + ny[r] * tau[j])
            if not (x >= 0.0 and x < w and y >= 0.0 and y < h):  # (NaN too)
                continue
            if mask[int(y), int(x)] != 0:
                out[r] = True
                break
    return out


def window_touches(
    mask: NDArray,
    points: NDArray,
    normals: NDArray,
    tau: NDArray,
    centre: NDArray,
    reach: float,
) -> NDArray:
    """Whether each line's window meets ``mask``: a sample ``points[r] + t normals[r]``,
    ``t`` one of ``tau`` within ``reach`` of ``centre[r]``, on a nonzero pixel (nearest).

    Parameters
    ----------
    mask : ndarray, shape (H, W)
        Nonzero where a window must not reach (a laser stripe, glare).
    points, normals : ndarray, shape (N, 2)
        Each line's origin and direction ``(u, v)``, px.
    tau : ndarray, shape (M,)
        The lines' evenly spaced, increasing sample positions, px.
    centre : ndarray, shape (N,)
        The window's centre on each line, px (a line whose centre is not finite meets
        nothing).
    reach : float
        The window's half width, px.

    Returns
    -------
    ndarray, shape (N,), bool
    """
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    t = np.ascontiguousarray(tau, dtype=np.float64)
    c = np.ascontiguousarray(centre, dtype=np.float64)
    if mask.ndim != 2 or p.ndim != 2 or p.shape[1:] != (2,) or n.shape != p.shape:
        raise ValueError(
            "mask, points, normals: expected shapes (H, W), (N, 2), (N, 2), got "
            f"{mask.shape}, {p.shape}, {n.shape}"
        )
    if t.ndim != 1 or len(t) < 2 or c.shape != (len(p),):
        raise ValueError(f"tau, centre: expected shapes (M >= 2,), (N,), got {t.shape}, {c.shape}")
    return _touches(
        np.ascontiguousarray(mask),
        np.ascontiguousarray(p[:, 0]),
        np.ascontiguousarray(p[:, 1]),
        np.ascontiguousarray(n[:, 0]),
        np.ascontiguousarray(n[:, 1]),
        t,
        c,
        float(reach),
    )
