"""Compiled kernel of the coarse ring labelling: every ray's first crossings in one pass.

:func:`label_rays` samples the darkness map along all rays from a candidate centre
(bilinear, every pixel, each ray only as far as its crossings go), takes the maxima of the runs
above the threshold (to sub-pixel, the vertex of a parabola through three samples) (a run touching the ray's start is the centre's own crossing of the
diameter lines and is skipped), fits the first ones to the 1-D projectivity
``t = a r / (1 + b r)`` of the known radii and gives the fit's largest residual. Candidate
centres are many (every crossing of two long lines, at several scales), so this loop was
most of the detector's time.

Compiled with numba where it imports (:data:`HAVE_NUMBA`); without it the same code runs as
Python (slowly, but with the same results).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanner.core.jit import HAVE_NUMBA, njit

__all__ = ["HAVE_NUMBA", "label_rays"]


@njit(cache=True, nogil=True)
def _label(d, cx, cy, cos_a, sin_a, radii, thr):  # pragma: no cover - compiled
    h, w = d.shape
    n_rays = cos_a.size
    k_max = radii.size
    n_samples = int(np.hypot(w, h)) + 1
    row = np.zeros(n_samples)
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
            else:
                row[s] = 0.0
                if was_inside:
                    n = s + 1
                    break
            n = s + 1
        j = first
        while j < n and row[j] > thr:  # the run touching the start
            j += 1
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
                peaks[i, m] = 1.0 + best + off
                m += 1
            else:
                j += 1
        if first > 0 and m > 0 and 1.0 + first > 0.5 * peaks[i, 0]:
            # the hidden start may hide the first ring: its labels are not to be trusted
            m = 0
            peaks[i, :] = np.nan
        count[i] = m
        if m < 3:
            continue
        # least squares of [r, -r t] (a, b) = t through its normal equations
        s11 = 0.0
        s12 = 0.0
        s22 = 0.0
        b1 = 0.0
        b2 = 0.0
        for k in range(m):
            r = radii[k]
            tk = peaks[i, k]
            s11 += r * r
            s12 -= r * r * tk
            s22 += r * r * tk * tk
            b1 += r * tk
            b2 -= r * tk * tk
        det = s11 * s22 - s12 * s12
        if det <= 1e-12 * s11 * s22:
            continue
        a = (s22 * b1 - s12 * b2) / det
        b = (s11 * b2 - s12 * b1) / det
        if a <= 0:
            continue
        worst = 0.0
        ok = True
        for k in range(m):
            den = 1.0 + b * radii[k]
            if den <= 0.05:
                ok = False
                break
            res = abs(a * radii[k] / den - peaks[i, k])
            if res > worst:
                worst = res
        if ok:
            err[i] = worst
    return count, peaks, err


def label_rays(
    darkness: NDArray, centre_px: NDArray, angles: NDArray, radii: NDArray, thr: float
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

    Returns
    -------
    count : ndarray, shape (R,), int
        Crossings found on each ray, at most ``K``.
    peaks_px : ndarray, shape (R, K)
        Their distances from the centre (NaN beyond ``count``).
    err_px : ndarray, shape (R,)
        Largest residual of the fit of ``t = a r / (1 + b r)`` to the first ``count`` radii
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
    )
