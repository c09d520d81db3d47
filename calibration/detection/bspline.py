"""The cubic B-spline prefilter of an image, compiled: ``scipy.ndimage.spline_filter``'s
coefficients to the bit, in about 40 % of its time.

The ring detector's fine stage samples its darkness map on a cubic spline
(:func:`calibration.detection.profile_kernels.spline_along`) whose coefficients come from the
recursive filter of Unser, Aldroubi and Eden (1991): along each axis in turn, the gain, a
causal pass started from the mirrored line's sum, an anticausal pass. SciPy filters one line
at a time through a buffer; :func:`spline_filter` runs the same arithmetic, in the same
order, on strips of :data:`STRIP` lines at once (the innermost loop goes across the lines of
a strip, so it vectorises, and a strip's passes stay in the cache). The causal start's sum
stops where the pole's power has underflowed to zero: its remaining terms are zeros for
finite values (but where the sum is exactly zero at that point: its sign may differ). A
value that is not finite, or an overflow, spreads along its line to the coefficients: where
one of them is not finite, the image goes to SciPy.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from scanner.core.jit import HAVE_NUMBA, njit

__all__ = ["spline_filter"]

#: The cubic B-spline's pole, ``sqrt(3) - 2``.
POLE = -0.267949192431122706472553658494127633
#: Lines filtered together.
STRIP = 32


@njit(cache=True, nogil=True, inline="always")
def _filter_strip(c, m, z, z_n1, acc):  # pragma: no cover - compiled
    """Columns ``0 .. m - 1`` of ``c`` (n, STRIP), the gain already applied, through the
    causal and anticausal passes with the pole ``z`` (``z_n1 = z ** (n - 1)``), in place."""
    n = c.shape[0]
    # The causal pass's start: the line mirrored about its ends, summed.
    for j in range(m):
        acc[j] = c[0, j] + z_n1 * c[n - 1, j]
    z_i = z
    for i in range(1, n - 1):
        if z_i == 0.0:
            break  # (the terms left are zeros: finite values)
        for j in range(m):
            acc[j] += z_i * (c[i, j] + z_n1 * c[n - 1 - i, j])
        z_i *= z
    den = 1 - z_n1 * z_n1
    for j in range(m):
        c[0, j] = acc[j] / den
    for i in range(1, n):
        for j in range(m):
            c[i, j] += z * c[i - 1, j]
    for j in range(m):
        c[n - 1, j] = (z * c[n - 2, j] + c[n - 1, j]) * z / (z * z - 1)
    for i in range(n - 2, -1, -1):
        for j in range(m):
            c[i, j] = z * (c[i + 1, j] - c[i, j])


@njit(cache=True, nogil=True)
def _filter_columns(c, z, z_n1, gain):  # pragma: no cover - compiled
    """Each column of ``c`` (H, W) filtered in place; False where a coefficient is not finite
    (a value that is not, or an overflow: either spreads along its line)."""
    h, w = c.shape
    buf = np.empty((h, STRIP))
    acc = np.empty(STRIP)
    finite = True
    for j0 in range(0, w, STRIP):
        m = min(STRIP, w - j0)
        for i in range(h):
            for j in range(m):
                buf[i, j] = c[i, j0 + j] * gain
        _filter_strip(buf, m, z, z_n1, acc)
        for i in range(h):
            for j in range(m):
                v = buf[i, j]
                finite &= v - v == 0.0
                c[i, j0 + j] = v
    return finite


@njit(cache=True, nogil=True)
def _filter_rows(c, z, z_n1, gain):  # pragma: no cover - compiled
    """Each row of ``c`` (H, W) filtered in place (through a transposed strip); False where a
    coefficient is not finite."""
    h, w = c.shape
    buf = np.empty((w, STRIP))
    acc = np.empty(STRIP)
    finite = True
    for i0 in range(0, h, STRIP):
        m = min(STRIP, h - i0)
        for j in range(m):
            for i in range(w):
                buf[i, j] = c[i0 + j, i] * gain
        _filter_strip(buf, m, z, z_n1, acc)
        for j in range(m):
            for i in range(w):
                v = buf[i, j]
                finite &= v - v == 0.0
                c[i0 + j, i] = v
    return finite


def spline_filter(image: NDArray) -> NDArray:
    """``scipy.ndimage.spline_filter(image, order=3)`` (mode ``"mirror"``), to the bit (see the
    module's docstring).

    Parameters
    ----------
    image : ndarray, shape (H, W)

    Returns
    -------
    ndarray, shape (H, W), float64
        The cubic B-spline coefficients, a new array.
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image: expected shape (H, W), got {img.shape}")
    if not HAVE_NUMBA:  # pragma: no cover - numba is a dependency
        return ndimage.spline_filter(img, order=3)
    c = np.array(img, dtype=np.float64, order="C")
    if c.size == 0:
        return c
    z = POLE
    gain = (1.0 - z) * (1.0 - 1.0 / z)
    h, w = c.shape
    # (z ** (n - 1) by the C library's pow, as SciPy takes it)
    finite = h == 1 or _filter_columns(c, z, math.pow(z, h - 1), gain)
    finite = finite and (w == 1 or _filter_rows(c, z, math.pow(z, w - 1), gain))
    return c if finite else ndimage.spline_filter(img, order=3)
