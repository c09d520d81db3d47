"""Precise mode: Steger's line detector at each fast-mode centre.

The Gaussian-smoothed image's gradient and Hessian are evaluated *at* the fast estimate
(kernels shifted by its sub-pixel offset); the stripe's cross direction is the Hessian's
dominant eigenvector, the centre the second-order Taylor model's along it, slid along the
stripe back onto the scan line. The ridge's shift by smoothing a curved stripe is subtracted
(:func:`_curvature_shift`).
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import NDArray

from scanner.stripe.kernels import HAVE_NUMBA, steger_points
from scanner.stripe.peaks import _segments
from scanner.stripe.profile import StripeFlag, _Peaks


def _gauss_kernels(x: NDArray, sigma: float) -> tuple[NDArray, NDArray, NDArray]:
    """Sampled Gaussian and its first and second derivatives at ``x`` (any shape)."""
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= np.sqrt(2 * np.pi) * sigma
    g1 = -x / sigma**2 * g
    g2 = (x**2 / sigma**4 - 1.0 / sigma**2) * g
    return g, g1, g2


def _refine_precise(img: NDArray, peaks: _Peaks, sigma: float) -> tuple[NDArray, NDArray]:
    """Steger refinement of ``peaks`` (working orientation). Returns ``(pos, v_offset)``.

    ``pos`` is the centre on the scan line; ``v_offset`` is 0 where the point was slid back onto
    its line and the across-line offset otherwise (kept for stripes parallel to the lines).
    Where numba imports, the compiled kernel does it point by point
    (:func:`scanner.stripe.kernels.steger_points`); this NumPy path stays for frames of other
    types and for platforms without numba.
    """
    sat = (peaks.flags & np.uint8(StripeFlag.SATURATED)) != 0
    level = (peaks.peak - peaks.contrast).astype(np.float64)  # the background at each peak
    if (
        HAVE_NUMBA
        and img.dtype in (np.uint8, np.uint16, np.float32)
        and img.dtype.isnative
        and (img.flags.c_contiguous or img.flags.f_contiguous)
        and not (img.dtype == np.float32 and np.isnan(img.max()))  # NaN: as NumPy treats it
    ):
        pos = steger_points(img, peaks.line, peaks.pos, peaks.slope, level, sat, sigma)
        return pos, np.zeros(pos.size)
    return _refine_numpy(img, peaks, sigma, sat, level)


def _refine_numpy(
    img: NDArray, peaks: _Peaks, sigma: float, sat: NDArray, level: NDArray
) -> tuple[NDArray, NDArray]:
    """:func:`_refine_precise` with NumPy, all points at once (``sat``: saturated peaks,
    ``level``: the background's level at each, grey levels)."""
    H, W = img.shape
    R = int(np.ceil(2.5 * sigma))
    n = peaks.line.size
    pos = peaks.pos.copy()
    voff = np.zeros(n)
    c0 = np.rint(pos).astype(np.int64)
    delta = pos - c0
    j = np.arange(-R, R + 1)
    line = peaks.line
    rows_in = (line >= R) & (line < H - R)
    cols_in = (c0 >= R) & (c0 < W - R)
    # One broadcast index for all patches, ordered (row v, point, column u); rows or columns
    # past the border are clamped by ``clip`` (their points fall back to the 1-D estimate or
    # keep the fast one, below).
    P = j.size
    idx = (j * W)[:, None] + ((line * W + c0)[:, None] + j).reshape(-1)  # (P, n * P)
    patch = img.reshape(-1).take(idx, mode="clip").astype(np.float32)

    # Kernels along the line evaluated at the fast estimate: (I * g')(pos) = sum I(c) g'(pos - c).
    x = (delta[:, None] - j[None, :]).astype(np.float32)
    inv_s2 = np.float32(1.0 / sigma**2)
    x2 = x * x
    x2 *= inv_s2
    g0 = np.exp(np.float32(-0.5) * x2)
    g0 /= (g0 @ np.ones(P, np.float32))[:, None]
    g1 = x * g0
    g1 *= -inv_s2
    x2 -= 1.0
    x2 *= inv_s2
    g2 = x2 * g0
    # Across the lines: the same sampled derivatives, all scaled by one factor (as along the
    # line), so that the Hessian's mixed and pure terms compare.
    kv0, kv1, kv2 = _gauss_kernels(-j.astype(np.float64), sigma)
    kv0, kv1, kv2 = (k * (1.0 / kv0.sum()) for k in (kv0, kv1, kv2))
    centre = (j == 0).astype(np.float64)
    # Seven responses (kernel along v, kernel along u): ru (kv0, g1), ruu (kv0, g2),
    # rv (kv1, g0), ruv (kv1, g1), rvv (kv2, g0) and, on the centre row, r1 (g1), r2 (g2).
    # Along v with the fixed kernels, all points by one matrix product; then along u with each
    # point's own kernels.
    kv = np.stack([kv0, kv0, kv1, kv1, kv2, centre, centre]).astype(np.float32)
    resp = (kv @ patch).reshape(7, n, P)
    resp *= np.stack([g1, g2, g0, g1, g0, g1, g2])
    resp = (resp.reshape(7 * n, P) @ np.ones(P, np.float32)).reshape(7, n)
    ru, ruu, rv, ruv, rvv, r1, r2 = resp
    # The local background: sampled and truncated, the derivative kernels do not sum to zero,
    # so its level leaks into the responses through their sums (at 120 grey levels 0.004 ->
    # 0.021 px RMS) and is taken out; its slope along the line biases the gradient of an
    # asymmetric profile.
    sg1 = g1.astype(np.float64) @ np.ones(P)
    sg2 = g2.astype(np.float64) @ np.ones(P)
    sv1, sv2 = float(kv1.sum()), float(kv2.sum())
    ruu = ruu - level * sg2
    rv = rv - level * sv1
    ruv = ruv - level * sv1 * sg1
    rvv = rvv - level * sv2
    r2 = r2 - level * sg2
    ru = ru - level * sg1 - peaks.slope

    # 1-D estimate along the centre row (lines at the image's top and bottom).
    r1 = r1 - level * sg1 - peaks.slope
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = -r1 / r2
    # 2-D: cross direction = eigenvector of the most negative Hessian eigenvalue.
    tr_half = 0.5 * (ruu + rvv)
    disc = np.sqrt(0.25 * (ruu - rvv) ** 2 + ruv**2)
    lam = tr_half - disc  # most negative
    nu = ruv
    nv = lam - ruu
    # Fall back to the other eigenvector form where this one degenerates.
    alt = np.abs(nu) + np.abs(nv) < 1e-12
    nu = np.where(alt, lam - rvv, nu)
    nv = np.where(alt, ruv, nv)
    norm = np.hypot(nu, nv)
    norm = np.where(norm > 0, norm, 1.0)
    nu, nv = nu / norm, nv / norm
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(ru * nu + rv * nv) / lam
        du, dv = t * nu, t * nv
        # Slide along the stripe (tangent (-nv, nu)) back onto the scan line.
        tu, tv = -nv, nu
        s = -dv / tv
        on_line = du + s * tu
    steep = np.abs(tv) > 0.3
    use2d = rows_in & cols_in & (lam < 0) & np.isfinite(on_line) & steep & (np.abs(on_line) < 1.5)
    use1d = ~use2d & cols_in & (r2 < 0) & np.isfinite(t1) & (np.abs(t1) < 1.5)
    pos = np.where(use2d, pos + on_line, pos)
    pos = np.where(use1d, peaks.pos + t1, pos)
    # Saturated peaks keep the saturated-run centre: the Taylor model of a flat top is wrong.
    if sat.any():
        pos = np.where(sat, peaks.pos, pos)
    return pos, voff


@functools.lru_cache(maxsize=8)
def _local_fit_kernels(k: int) -> tuple[NDArray, NDArray]:
    """Convolution kernels of a least-squares line's slope and parabola's ``x**2`` coefficient
    through ``2 k + 1`` equally spaced samples (reversed for :func:`numpy.convolve`)."""
    x = np.arange(-k, k + 1, dtype=np.float64)
    q = x * x - np.mean(x * x)
    w2 = q / np.sum(q * q)  # least-squares quadratic coefficient
    w1 = x / np.sum(x * x)  # least-squares slope (symmetric window)
    w1, w2 = np.ascontiguousarray(w1[::-1]), np.ascontiguousarray(w2[::-1])
    w1.flags.writeable = False
    w2.flags.writeable = False
    return w1, w2


def _curvature_shift(
    peaks: _Peaks, sigma: float, n_lines: int, link_px: float, k: int = 6
) -> NDArray:
    """Shift of the smoothed ridge of a curved stripe along its scan line, to subtract.

    Smoothing a curved line with a Gaussian of ``sigma`` moves its ridge towards the centre of
    curvature by ``sigma**2 * kappa / 2`` (along the normal), which is
    ``sigma**2 * pos'' / (2 (1 + pos'**2))`` along the scan line. ``pos'`` and ``pos''`` come
    from a least-squares quadratic through the fast centres of the ``2 k + 1`` neighbouring
    lines of the same segment (noise on ``pos''`` is then ~1/20 of the centres' own). Points
    without a full, continuous neighbourhood are left as they are.
    """
    shift = np.zeros(peaks.line.size)
    if peaks.line.size < 2 * k + 1:
        return shift
    # Segments as index arrays, and whether each has one point per line.
    if np.all(peaks.line[1:] > peaks.line[:-1]):
        groups = [(np.arange(peaks.line.size), True)]
    else:
        labels = _segments(peaks, link_px)
        groups = [(np.flatnonzero(labels == lab), False) for lab in np.unique(labels)]
    w1, w2 = _local_fit_kernels(k)
    for sel, unique in groups:
        if sel.size < 2 * k + 1:
            continue
        ln = peaks.line[sel]
        lo, hi = int(ln.min()), int(ln.max())
        span = hi - lo + 1
        if span < 2 * k + 1:
            continue
        if unique:
            one = np.ones(sel.size, bool)
            dense = np.full(span, np.nan)  # NaN: lines without a point
            dense[ln - lo] = peaks.pos[sel]
        else:
            counts = np.bincount(ln - lo, minlength=span)
            dense = np.full(span, np.nan)
            one = counts[ln - lo] == 1
            dense[ln[one] - lo] = peaks.pos[sel[one]]
        # A jump between neighbouring lines (another surface) breaks the neighbourhood.
        steps = np.abs(np.diff(dense)) > link_px
        c2 = np.convolve(dense, w2, mode="same")
        c1 = np.convolve(dense, w1, mode="same")
        valid = np.isfinite(c2) & np.isfinite(c1)
        if steps.any():
            jump = np.zeros(span)
            jump[1:] = np.where(steps, np.nan, 0.0)
            valid &= np.isfinite(np.convolve(jump, np.ones(2 * k + 1), mode="same"))
        valid[:k] = False
        valid[span - k :] = False
        along = np.where(valid, sigma**2 * c2 / (1.0 + c1 * c1), 0.0)  # sigma^2/2 * 2 c2
        shift[sel[one]] = along[ln[one] - lo]
    return shift
