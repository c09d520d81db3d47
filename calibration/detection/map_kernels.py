"""Compiled per-pixel steps of the ring detector's darkness and bright maps.

:func:`calibration.detection.concentric_rays._darkness` and ``_bright_mask`` run on every
pixel of a view at least twice (the coarse stage, then the fine stage's scale). Written as
array expressions, each of their steps makes a full-image temporary (a quotient, a clipped
copy, a comparison, a float64 copy): together about a tenth of a detection's time. These
kernels do the same arithmetic in one pass each, to the bit: float32 where NumPy computes in
float32 (a Python float against a float32 array is taken as float32, so the thresholds come
in as float32), float64 where it does.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanner.core.jit import HAVE_NUMBA, njit

__all__ = [
    "bright_seeds",
    "darkness_maps",
    "every_nth_selected",
    "kept_components",
    "line_maps",
]


@njit(cache=True, nogil=True)
def _darkness_maps(img32, bg32, dark_below):  # pragma: no cover - compiled
    h, w = img32.shape
    d = np.empty((h, w), np.float64)
    bg = np.empty((h, w), np.float64)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    tiny = np.float32(1e-6)
    for y in range(h):
        for x in range(w):
            b = bg32[y, x]
            v = one - img32[y, x] / max(b, tiny)
            if b < dark_below:
                v = zero
            d[y, x] = min(max(v, zero), one)
            bg[y, x] = b
    return d, bg


def darkness_maps(img32: NDArray, bg32: NDArray, dark_below: float) -> tuple[NDArray, NDArray]:
    """Darkness ``clip(1 - img / max(bg, 1e-6), 0, 1)``, 0 where ``bg < dark_below``, and the
    background, both float64; the arithmetic in float32.

    Parameters
    ----------
    img32, bg32 : ndarray, shape (H, W), float32
        The image and its background (a grey closing, at least the image).
    dark_below : float
        Background level under which nothing printed can be seen (taken as float32).

    Returns
    -------
    d, bg : ndarray, shape (H, W), float64
    """
    a = np.ascontiguousarray(img32, dtype=np.float32)
    b = np.ascontiguousarray(bg32, dtype=np.float32)
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(f"img32, bg32: expected one (H, W) shape, got {a.shape}, {b.shape}")
    below = np.float32(dark_below)
    if not HAVE_NUMBA:  # pragma: no cover - numba is a dependency
        d = 1.0 - a / np.maximum(b, 1e-6)
        d[b < below] = 0.0
        return np.clip(d, 0.0, 1.0).astype(np.float64), b.astype(np.float64)
    return _darkness_maps(a, b, below)


@njit(cache=True, nogil=True)
def _bright_seeds(
    smooth, paper, img, gain, offset, core_min, clip_level, weak_min
):  # pragma: no cover - compiled
    h, w = smooth.shape
    core = np.empty((h, w), np.bool_)
    weak = np.empty((h, w), np.uint8)
    for y in range(h):
        for x in range(w):
            above = smooth[y, x] - paper[y, x]
            c = above > max(paper[y, x] * gain + offset, core_min)
            c = c or (img[y, x] >= clip_level and above > core_min)
            core[y, x] = c
            weak[y, x] = 1 if (c or above > weak_min) else 0
    return core, weak


def bright_seeds(
    smooth: NDArray,
    paper: NDArray,
    img: NDArray,
    gain: float,
    offset: float,
    core_min: float,
    clip_level: float,
    weak_min: float,
) -> tuple[NDArray, NDArray]:
    """The bright map's cores and the pixels still over the noise, with ``above = smooth -
    paper`` (float32): a core is over ``max(paper * gain + offset, core_min)``, or over
    ``core_min`` where ``img >= clip_level``; weak is a core or over ``weak_min``.

    Parameters
    ----------
    smooth, paper : ndarray, shape (H, W), float32
        The lightly smoothed image and its paper level (thin lines taken out).
    img : ndarray, shape (H, W)
        The image; ``clip_level`` is compared in its type (float64 for an integer image),
        the rest in float32.
    gain, offset, core_min, clip_level, weak_min : float

    Returns
    -------
    core : ndarray, shape (H, W), bool
    weak : ndarray, shape (H, W), uint8
        1 where weak (the input of :func:`cv2.connectedComponents`).
    """
    s = np.ascontiguousarray(smooth, dtype=np.float32)
    p = np.ascontiguousarray(paper, dtype=np.float32)
    im = np.ascontiguousarray(img)
    if im.dtype not in (np.float32, np.float64):
        im = im.astype(np.float64)  # (as NumPy compares an integer image with a float)
    clip = im.dtype.type(clip_level)  # (NumPy compares a float32 image in float32)
    if not (s.shape == p.shape == im.shape and s.ndim == 2):
        raise ValueError(
            f"smooth, paper, img: expected one (H, W) shape, got {s.shape}, {p.shape}, {im.shape}"
        )
    g, o, cmin, wmin = (np.float32(v) for v in (gain, offset, core_min, weak_min))
    if not HAVE_NUMBA:  # pragma: no cover - numba is a dependency
        above = s - p
        core = above > np.maximum(p * g + o, cmin)
        core |= (im >= clip) & (above > cmin)
        return core, ((above > wmin) | core).astype(np.uint8)
    return _bright_seeds(s, p, im, g, o, cmin, clip, wmin)


@njit(cache=True, nogil=True)
def _kept_components(labels, core, n):  # pragma: no cover - compiled
    h, w = labels.shape
    keep = np.zeros(n, np.bool_)
    for y in range(h):
        for x in range(w):
            if core[y, x]:
                keep[labels[y, x]] = True
    keep[0] = False
    out = np.empty((h, w), np.uint8)
    for y in range(h):
        for x in range(w):
            out[y, x] = 1 if keep[labels[y, x]] else 0
    return out


def kept_components(labels: NDArray, core: NDArray, n: int) -> NDArray:
    """1 on the components of ``labels`` (``n`` labels, 0 the background, never kept) that
    hold a ``core`` pixel, else 0.

    Parameters
    ----------
    labels : ndarray, shape (H, W), int32
        :func:`cv2.connectedComponents`' labels.
    core : ndarray, shape (H, W), bool
    n : int

    Returns
    -------
    ndarray, shape (H, W), uint8
    """
    lab = np.ascontiguousarray(labels)
    c = np.ascontiguousarray(core, dtype=np.bool_)
    if lab.shape != c.shape or lab.ndim != 2:
        raise ValueError(f"labels, core: expected one (H, W) shape, got {lab.shape}, {c.shape}")
    if int(n) < 1 or (lab.size and not 0 <= int(lab.min()) <= int(lab.max()) < int(n)):
        raise ValueError(
            f"labels: expected labels 0 .. n - 1 with n = {n} >= 1, got "
            f"{lab.min() if lab.size else None} .. {lab.max() if lab.size else None}"
        )
    if not HAVE_NUMBA:  # pragma: no cover - numba is a dependency
        keep = np.zeros(int(n), dtype=bool)
        keep[lab[c]] = True
        keep[0] = False
        return keep[lab].astype(np.uint8)
    return _kept_components(lab, c, int(n))


@njit(cache=True, nogil=True, error_model="numpy")  # (a 0 threshold gives inf, as in NumPy)
def _line_maps(d, thr, hidden, z_line):  # pragma: no cover - compiled
    h, w = d.shape
    mask = np.empty((h, w), np.uint8)
    z_rays = np.empty((h, w), np.float64)
    for y in range(h):
        for x in range(w):
            z = d[y, x] / np.float64(thr[y, x])
            mask[y, x] = 255 if z > z_line else 0
            z_rays[y, x] = -1.0 if hidden[y, x] else z
    return mask, z_rays


def line_maps(d: NDArray, thr: NDArray, hidden: NDArray, z_line: float) -> tuple[NDArray, NDArray]:
    """The darkness over its threshold ``z = d / thr``: the line mask (255 where ``z >
    z_line``) and the rays' map (``z``, -1 where ``hidden``).

    Parameters
    ----------
    d : ndarray, shape (H, W), float64
    thr : ndarray, shape (H, W), float32 or float64
        The threshold map (divided in float64).
    hidden : ndarray, shape (H, W), bool
    z_line : float

    Returns
    -------
    mask : ndarray, shape (H, W), uint8
    z_rays : ndarray, shape (H, W), float64
    """
    dd = np.ascontiguousarray(d, dtype=np.float64)
    t = np.ascontiguousarray(thr)
    hid = np.ascontiguousarray(hidden, dtype=np.bool_)
    if not (dd.shape == t.shape == hid.shape and dd.ndim == 2):
        raise ValueError(
            f"d, thr, hidden: expected one (H, W) shape, got {dd.shape}, {t.shape}, {hid.shape}"
        )
    if not HAVE_NUMBA:  # pragma: no cover - numba is a dependency
        z = dd / t
        return (z > z_line).astype(np.uint8) * 255, np.where(hid, -1.0, z)
    return _line_maps(dd, t, hid, float(z_line))


@njit(cache=True, nogil=True)
def _every_nth_selected(values, selected, step):  # pragma: no cover - compiled
    v = values.ravel()
    sel = selected.ravel()
    count = 0
    for i in range(v.size):
        if sel[i]:
            count += 1
    out = np.empty((count + step - 1) // step, v.dtype)
    seen = 0
    m = 0
    for i in range(v.size):
        if sel[i]:
            if seen % step == 0:
                out[m] = v[i]
                m += 1
            seen += 1
    return out


def every_nth_selected(values: NDArray, selected: NDArray, step: int) -> NDArray:
    """``values[selected][::step]`` without the whole selection's copy.

    Parameters
    ----------
    values : ndarray, shape (H, W)
    selected : ndarray, shape (H, W), bool
    step : int
        At least 1.

    Returns
    -------
    ndarray, shape (ceil(count / step),), ``values``' type
    """
    v = np.ascontiguousarray(values)
    sel = np.ascontiguousarray(selected, dtype=np.bool_)
    if v.shape != sel.shape:
        raise ValueError(f"values, selected: expected one shape, got {v.shape}, {sel.shape}")
    if int(step) < 1:
        raise ValueError(f"step: expected at least 1, got {step}")
    if not HAVE_NUMBA:  # pragma: no cover - numba is a dependency
        return v[sel][:: int(step)]
    return _every_nth_selected(v, sel, int(step))
