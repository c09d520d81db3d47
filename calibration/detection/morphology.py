"""Grey dilation and erosion by a flat element made of centred row segments (an ellipse).

The ring detector's background is a grey closing by an elliptic element several line widths
across (:func:`calibration.detection.concentric_rays._darkness`). OpenCV takes the maximum
over every point of a non-rectangular element, so its time grows with the element's area:
about 20 ms for a 25 px ellipse over a 1280x1024 16-bit image, most of such a closing's
share of a detection. An element whose rows are segments centred on its middle column (the
ellipse of :func:`cv2.getStructuringElement` for an odd size) splits into rows: the image is
dilated along its rows by each distinct half-width the element's rows have (each half-width
from a smaller one by a maximum of three shifted copies), and every output row is then the
maximum, over the element's rows, of the input row it reaches dilated by that row's
half-width. That is about ``3 x (distinct half-widths) + (rows)`` comparisons per pixel
instead of the element's area, in rolling buffers of ``rows`` image rows.

The values are OpenCV's to the bit (a maximum or minimum only picks values): the element's
anchor is its centre, and pixels beyond the image are left out, as OpenCV's default border
(:func:`cv2.morphologyDefaultBorderValue`) leaves out every finite value. Other elements
(even sizes, other shapes), other image types, empty images and float images holding a
value that is not finite (OpenCV's border, the largest float, then takes part) go to OpenCV.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from scanner.core.jit import HAVE_NUMBA, njit

__all__ = ["dilate", "erode", "from_levels", "grey_morphology", "row_half_widths", "to_levels"]


def row_half_widths(se: NDArray) -> NDArray | None:
    """Half-width of each row of a flat element whose rows are segments centred on its middle
    column, shape (k,), int64 (-1 for an empty row); ``None`` for any other element (an even
    size, an off-centre or broken row, an empty middle row).

    Parameters
    ----------
    se : ndarray, shape (k, k)
        The element; non-zero entries belong to it.
    """
    se = np.asarray(se)
    if se.ndim != 2 or se.shape[0] != se.shape[1] or se.shape[0] % 2 == 0:
        return None
    k = se.shape[0]
    mid = k // 2
    out = np.full(k, -1, dtype=np.int64)
    for y in range(k):
        cols = np.flatnonzero(se[y])
        if cols.size == 0:
            continue
        if cols[-1] - cols[0] + 1 != cols.size or cols[0] + cols[-1] != 2 * mid:
            return None
        out[y] = mid - cols[0]
    if out[mid] < 0:
        return None
    return out


def _plan(half_widths: NDArray) -> tuple[NDArray, NDArray]:
    """The row dilations' half-widths from 0 up, each reachable from the one before it by
    three shifted copies (a step of at most ``2 r + 1``), and each element row's index among
    them (-1 for an empty row)."""
    wanted = sorted({int(r) for r in half_widths if r >= 0})
    radii = [0]
    for r in wanted:
        while radii[-1] < r:
            radii.append(min(r, 3 * radii[-1] + 1))
    index = {r: i for i, r in enumerate(radii)}
    rows = np.array([index[int(r)] if r >= 0 else -1 for r in half_widths], dtype=np.int64)
    return np.asarray(radii, dtype=np.int64), rows


@njit(cache=True, nogil=True)
def _extend(prev, cur, d, take_max):  # pragma: no cover - compiled
    """``cur[x]``: the extreme of ``prev`` at ``x - d``, ``x``, ``x + d`` (clamped)."""
    w = prev.size
    lo = min(d, w)
    hi = max(w - d, lo)
    for x in range(lo):
        a, b, c = prev[0], prev[x], prev[min(x + d, w - 1)]
        cur[x] = max(a, max(b, c)) if take_max else min(a, min(b, c))
    # (views indexed from 0: numba then knows no index is negative, and the loop vectorises)
    n = hi - lo
    left, mid, right, dst = prev[lo - d : hi - d], prev[lo:hi], prev[lo + d : hi + d], cur[lo:hi]
    if take_max:
        for x in range(n):
            dst[x] = max(left[x], max(mid[x], right[x]))
    else:
        for x in range(n):
            dst[x] = min(left[x], min(mid[x], right[x]))
    for x in range(hi, w):
        a, b, c = prev[max(x - d, 0)], prev[x], prev[w - 1]
        cur[x] = max(a, max(b, c)) if take_max else min(a, min(b, c))


@njit(cache=True, nogil=True)
def _by_rows(img, radii, row_index, take_max):  # pragma: no cover - compiled
    h, w = img.shape
    k = row_index.size
    half = k // 2
    nr = radii.size
    buf = np.empty((nr, k, w), img.dtype)
    out = np.empty_like(img)
    done = 0  # input rows dilated along the row so far
    for y in range(h):
        last = min(h - 1, y + half)
        while done <= last:
            slot = done % k
            buf[0, slot, :] = img[done]
            for q in range(1, nr):
                _extend(buf[q - 1, slot], buf[q, slot], radii[q] - radii[q - 1], take_max)
            done += 1
        o = out[y]
        o[:] = buf[row_index[half], y % k]
        for dy in range(k):
            yy = y + dy - half
            q = row_index[dy]
            if dy == half or q < 0 or yy < 0 or yy >= h:
                continue
            src = buf[q, yy % k]
            if take_max:
                for x in range(w):
                    o[x] = max(o[x], src[x])
            else:
                for x in range(w):
                    o[x] = min(o[x], src[x])
    return out


_TYPES = (np.uint8, np.uint16, np.float32)

#: OpenCV's time grows with the element's points times the pixel's bytes, the rows' way with
#: the element's size: below this product (ellipses up to 15 px in 8 bits, 11 px in 16 bits,
#: 7 px in float32) OpenCV is the faster (measured on 1280x1024 images, 2026-12-02; the tests
#: time neither).
ROWS_FROM_POINT_BYTES = 200


def _apply(img: NDArray, se: NDArray, take_max: bool) -> NDArray:
    half_widths = row_half_widths(se)
    a = np.asarray(img)
    if (
        half_widths is None
        or a.ndim != 2
        or a.dtype not in _TYPES
        or not HAVE_NUMBA
        or np.count_nonzero(se) * a.dtype.itemsize < ROWS_FROM_POINT_BYTES
        or np.all(half_widths == half_widths[0])  # a rectangle: OpenCV splits it, faster
        or a.size == 0
        or (a.dtype == np.float32 and not np.isfinite(a).all())
    ):
        op = cv2.dilate if take_max else cv2.erode
        return op(a, np.asarray(se, dtype=np.uint8))
    radii, rows = _plan(half_widths)
    return _by_rows(np.ascontiguousarray(a), radii, rows, take_max)


def dilate(img: NDArray, se: NDArray) -> NDArray:
    """``cv2.dilate(img, se)`` (anchor at the centre, pixels beyond the image left out).

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8, uint16 or float32
    se : ndarray, shape (k, k)
        Flat element; one made of centred row segments (:func:`row_half_widths`) of
        unequal widths (OpenCV splits a rectangle into a row and a column, faster), large
        enough (:data:`ROWS_FROM_POINT_BYTES`), is processed by rows; any other by OpenCV.

    Returns
    -------
    ndarray, shape (H, W), ``img``'s type
    """
    return _apply(img, se, True)


def erode(img: NDArray, se: NDArray) -> NDArray:
    """``cv2.erode(img, se)``: as :func:`dilate`, with the minimum.

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8, uint16 or float32
    se : ndarray, shape (k, k)

    Returns
    -------
    ndarray, shape (H, W), ``img``'s type
    """
    return _apply(img, se, False)


def grey_morphology(img: NDArray, op: int, se: NDArray) -> NDArray:
    """``cv2.morphologyEx(img, op, se)`` for ``cv2.MORPH_CLOSE`` (a dilation, then an erosion)
    and ``cv2.MORPH_OPEN`` (the other way round); any other operation goes to OpenCV.

    Parameters
    ----------
    img : ndarray, shape (H, W), uint8, uint16 or float32
    op : int
        An OpenCV morphology operation (``cv2.MORPH_*``).
    se : ndarray, shape (k, k)

    Returns
    -------
    ndarray, shape (H, W), ``img``'s type
    """
    if op == cv2.MORPH_CLOSE:
        return erode(dilate(img, se), se)
    if op == cv2.MORPH_OPEN:
        return dilate(erode(img, se), se)
    return cv2.morphologyEx(img, op, se)


@njit(cache=True, nogil=True)
def _to_levels(img, lo, inv_scale):  # pragma: no cover - compiled
    h, w = img.shape
    out = np.empty((h, w), np.uint16)
    top = np.float32(65535.0)
    zero = np.float32(0.0)
    for y in range(h):
        for x in range(w):
            v = (img[y, x] - lo) * inv_scale
            v = min(max(v, zero), top)
            out[y, x] = np.uint16(np.rint(v))
    return out


@njit(cache=True, nogil=True)
def _from_levels(levels, own, img, scale, lo):  # pragma: no cover - compiled
    h, w = levels.shape
    out = np.empty((h, w), np.float32)
    for y in range(h):
        for x in range(w):
            q = levels[y, x]
            out[y, x] = img[y, x] if q == own[y, x] else np.float32(q) * scale + lo
    return out


def to_levels(img: NDArray, lo: np.float32, inv_scale: np.float32) -> NDArray:
    """16-bit levels of a float32 image: ``rint(clip((img - lo) * inv_scale, 0, 65535))``,
    in float32 arithmetic as NumPy does it, to the bit.

    Parameters
    ----------
    img : ndarray, shape (H, W), float32
    lo, inv_scale : float32
        The level 0's value and the levels per unit.

    Returns
    -------
    ndarray, shape (H, W), uint16
    """
    a = np.ascontiguousarray(img, dtype=np.float32)
    if a.ndim != 2:
        raise ValueError(f"img: expected shape (H, W), got {a.shape}")
    lo32, inv32 = np.float32(lo), np.float32(inv_scale)
    if not HAVE_NUMBA:  # pragma: no cover - numba is a dependency
        scaled = (a - lo32) * inv32
        return np.rint(np.clip(scaled, 0.0, 65535.0, out=scaled), out=scaled).astype(np.uint16)
    return _to_levels(a, lo32, inv32)


def from_levels(
    levels: NDArray, own: NDArray, img: NDArray, scale: np.float32, lo: np.float32
) -> NDArray:
    """Values of ``levels`` (a morphology's output of ``own = to_levels(img, ...)``): the
    image's own value where the level came back unchanged, ``level * scale + lo`` (float32)
    elsewhere.

    Parameters
    ----------
    levels, own : ndarray, shape (H, W), uint16
    img : ndarray, shape (H, W), float32
    scale, lo : float32

    Returns
    -------
    ndarray, shape (H, W), float32
    """
    a = np.ascontiguousarray(img, dtype=np.float32)
    if not (np.shape(levels) == np.shape(own) == a.shape and a.ndim == 2):
        raise ValueError(
            f"levels, own, img: expected one (H, W) shape, got {np.shape(levels)}, "
            f"{np.shape(own)}, {a.shape}"
        )
    s32, lo32 = np.float32(scale), np.float32(lo)
    if not HAVE_NUMBA:  # pragma: no cover - numba is a dependency
        out = levels.astype(np.float32) * s32 + lo32
        same = levels == own
        out[same] = a[same]
        return out
    return _from_levels(np.ascontiguousarray(levels), np.ascontiguousarray(own), a, s32, lo32)
