"""The ring detector's coarse-stage kernels: the labelling's rays, the tiles' thresholds.

:func:`label_rays` samples the darkness map along all rays from a candidate centre
(bilinear, every pixel, each ray only as far as its crossings go), takes the maxima of the runs
above the threshold (to sub-pixel, the vertex of a parabola through three samples; a run
touching the ray's start is the centre's own crossing of the diameter lines and is skipped),
fits the first ones to the 1-D projectivity ``t = a r / (1 + b r)`` of the known radii and
gives the fit's largest residual; on request it may label them from ring 1 instead, where
ring 0's image is lost in that run at the start, or sample bundles of parallel rays.
Candidate centres are many (every crossing of two long lines, at several scales), so this
loop was most of the detector's time.

:func:`tile_thresholds` gives the darkness threshold of each tile of the coarse stage: the
robust level and spread of its paper with the printed lines clipped out (``np.nanpercentile``
and ``np.nanmedian`` over a tile axis run one tile at a time in Python).

The fine stage's profiles across the rings are sampled and measured in
:mod:`calibration.detection.profile_kernels`.

Compiled with numba where it imports (:data:`HAVE_NUMBA`); without it the same code runs as
Python (slowly, but with the same results).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanner.core.jit import HAVE_NUMBA, njit

__all__ = [
    "CENSORED_SPREAD",
    "FIT_TOL_FRACTION",
    "FIT_TOL_PX",
    "HAVE_NUMBA",
    "label_rays",
    "tile_thresholds",
]

#: A ray's crossings fit the radii when the projectivity's largest residual is at most
#: ``FIT_TOL_PX + FIT_TOL_FRACTION * t_last`` px (the coarse crossings' own error and the lens).
FIT_TOL_PX = 1.5
FIT_TOL_FRACTION = 0.01

#: A tile whose 5th and 25th percentiles are closer than this learns no threshold
#: (:func:`tile_thresholds`): a quarter or more of its darkness is exactly 0 (where a closing
#: that follows the noise, the smaller scales, leaves the pixels that are their own
#: neighbourhood's maximum) or it has no noise to learn. Censored low quantiles say nothing
#: of the spread: the caller chooses the tile's level
#: (:func:`~calibration.detection.concentric_rays._threshold_map`).
CENSORED_SPREAD = 1e-4


@njit(cache=True, nogil=True)
def _fit_labels(radii, found, o, m):  # pragma: no cover - compiled
    """Least squares of ``t = a r / (1 + b r)`` with ``found[:m]`` labelled as the rings
    ``o .. o + m - 1``, through its normal equations: ``(a, b, largest residual)``, the
    residual ``inf`` where the fit has no meaning."""
    s11 = 0.0
    s12 = 0.0
    s22 = 0.0
    b1 = 0.0
    b2 = 0.0
    for k in range(m):
        r = radii[o + k]
        tk = found[k]
        s11 += r * r
        s12 -= r * r * tk
        s22 += r * r * tk * tk
        b1 += r * tk
        b2 -= r * tk * tk
    det = s11 * s22 - s12 * s12
    if det <= 1e-12 * s11 * s22:
        return 0.0, 0.0, np.inf
    a = (s22 * b1 - s12 * b2) / det
    b = (s11 * b2 - s12 * b1) / det
    if a <= 0:
        return a, b, np.inf
    worst = 0.0
    for k in range(m):
        den = 1.0 + b * radii[o + k]
        if den <= 0.05:
            return a, b, np.inf
        res = abs(a * radii[o + k] / den - found[k])
        if res > worst:
            worst = res
    return a, b, worst


@njit(cache=True, nogil=True)
def _label(
    d, cx, cy, cos_a, sin_a, radii, thr, tol_px, tol_frac, ring0_hidden, bundle_step_px
):  # pragma: no cover - compiled
    h, w = d.shape
    n_rays = cos_a.size
    k_max = radii.size
    n_samples = int(np.hypot(w, h)) + 1
    row = np.zeros(n_samples)
    found = np.zeros(k_max)
    count = np.zeros(n_rays, np.int64)
    peaks = np.full((n_rays, k_max), np.nan)
    err = np.full(n_rays, np.inf)
    for i in range(n_rays):
        # bilinear samples at t = 1, 2, ... (0 outside [1, w - 2] x [1, h - 2]); a ray that
        # has left the image does not come back. Where the print is hidden (any corner < 0)
        # the ray ends, unless it starts there: then it starts where it leaves it.
        n = 0
        first = 0
        was_inside = False
        # The runs over ``thr`` so far, as the crossings below count them (0: in the run
        # touching the start, 1: between runs, 2: in a run): the ray stops one sample after
        # its K-th, since no crossing beyond is labelled.
        phase = 0
        runs = 0
        for s in range(n_samples - 1):
            t = 1.0 + s
            u = cx + t * cos_a[i]
            v = cy + t * sin_a[i]
            if u >= 1 and u <= w - 2 and v >= 1 and v <= h - 2:
                was_inside = True
                u0 = int(u)
                v0 = int(v)
                if d[v0, u0] < 0 or d[v0, u0 + 1] < 0 or d[v0 + 1, u0] < 0 or d[v0 + 1, u0 + 1] < 0:
                    row[s] = 0.0
                    if s == first:
                        first = s + 1
                        n = s + 1
                        continue
                    n = s  # the crossings beyond cannot be counted
                    break
                fu = u - u0
                fv = v - v0
                row[s] = (1 - fv) * ((1 - fu) * d[v0, u0] + fu * d[v0, u0 + 1]) + fv * (
                    (1 - fu) * d[v0 + 1, u0] + fu * d[v0 + 1, u0 + 1]
                )
                if bundle_step_px > 0:
                    # the mean over parallel rays either side but for the darkest and the
                    # lightest: a faint line's samples add up, and a diameter, a stripe's edge
                    # or clutter under one of them does not decide
                    total = row[s]
                    darkest = row[s]
                    lightest = row[s]
                    used = 1
                    for side in (-2.0, -1.0, 1.0, 2.0):
                        uo = u - side * bundle_step_px * sin_a[i]
                        vo = v + side * bundle_step_px * cos_a[i]
                        if uo >= 1 and uo <= w - 2 and vo >= 1 and vo <= h - 2:
                            a0 = int(uo)
                            b0 = int(vo)
                            c00 = d[b0, a0]
                            c01 = d[b0, a0 + 1]
                            c10 = d[b0 + 1, a0]
                            c11 = d[b0 + 1, a0 + 1]
                            if c00 >= 0 and c01 >= 0 and c10 >= 0 and c11 >= 0:
                                gu = uo - a0
                                gv = vo - b0
                                x = (1 - gv) * ((1 - gu) * c00 + gu * c01) + gv * (
                                    (1 - gu) * c10 + gu * c11
                                )
                                total += x
                                darkest = max(darkest, x)
                                lightest = min(lightest, x)
                                used += 1
                    if used >= 3:  # (else the middle ray's own sample)
                        row[s] = (total - darkest - lightest) / (used - 2)
            else:
                row[s] = 0.0
                if was_inside:
                    n = s + 1
                    break
            n = s + 1
            if row[s] > thr:
                phase = 2 if phase else 0
            elif phase == 2:
                phase = 1
                runs += 1
                if runs == k_max:
                    break
            else:
                phase = 1
        j = first
        while j < n and row[j] > thr:  # the run touching the start
            j += 1
        # Blind up to here: a hidden start and the dark run touching the start (the centre's
        # own crossing of the diameters, and with it the innermost ring where its image is
        # too small to be told from them): the run ends at t = 1 + j_blind.
        j_blind = j
        m = 0
        while j < n and m < k_max:
            if row[j] > thr:
                best = j
                while j < n and row[j] > thr:
                    if row[j] > row[best]:
                        best = j
                    j += 1
                # the vertex of the parabola through the maximum and its neighbours
                off = 0.0
                if 0 < best < n - 1:
                    curv = row[best - 1] - 2.0 * row[best] + row[best + 1]
                    if curv < 0:
                        off = 0.5 * (row[best - 1] - row[best + 1]) / curv
                found[m] = 1.0 + best + off
                m += 1
            else:
                j += 1
        # the hidden start may hide the first ring: labels from ring 0 are not to be trusted
        start_hides = first > 0 and m > 0 and 1.0 + first > 0.5 * found[0]
        o = 0
        worst = np.inf
        if ring0_hidden and m >= 3:
            # Ring 0 as the first crossing, or (ring 0 unseen in the ray's blind start) ring
            # 1: a ray is labelled only where exactly one of the two fits. (A hidden start
            # that may hide the first ring forbids the first, but a fit of it still makes the
            # second ambiguous.)
            a, b, worst0 = _fit_labels(radii, found, 0, m)
            fits0 = worst0 <= tol_px + tol_frac * found[m - 1]
            # (with all K rings crossed, the K-th crossing has no ring beyond ring 1's
            # labelling: that fit takes the first K - 1)
            m1 = min(m, k_max - 1)
            fits1 = False
            worst1 = np.inf
            if m1 >= 3 and j_blind > 0:  # a blind start to hide ring 0 in
                a, b, worst1 = _fit_labels(radii, found, 1, m1)
                den = 1.0 + b * radii[0]
                fits1 = (
                    worst1 <= tol_px + tol_frac * found[m1 - 1]
                    and den > 0.05
                    and a * radii[0] / den <= 1.0 + j_blind + tol_px
                )
            if fits1 and not fits0 and m1 < m:
                # the same crossings as ring 1's fit, from ring 0 (the last crossing, which
                # that fit leaves out, may be clutter beyond the outer ring)
                a, b, worst01 = _fit_labels(radii, found, 0, m1)
                fits0 = worst01 <= tol_px + tol_frac * found[m1 - 1]
            if fits0 and fits1:
                m = 0
            elif fits1:
                o, m, worst = 1, m1, worst1
            elif start_hides:
                m = 0
            else:
                worst = worst0  # fitting or not: the caller judges it
        else:
            if start_hides:
                m = 0
            if m >= 3:
                a, b, worst = _fit_labels(radii, found, 0, m)
        count[i] = m
        for k in range(m):
            peaks[i, o + k] = found[k]
        err[i] = worst
    return count, peaks, err


def label_rays(
    darkness: NDArray,
    centre_px: NDArray,
    angles: NDArray,
    radii: NDArray,
    thr: float,
    tol_px: float = FIT_TOL_PX,
    tol_frac: float = FIT_TOL_FRACTION,
    ring0_hidden: bool = False,
    bundle_step_px: float = 0.0,
) -> tuple[NDArray, NDArray, NDArray]:
    """Each ray's first crossings of dark lines and how well they fit the radii's projectivity.

    Parameters
    ----------
    darkness : ndarray, shape (H, W)
        The darkness map (bilinear samples every pixel along each ray). Negative where the
        print is hidden (a laser stripe, glare): a ray ends there, since a ring it hides
        would shift the labels of every crossing after it.
    centre_px : ndarray, shape (2,)
        The candidate image of O, ``(u, v)``.
    angles : ndarray, shape (R,)
        The rays' directions, rad.
    radii : ndarray, shape (K,)
        The spec's ring radii, increasing, mm.
    thr : float
        Darkness above which a sample may be on a printed line.
    tol_px, tol_frac : float
        A labelling fits where its largest residual is at most ``tol_px + tol_frac * t``,
        ``t`` the farthest crossing's distance (used with ``ring0_hidden`` only; otherwise
        the caller judges ``err_px``).
    ring0_hidden : bool
        Also label a ray's first crossing as ring 1 where the fit puts ring 0 inside the
        ray's blind start (the dark run from the centre, or a hidden start): on a small,
        steep target the innermost ring's image merges with the diameters' crossing at O.
        A ray is then labelled only where exactly one of the two labellings fits (a hidden
        start that may hide the first ring forbids labelling from ring 0, but a fit from
        ring 0 still refuses the ray as ambiguous).
    bundle_step_px : float
        If > 0, each ray is a bundle of five parallel rays this far apart (offset across
        the ray), each sample the mean of theirs but for the darkest and the lightest (nearly
        the mean's noise, robust to one outlier): a line too faint for one ray's samples adds
        up along its ring, which a bundle crosses at nearly one distance from the centre (a
        ring whose image curves with radius ``rho`` px moves in by about
        ``bundle_step_px**2 / rho``), and one side ray over a diameter, a stripe's edge or
        clutter does not decide. Side samples outside the image or over hidden print are
        left out (with fewer than three left, the middle ray's sample stands); only the
        middle ray's hidden samples end the ray.

    Returns
    -------
    count : ndarray, shape (R,), int
        Crossings labelled on each ray, at most ``K`` (``K - 1`` from ring 1).
    peaks_px : ndarray, shape (R, K)
        Their distances from the centre, column ``k`` for ring ``k`` (NaN for rings not
        crossed: beyond the last crossing, and ring 0 where it is hidden).
    err_px : ndarray, shape (R,)
        Largest residual of the fit of ``t = a r / (1 + b r)`` to the labelled crossings
        (``inf`` for fewer than 3 crossings or a fit without meaning).
    """
    d = np.ascontiguousarray(darkness, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"darkness: expected shape (H, W), got {d.shape}")
    angles = np.asarray(angles, dtype=np.float64).reshape(-1)
    return _label(
        d,
        float(centre_px[0]),
        float(centre_px[1]),
        np.cos(angles),
        np.sin(angles),
        np.ascontiguousarray(radii, dtype=np.float64),
        float(thr),
        float(tol_px),
        float(tol_frac),
        bool(ring0_hidden),
        float(bundle_step_px),
    )


@njit(cache=True, nogil=True)
def _order_pair(x, n, i):  # pragma: no cover - compiled
    """The ``i``-th and ``i + 1``-th smallest of ``x[:n]`` (``i + 1 < n``); reorders ``x[:n]``."""
    part = np.partition(x[:n], i + 1)
    x[:n] = part
    lo = part[0]
    for k in range(1, i + 1):
        if part[k] > lo:
            lo = part[k]
    return lo, part[i + 1]


@njit(cache=True, nogil=True)
def _quantile(x, n, q):  # pragma: no cover - compiled
    """``np.quantile`` (linear) of ``x[:n]``, by selection; reorders ``x[:n]``."""
    f = q * (n - 1)
    i = int(np.floor(f))
    if i >= n - 1:
        return np.max(x[:n])
    lo, hi = _order_pair(x, n, i)
    return lo + (f - i) * (hi - lo)


@njit(cache=True, nogil=True)
def _tiles(blocks, clip_sigmas, spread):  # pragma: no cover - compiled
    ny, nx, m = blocks.shape
    out = np.full((ny, nx), np.nan)
    vals = np.empty(m)
    dev = np.empty(m)
    for a in range(ny):
        for b in range(nx):
            n = 0
            for k in range(m):
                x = blocks[a, b, k]
                if np.isfinite(x):
                    vals[n] = x
                    n += 1
            if n == 0:
                continue
            # (order statistics by selection: the same values as from a sort, in less time)
            p5 = _quantile(vals, n, 0.05)
            p25 = _quantile(vals, n, 0.25)
            if p25 - p5 < CENSORED_SPREAD:
                continue  # the low quantiles are censored at 0: no spread to learn here
            sig = (p25 - p5) / 0.97
            cut = p25 + 0.674 * sig + clip_sigmas * sig
            kept = 0
            for k in range(n):
                if vals[k] <= cut:
                    vals[kept] = vals[k]
                    kept += 1
            if kept == 0:
                continue
            med = _quantile(vals, kept, 0.5)
            for k in range(kept):
                dev[k] = abs(vals[k] - med)
            mad = 1.4826 * _quantile(dev, kept, 0.5)
            out[a, b] = med + spread * mad
    return out


def tile_thresholds(blocks: NDArray, clip_sigmas: float = 4.0, spread: float = 6.0) -> NDArray:
    """Per tile, the median + ``spread`` MAD of its finite values, the dark outliers clipped.

    A first level and spread come from the low quantiles (``sigma = (p25 - p5) / 0.97``,
    ``level = p25 + 0.674 sigma``: they hold while printed lines, the outliers on the dark
    side, cover up to 3/4 of the tile); values over ``level + clip_sigmas * sigma`` are
    dropped before the median and the MAD (scaled by 1.4826) of the rest. Where the low
    quantiles are closer than :data:`CENSORED_SPREAD` (a quarter of the tile or more exactly 0,
    or no noise at all) the tile learns nothing: its spread would be taken as nil and all its
    noise clipped as lines.

    Parameters
    ----------
    blocks : ndarray, shape (NY, NX, M)
        M samples of each tile; NaN where a sample is not to be used.

    Returns
    -------
    ndarray, shape (NY, NX)
        NaN for a tile without a finite sample or with censored low quantiles.
    """
    b = np.ascontiguousarray(blocks, dtype=np.float64)
    if b.ndim != 3:
        raise ValueError(f"blocks: expected shape (NY, NX, M), got {b.shape}")
    return _tiles(b, float(clip_sigmas), float(spread))
