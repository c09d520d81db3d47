"""The median of a large float sample by radix selection: ``np.median``'s value, in 2-3 passes.

``np.median`` partitions its sample (introselect): about 7 ns per value, 2-4 ms for the ring
detector's 200,000-330,000-value noise samples, four of them per image. :func:`median` finds
the same order statistics from histograms of the values' bits instead: a float's bit
pattern, its sign bit flipped (all bits, for a negative value), sorts as the float does; a
histogram of its top 16 bits says which bin holds the middle rank, a histogram of the next
16 bits of the values in that bin narrows it down, and so on until the value itself (two
levels for float32, four for float64, each after the first over the few values left).

The result is ``np.median``'s to the bit: the middle value, or for an even count the mean of
the two middle values in the sample's own precision (``(a + b) / 2`` in float32 for a
float32 sample, as ``np.mean`` gives it); a zero median is ``+0.0``, as NumPy's mean makes
it (its sums start from ``+0.0``), though the keys sort ``-0.0`` below ``0.0``; a sample
holding NaN gives NaN, as in NumPy.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanner.core.jit import HAVE_NUMBA, njit

__all__ = ["median"]

#: Below this many values NumPy's partition is as fast (and the histograms' set-up is not).
SMALL_SAMPLE = 4096


@njit(cache=True, nogil=True)
def _keys32(x, bits):  # pragma: no cover - compiled
    """Sortable keys of the float32 ``x`` (``bits``: its view as uint32): the sign bit
    flipped, all bits of a negative value; and whether any value is NaN."""
    keys = np.empty(x.size, np.uint64)
    nan = False
    for i in range(x.size):
        b = np.uint64(bits[i])
        keys[i] = (
            b ^ np.uint64(0xFFFFFFFF) if b >= np.uint64(0x80000000) else b | np.uint64(0x80000000)
        )
        nan |= x[i] != x[i]
    return keys, nan


@njit(cache=True, nogil=True)
def _keys64(x, bits):  # pragma: no cover - compiled
    """Sortable keys of the float64 ``x`` (``bits``: its view as uint64), and whether any
    value is NaN."""
    keys = np.empty(x.size, np.uint64)
    sign = np.uint64(0x8000000000000000)
    nan = False
    for i in range(x.size):
        b = bits[i]
        keys[i] = ~b if b >= sign else b | sign
        nan |= x[i] != x[i]
    return keys, nan


@njit(cache=True, nogil=True)
def _select(keys, rank, top_shift):  # pragma: no cover - compiled
    """The key of rank ``rank`` (0-based) among ``keys``, and how many keys equal it have a
    higher rank. Reorders nothing; ``top_shift``: the lowest bit of the keys' top 16."""
    hist = np.zeros(65536, np.int64)
    cand = keys
    m = keys.size
    r = rank
    prefix = np.uint64(0)
    shift = top_shift
    while True:
        hist[:] = 0
        s = np.uint64(shift)
        for i in range(m):
            hist[np.int64((cand[i] >> s) & np.uint64(0xFFFF))] += 1
        b = 0
        below = 0
        while below + hist[b] <= r:
            below += hist[b]
            b += 1
        r -= below
        prefix = (prefix << np.uint64(16)) | np.uint64(b)
        if shift == 0:
            return prefix, hist[b] - 1 - r
        # The values of bin b, the next 16 bits of which the next histogram counts.
        nxt = np.empty(hist[b], np.uint64)
        k = 0
        for i in range(m):
            if (cand[i] >> s) & np.uint64(0xFFFF) == np.uint64(b):
                nxt[k] = cand[i]
                k += 1
        cand = nxt
        m = k
        shift -= 16


@njit(cache=True, nogil=True)
def _above(keys, key):  # pragma: no cover - compiled
    """The smallest of ``keys`` above ``key``."""
    top = np.uint64(0xFFFFFFFFFFFFFFFF)
    best = top
    for i in range(keys.size):  # (without a branch: it vectorises)
        best = min(best, keys[i] if keys[i] > key else top)
    return best


def _value(key: np.uint64, dtype: np.dtype) -> np.floating:
    """The float whose sortable key is ``key`` (the inverse of ``_keys32``/``_keys64``)."""
    if dtype == np.float32:
        k = int(key)
        bits = k ^ 0x80000000 if k >= 0x80000000 else k ^ 0xFFFFFFFF
        return np.array([bits], np.uint32).view(np.float32)[0]
    k = int(key)
    bits = k ^ 0x8000000000000000 if k >= 0x8000000000000000 else k ^ 0xFFFFFFFFFFFFFFFF
    return np.array([bits], np.uint64).view(np.float64)[0]


def median(x: NDArray) -> float:
    """``float(np.median(x))``, by radix selection (see the module's docstring).

    Parameters
    ----------
    x : ndarray, shape (N,), float32 or float64
        The sample (N >= 1). Other dtypes, and samples below :data:`SMALL_SAMPLE` values, go
        to ``np.median``.

    Returns
    -------
    float
        The median; NaN where ``x`` holds NaN.
    """
    x = np.asarray(x)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"x: expected a non-empty 1-D array, got shape {x.shape}")
    if not HAVE_NUMBA or x.size < SMALL_SAMPLE or x.dtype not in (np.float32, np.float64):
        return float(np.median(x))
    single = x.dtype == np.float32
    x = np.ascontiguousarray(x)
    keys, nan = (_keys32 if single else _keys64)(x, x.view(np.uint32 if single else np.uint64))
    if nan:
        return float("nan")
    n = x.size
    top = 16 if single else 48
    lo_key, equal_above = _select(keys, (n - 1) // 2, top)
    lo = _value(lo_key, x.dtype)
    if n % 2:
        mid = float(lo)
    else:
        hi = lo if equal_above > 0 else _value(_above(keys, np.uint64(lo_key)), x.dtype)
        mid = float((lo + hi) / x.dtype.type(2))
    return 0.0 if mid == 0.0 else mid  # (+0.0 for -0.0, as NumPy's)
