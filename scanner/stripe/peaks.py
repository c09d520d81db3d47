"""Several peaks per scan line: candidates, de-duplication, segments and reflections.

Every local maximum above a contrast threshold set by the image noise and by the line's
brightest peak is kept. Peaks on neighbouring lines link into segments; a weaker segment that
never appears without a brighter companion is taken for a reflection and dropped, and the
survivors on those lines carry :attr:`StripeFlag.AMBIGUOUS`.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from scanner.core.jit import HAVE_NUMBA, njit
from scanner.stripe.estimates import _median
from scanner.stripe.fast import _contiguous, _measure_lines, _measure_many, _saturation_level
from scanner.stripe.profile import StripeFlag, StripeOptions, _Peaks


def contrast_threshold(img: NDArray, options: StripeOptions, noise: float, sat: float) -> float:
    """The smallest contrast a peak needs, grey levels: ``k_noise`` times the noise, and at
    least ``min_contrast`` (by default 3 % of the saturation level, or of a float frame's
    maximum)."""
    min_contrast = options.min_contrast
    if min_contrast is None:
        min_contrast = 0.03 * (sat if np.isfinite(sat) else float(img.max()))
    return max(options.k_noise * noise, float(min_contrast))


def _primary_and_secondary(
    img: NDArray, options: StripeOptions, noise: float, hw: int
) -> tuple[_Peaks, bool]:
    """All peaks of the working-orientation image (rows are scan lines).

    Returns the peaks and whether the lines may hold several peaks (``False``: at most one per
    line, in line order).
    """
    H, W = img.shape
    sat = _saturation_level(img, options)
    thr_contrast = contrast_threshold(img, options, noise, sat)

    # Lines where something else clears the threshold outside the primary's window are searched
    # for further peaks; the common frame (one stripe, dark background) skips this entirely.
    if options.background_level is not None:
        bg_level = float(options.background_level)
    else:
        bg_level = _median(img[:: max(1, H // 32), :: max(1, W // 32)])
    thr = bg_level + thr_contrast
    # The candidates: pixels above the level (as cv2.threshold compares: an 8-bit frame's 255
    # always counts, a float32 frame is compared with the level in float32).
    if img.dtype == np.uint8:
        thr_pixel = min(thr, 254.0)
    elif img.dtype == np.float32:
        thr_pixel = float(np.float32(thr))
    else:
        thr_pixel = thr
    compiled = _measure_lines(img, hw, sat, thr_pixel)
    if compiled is not None:
        prim, cols, other = compiled
        extra = np.flatnonzero(other) if np.count_nonzero(other) else cols[:0]
    else:
        img = _contiguous(img)  # OpenCV reads rows: a transposed view is copied
        cols = img.argmax(axis=1)
        # The primary windows cleared from the candidates: what remains is elsewhere on its line.
        if img.dtype == np.uint8:
            _, mask = cv2.threshold(img, thr_pixel, 1, cv2.THRESH_BINARY)
        elif img.dtype == np.float32:
            mask = cv2.threshold(img, thr, 1, cv2.THRESH_BINARY)[1].astype(np.uint8)
        else:
            mask = (img > thr).astype(np.uint8)
        prim = _measure_many(img, np.arange(H), cols, hw, sat, clear=mask)
        extra = np.flatnonzero(cv2.reduce(mask, 1, cv2.REDUCE_MAX).reshape(-1))
    parts = [prim]
    if extra.size:
        img = _contiguous(img)  # rows of a transposed view are read below: one copy
        # The global level is only a first sieve: a further peak must clear its own line's
        # background and the fraction of the line's brightest contrast.
        line_bg = prim.peak[extra] - prim.contrast[extra]
        line_thr = np.maximum(line_bg, bg_level) + np.maximum(
            thr_contrast, options.min_relative_peak * np.maximum(prim.contrast[extra], 0.0)
        )
        above = img[extra] > line_thr[:, None]
        win = cols[extra][:, None] + np.arange(-hw, hw + 1)
        in_line_win = np.take_along_axis(above, np.clip(win, 0, W - 1), axis=1) & (
            (win >= 0) & (win < W)
        )
        extra = extra[above.sum(axis=1) > in_line_win.sum(axis=1)]
        if extra.size:
            parts.append(_secondary_peaks(img, extra, cols[extra], hw, sat, thr))
    if len(parts) == 1:
        # One peak per line: the line's brightest is the peak itself, only the noise and
        # absolute thresholds apply.
        if prim.contrast.min() >= thr_contrast:
            return prim, False
        return prim.take(np.flatnonzero(prim.contrast >= thr_contrast)), False
    peaks = _Peaks.concat(parts)

    # Contrast thresholds: noise, absolute, and relative to the line's brightest peak.
    best = _line_max(peaks.line, peaks.contrast, H)
    keep = (peaks.contrast >= thr_contrast) & (
        peaks.contrast >= options.min_relative_peak * best[peaks.line]
    )
    peaks = peaks.take(np.flatnonzero(keep))
    return _dedupe(peaks, hw), True


def _line_max(line: NDArray, value: NDArray, n_lines: int) -> NDArray:
    """Per-line maximum of ``value`` (0 where a line has none); fast when lines are unique."""
    best = np.zeros(n_lines, np.float32)
    if line.size and np.all(line[1:] > line[:-1]):
        best[line] = value
        return best
    # Two sorted runs (primary peaks, then further peaks): a stable sort merges them cheaply.
    order = np.argsort(line, kind="stable")
    ls = line[order]
    starts = np.flatnonzero(np.concatenate([[True], ls[1:] != ls[:-1]]))
    best[ls[starts]] = np.maximum.reduceat(value[order], starts)
    return best


def _secondary_peaks(
    img: NDArray,
    lines: NDArray,
    primary_cols: NDArray,
    hw: int,
    sat: float,
    thr: float,
) -> _Peaks:
    """Local maxima above ``thr`` on ``lines``, away from the primary peak's window."""
    sub = img[lines].astype(np.float32)
    mx = ndimage.maximum_filter1d(sub, size=2 * hw + 1, axis=1, mode="nearest")
    is_max = (sub >= mx) & (sub > thr)
    # A plateau (saturation) gives a run of equal maxima: keep its first pixel only.
    is_max[:, 1:] &= ~(is_max[:, :-1] & (sub[:, 1:] == sub[:, :-1]))
    r, c = np.nonzero(is_max)
    far = np.abs(c - primary_cols[r]) > hw
    # Also drop pixels inside a saturated run that continues from the primary peak.
    r, c = r[far], c[far]
    if r.size == 0:
        return _empty_peaks()
    return _measure_many(img, lines[r], c, hw, sat)


def _empty_peaks() -> _Peaks:
    return _Peaks(
        np.zeros(0, np.int64),
        np.zeros(0),
        np.zeros(0, np.float32),
        np.zeros(0, np.float32),
        np.zeros(0, np.float32),
        np.zeros(0, np.uint8),
        np.zeros(0, np.float32),
    )


def _dedupe(peaks: _Peaks, hw: int) -> _Peaks:
    """Merge peaks of one line that landed within a window of each other (keep the brighter)."""
    if peaks.line.size < 2:
        return peaks
    order = np.lexsort((peaks.pos, peaks.line))
    p = peaks.take(order)
    same = (p.line[1:] == p.line[:-1]) & (np.abs(p.pos[1:] - p.pos[:-1]) <= hw)
    if not np.any(same):
        return p
    drop = np.zeros(p.line.size, bool)
    idx = np.flatnonzero(same)
    weaker_first = p.contrast[idx] < p.contrast[idx + 1]
    drop[np.where(weaker_first, idx, idx + 1)] = True
    keep_idx = np.flatnonzero(~drop)
    out = p.take(keep_idx)
    # The kept neighbour of a merged pair saw two maxima in its window.
    merged_into = np.where(weaker_first, idx + 1, idx)
    amb = np.zeros(p.line.size, bool)
    amb[merged_into] = True
    out.flags[amb[keep_idx]] |= np.uint8(StripeFlag.AMBIGUOUS)
    return out


def _segments(peaks: _Peaks, link_px: float, max_gap: int = 1) -> NDArray:
    """Segment label per peak (``0 .. k - 1``): chains of peaks on lines at most ``max_gap``
    apart (1: consecutive lines) within ``link_px`` per line of each other."""
    n = peaks.line.size
    order = np.lexsort((peaks.pos, peaks.line))
    line = peaks.line[order]
    pos = peaks.pos[order]
    # Nearest peak on an earlier line, via a sorted key line * big + pos. A NaN position
    # (sorted last on its line) links to nothing: it gets the key after the line's others.
    finite = np.isfinite(pos)
    top = float(pos[finite].max()) if finite.any() else 0.0
    big = float(max(1e6, top + 10 * max_gap * link_px + 1))
    key = line * big + np.where(finite, pos, big - 1.0)
    if HAVE_NUMBA:
        labels_sorted = _link_labels(
            np.ascontiguousarray(line, np.int64), pos, key, big, float(link_px), int(max_gap)
        )
    else:
        src, dst = [], []
        for gap in range(1, max_gap + 1):
            j = np.searchsorted(key, (line - gap) * big + pos)
            for cand in (j - 1, j):
                ok = (cand >= 0) & (cand < n)
                cc = np.clip(cand, 0, n - 1)
                ok &= (line[cc] == line - gap) & (np.abs(pos[cc] - pos) <= gap * link_px)
                src.append(np.flatnonzero(ok))
                dst.append(cc[ok])
        s = np.concatenate(src)
        d = np.concatenate(dst)
        graph = coo_matrix((np.ones(s.size), (s, d)), shape=(n, n))
        _, labels_sorted = connected_components(graph, directed=False)
    labels = np.empty(n, np.int64)
    labels[order] = labels_sorted
    return labels


@njit(cache=True, nogil=True, inline="always")
def _root(parent, a):  # pragma: no cover - compiled
    """The root of ``a`` in the union-find forest ``parent`` (its paths halved on the way:
    every merge below keeps the smaller root, so a component's root is its first member)."""
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@njit(cache=True, nogil=True)
def _link_labels(line, pos, key, big, link_px, max_gap):  # pragma: no cover - compiled
    """:func:`_segments`' components for peaks sorted by line and position: each peak linked
    to the nearest ones on the ``max_gap`` lines before it (the two neighbours of its key's
    place), the links merged by union-find, the labels numbered in order of first appearance
    (as :func:`scipy.sparse.csgraph.connected_components` numbers them)."""
    n = line.size
    parent = np.arange(n)
    for i in range(n):
        for gap in range(1, max_gap + 1):
            j = np.searchsorted(key, (line[i] - gap) * big + pos[i])
            for cand in (j - 1, j):
                if cand < 0 or cand >= n:
                    continue
                # (as the NumPy path compares: a NaN position links to nothing)
                if line[cand] != line[i] - gap or not abs(pos[cand] - pos[i]) <= gap * link_px:
                    continue
                a = _root(parent, i)
                b = _root(parent, cand)
                if a != b:
                    parent[max(a, b)] = min(a, b)
    labels = np.empty(n, np.int64)
    number = np.full(n, -1, np.int64)
    k = 0
    for i in range(n):
        r = _root(parent, i)
        if number[r] < 0:
            number[r] = k
            k += 1
        labels[i] = number[r]
    return labels


def _stretch_ends(peaks: _Peaks, link_px: float, n_lines: int, end_lines: int) -> NDArray:
    """Peaks fewer than ``end_lines`` lines from the end of their run of linked peaks.

    A run is a chain of peaks on lines at most 2 apart (noise drops a peak now and then, or
    puts a stray one beside the stripe) within ``link_px`` per line of each other. A run that
    reaches the image's first or last line, or the line next to it, does not end there (the
    stripe goes on outside).
    """
    n = peaks.line.size
    if n == 0 or end_lines <= 0:
        return np.zeros(n, bool)
    line = peaks.line
    # One peak per line, in line order (the common case): one compiled pass.
    ends = _line_run_ends(line, peaks.pos, float(link_px), int(n_lines), int(end_lines))
    if ends is not None:
        return ends
    run = _segments(peaks, link_px, max_gap=2)  # labels 0 .. k - 1
    order = np.argsort(run, kind="stable")
    starts = np.concatenate([[0], np.flatnonzero(np.diff(run[order])) + 1])
    first = np.minimum.reduceat(line[order], starts)[run]
    last = np.maximum.reduceat(line[order], starts)[run]
    to_first = np.where(first > 1, line - first, end_lines)
    to_last = np.where(last < n_lines - 2, last - line, end_lines)
    return np.minimum(to_first, to_last) < end_lines


@njit(cache=True, nogil=True)
def _line_run_ends(line, pos, link_px, n_lines, end_lines):  # pragma: no cover - compiled
    """:func:`_stretch_ends` for one peak per line in line order (``None`` otherwise): the
    runs linked as :func:`_segments` links them with ``max_gap=2``, each run's first and last
    line, the distances to them.

    A peak joins the run of the peak before it, or of the one before that (a stray peak or a
    dropout between); where it links to both and they are in different runs, the runs merge
    (labels through a small union-find, rarely needed)."""
    n = line.size
    label = np.empty(n, np.int64)
    parent = np.empty(n, np.int64)  # per label
    k = 0
    for i in range(n):
        if i and line[i] <= line[i - 1]:
            return None
        a = -1
        b = -1
        if i >= 1:
            gap = line[i] - line[i - 1]
            if gap <= 2 and abs(pos[i] - pos[i - 1]) <= link_px * gap:
                a = label[i - 1]
        if i >= 2:
            gap = line[i] - line[i - 2]
            if gap <= 2 and abs(pos[i] - pos[i - 2]) <= link_px * gap:
                b = label[i - 2]
        if a < 0 and b < 0:
            parent[k] = k
            label[i] = k
            k += 1
            continue
        if a >= 0 and b >= 0:
            a = _root(parent, a)
            b = _root(parent, b)
            if a != b:
                parent[max(a, b)] = min(a, b)
            label[i] = min(a, b)
        else:
            label[i] = max(a, b)
    first = np.full(k, n_lines, np.int64)
    last = np.full(k, -1, np.int64)
    for i in range(n):
        r = _root(parent, label[i])
        label[i] = r
        first[r] = min(first[r], line[i])
        last[r] = max(last[r], line[i])
    out = np.zeros(n, np.bool_)
    for i in range(n):
        r = label[i]
        to_first = line[i] - first[r] if first[r] > 1 else end_lines
        to_last = last[r] - line[i] if last[r] < n_lines - 2 else end_lines
        out[i] = min(to_first, to_last) < end_lines
    return out


def _resolve_multi(peaks: _Peaks, options: StripeOptions) -> _Peaks:
    """Drop reflections, flag ambiguity and secondary segments on lines with several peaks."""
    n = peaks.line.size
    if n < 2 or np.all(peaks.line[1:] > peaks.line[:-1]):  # one peak per line: nothing to do
        return peaks
    counts = np.bincount(peaks.line)
    multi_line = counts[peaks.line] > 1
    if not np.any(multi_line):
        return peaks
    labels = _segments(peaks, options.link_px)
    best = _line_max(peaks.line, peaks.contrast, counts.size)
    is_best = peaks.contrast >= best[peaks.line]
    ratio = peaks.contrast / np.maximum(best[peaks.line], 1e-6)
    # A segment is a reflection when none of its peaks is alone on its line and each stays
    # below reflection_ratio of its line's brightest peak.
    n_lab = int(labels.max()) + 1
    alone = np.zeros(n_lab, bool)
    alone[labels[~multi_line]] = True
    strong = np.zeros(n_lab, bool)
    strong[labels[ratio >= options.reflection_ratio]] = True
    reflection = ~alone[labels] & ~strong[labels] & ~is_best
    peaks.flags[multi_line & ~is_best] |= np.uint8(StripeFlag.SECONDARY)
    amb_lines = np.unique(peaks.line[reflection])
    amb = np.isin(peaks.line, amb_lines)
    peaks.flags[amb] |= np.uint8(StripeFlag.AMBIGUOUS)
    if options.keep_reflections:
        return peaks
    return peaks.take(np.flatnonzero(~reflection))
