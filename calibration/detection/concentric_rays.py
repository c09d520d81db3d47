"""Concentric-circles detector, coarse stage: darkness, diameter lines, rings along rays.

Steps 1-3 of :mod:`calibration.detection.concentric`: the darkness map ``D = 1 - I /
background`` (a grey closing), the long thin dark lines (Hough) as candidate diameters whose
crossings are candidate images of O, and rays from a candidate centre whose first crossings
are labelled by the 1-D projectivity ``t = a r / (1 + b r)`` of the known radii.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.detection.conics import intersect_lines
from calibration.detection.hough import hough_lines
from calibration.detection.map_kernels import (
    bright_seeds,
    darkness_maps,
    every_nth_selected,
    kept_components,
)
from calibration.detection.morphology import from_levels, grey_morphology, to_levels
from calibration.detection.ray_kernels import (
    FIT_TOL_FRACTION,
    FIT_TOL_PX,
    label_rays,
    tile_thresholds,
)
from scanner.core.selection import median

#: The darkness threshold's floor (:func:`_threshold_map`) is the lit paper's own noise level,
#: between these two: one grey level of an 8-bit image at the paper's level (no fainter print
#: is looked for; a 16-bit image's finer steps show the paper's smooth texture there), and
#: 0.02, the fixed floor of the detector before 2026-11-26 (quiet paper under a faint print
#: lowers it; noisy paper does not raise it).
MIN_DARKNESS_STEP = 1.0 / 255.0
MAX_DARKNESS_FLOOR = 0.02

# --------------------------------------------------------------------------------------------
# Image preparation


def _darkness(
    img: NDArray, kernel_px: int, hidden: NDArray | None = None
) -> tuple[NDArray, NDArray, float]:
    """Darkness ``1 - I / background`` (>= 0), the background (closing with ``kernel_px``)
    and the lit paper's level in it (:func:`_lit_level`).

    Where the background is far below the lit paper (unlit or dark surroundings) no printed
    line can be seen and the darkness is 0; the paper's level comes from this image
    (:func:`_lit_level`), not from a constant: from the pixels not ``hidden`` (a laser
    stripe or glare, far brighter than the paper, would otherwise be taken for it and the
    paper for unlit surroundings).
    """
    k = int(kernel_px) | 1
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    img32 = img.astype(np.float32)
    # (integer images keep their own levels: see _grey_morphology)
    levels = img if img.dtype in (np.uint8, np.uint16) else img32
    bg = np.maximum(_grey_morphology(levels, (cv2.MORPH_CLOSE, se)), img32)
    lit = _lit_level(bg, hidden)
    d, bg64 = darkness_maps(img32, bg, 0.3 * lit)
    return d, bg64, lit


def _grey_morphology(img: NDArray, *steps: tuple[int, NDArray]) -> NDArray:
    """OpenCV's grey morphology ``steps`` (operation, structuring element), in turn, float32.

    A grey closing or opening only picks values of the image, so it commutes with any
    increasing map of them: 8- and 16-bit images are processed as they are, float images
    through 16-bit levels spanning their range (OpenCV's 16-bit morphology is about twice as
    fast as its float one). A pixel whose level comes back unchanged keeps its own value (a
    closing that leaves a pixel as it is leaves it exactly: its darkness stays 0); the others
    come back within half a level, 1/131070 of the range, so every value is within one level
    of the float morphology's. A range that float32 cannot split into levels (flat, not
    finite, too narrow or too wide) is processed in float.
    """
    if img.dtype in (np.uint8, np.uint16):
        out = img
        for op, se in steps:
            out = grey_morphology(out, op, se)
        return out.astype(np.float32)
    img32 = np.asarray(img, dtype=np.float32)
    lo, hi = float(np.min(img32)), float(np.max(img32))
    scale = (hi - lo) / 65535.0
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        usable = (
            np.isfinite(np.float32(hi - lo))
            and scale >= np.finfo(np.float32).tiny
            and np.isfinite(np.float32(1.0 / scale))
        )
    if not usable:
        out = img32
        for op, se in steps:
            out = grey_morphology(out, op, se)
        return out
    own = to_levels(img32, np.float32(lo), np.float32(1.0 / scale))
    levels = own
    for op, se in steps:
        levels = grey_morphology(levels, op, se)
    return from_levels(levels, own, img32, np.float32(scale), np.float32(lo))


def _lit_level(bg: NDArray, hidden: NDArray | None = None) -> float:
    """Level of the lit paper: the median background of the bright class of an Otsu split.

    Dark surroundings may fill most of the frame (a percentile of the whole image would then
    be their level); the Otsu split of the background separates them from the lit card.
    ``hidden`` pixels (a laser stripe, glare) are left out: the split would put them alone in
    the bright class.
    """
    step = max(1, int(np.sqrt(bg.size / 65536)))
    sub = bg[::step, ::step]
    if hidden is not None:
        seen = sub[~hidden[::step, ::step]]
        sub = seen.reshape(-1, 1) if seen.size >= 100 else sub
    top = float(np.percentile(sub, 99.9))
    if top <= 0:
        return 0.0
    u8 = np.clip(sub * (255.0 / top), 0, 255).astype(np.uint8)
    t, _ = cv2.threshold(u8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    bright = sub[u8 > t]
    return median(bright) if bright.size else top


def _live_mask(bg: NDArray, lit: float, hidden: NDArray | None = None) -> NDArray:
    """Pixels where a printed line could be seen: lit (the background at least 30 % of the
    paper's level ``lit``), not clipped at the white level, not ``hidden`` (a laser stripe or
    glare, whose darkness is 0 without noise: a tile it fills would otherwise learn a
    threshold far below the paper's noise)."""
    live = bg >= 0.3 * lit
    if hidden is not None:
        live &= ~hidden
    top = float(bg.max())
    flat = bg >= top * (1 - 1e-6)
    if flat.mean() > 0.01:  # a clipped (saturated) region: no noise there to learn from
        live &= ~flat
    return live


def _bright_element_px(kernel_px: int) -> int:
    """The size of :func:`_bright_mask`'s square element for the closing kernel
    ``kernel_px``: wider than a line and than the kernel."""
    return max(int(kernel_px) * 2 + 1, 15) | 1


def _smoothed(img: NDArray) -> NDArray:
    """The image lightly smoothed, float32: :func:`_bright_mask`'s (the noise drops about
    threefold, a stripe keeps most of its height)."""
    return cv2.GaussianBlur(img.astype(np.float32), (0, 0), 1.0)


def _bright_mask(img: NDArray, kernel_px: int, smooth: NDArray | None = None) -> NDArray:
    """1 where the image is clearly brighter than the paper around it (laser stripe, glare).

    The paper level is the image with thin lines taken out, dark ones and then bright ones
    (a grey closing, then an opening, wider than a line): densely printed rings cover much
    of any window, and a median over it would take their darkness for the paper's and the
    paper between them for glare. Clearly brighter: 12 % over the paper (or clipped at the
    image's top over paper that is nearly as bright), and beyond 3.5 times this image's own
    noise (the robust spread of the image about its paper level), so that sensor noise and
    paper grain are never taken for glare; with it, whatever around it is still 2 times the
    noise over the paper (its glow).

    Returns a uint8 map of 0 and 1; ``smooth``: :func:`_smoothed` of ``img`` where already
    made.
    """
    k = _bright_element_px(kernel_px)
    se = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    smooth = _smoothed(img) if smooth is None else smooth
    paper = _grey_morphology(smooth, (cv2.MORPH_CLOSE, se), (cv2.MORPH_OPEN, se))
    step = max(1, int(np.sqrt(paper.size / 200_000)))
    sub_paper = paper[::step, ::step]
    sub_above = smooth[::step, ::step] - sub_paper
    # The noise of the lit paper, not of dark surroundings (which would pull it to zero).
    lit = sub_paper > 0.5 * _lit_level(sub_paper)
    sample = sub_above[lit] if np.count_nonzero(lit) >= 100 else sub_above.ravel()
    noise = 1.4826 * median(np.abs(sample - median(sample)))
    # A core: 12 % over the paper and 3.5 noise levels. Over bright paper a stripe clips at
    # the image's top before it is 12 % over the paper: there, 3.5 noise levels. Its glow
    # (the beam's tails, the blur) reaches further: all that is still 2 noise levels over
    # the paper and connected to a core ("weak") is taken with it.
    core, weak = bright_seeds(
        smooth,
        paper,
        img,
        gain=0.12,
        offset=0.02 * median(sub_paper.ravel()),
        core_min=3.5 * noise,
        clip_level=0.99 * float(img.max()),
        weak_min=2.0 * noise,
    )
    n, labels = cv2.connectedComponents(weak, connectivity=8)
    return cv2.dilate(kept_components(labels, core, n), np.ones((3, 3), np.uint8))


class BrightMasks:
    """The bright masks of one image (:func:`_bright_mask`), each made once.

    The coarse stage's scales and the fine stage of every pass ask for them, often for an
    element size asked for before (the fine stage's kernel may be a coarse one; the kernels
    up to 7 px share the 15 px element); each costs about a tenth of a detection. Kept: the
    uint8 masks and the smoothed image, not the maps made on the way.
    """

    def __init__(self, img: NDArray) -> None:
        self.img = img
        self._smooth: NDArray | None = None
        self._masks: dict[int, NDArray] = {}

    def __call__(self, kernel_px: int) -> NDArray:
        """:func:`_bright_mask` of the image for the closing kernel ``kernel_px``: shape
        (H, W), uint8, 0 or 1."""
        k = _bright_element_px(kernel_px)
        if k not in self._masks:
            if self._smooth is None:
                self._smooth = _smoothed(self.img)
            mask = _bright_mask(self.img, kernel_px, self._smooth)
            mask.flags.writeable = False  # (shared by every pass that asks)
            self._masks[k] = mask
        return self._masks[k]


def _coarse_darkness(
    img: NDArray, kernel: int, hidden: NDArray
) -> tuple[NDArray, NDArray, float, NDArray]:
    """The coarse stage's darkness, background, lit paper level and hidden (bright) pixels
    with the closing kernel ``kernel`` px; ``hidden``: the bright pixels
    (``_bright_mask(img, kernel) > 0``, :class:`BrightMasks`)."""
    # Coarse stage on a lightly smoothed image: noise and grain drop about threefold, a
    # printed line keeps most of its darkness.
    d, bg, lit = _darkness(cv2.GaussianBlur(img, (0, 0), 1.0), kernel, hidden)
    return d, bg, lit, hidden


def _noise_threshold(d: NDArray, live: NDArray | None = None) -> float:
    """Darkness above which a pixel is not noise: median + 6 MAD over the lit target area.

    The statistics are those of the ``live`` pixels (lit, unclipped, not hidden:
    :func:`_live_mask`) only: dark or saturated surroundings filling most of the frame carry
    no paper noise, and over the whole image they would drive the MAD to zero. (0 where most
    of them are: :func:`_threshold_map` sets a floor.)
    """
    # Every ``step``-th of them (at most about 200,000), in the image's order.
    n = d.size if live is None else int(np.count_nonzero(live))
    if live is None or n < 100:
        sel = d.ravel()[:: max(1, d.size // 200_000)]
    else:
        sel = every_nth_selected(d, live, max(1, n // 200_000))
    med = median(sel)
    mad = median(np.abs(sel - med)) * 1.4826
    return med + 6.0 * mad


def _threshold_map(
    d: NDArray,
    bg: NDArray,
    tile_px: int,
    hidden: NDArray | None = None,
    floor: float | None = None,
    lit: float | None = None,
) -> tuple[NDArray, float]:
    """Per-pixel darkness threshold: median + 6 MAD of ``d`` in tiles of the lit area.

    Noise and paper grain differ between the card and its surroundings and over the card
    (uneven light): each tile of about ``tile_px`` learns its own level from its lit,
    unclipped pixels; tiles without enough of them take the whole lit area's
    (:func:`_noise_threshold`). The tile grid is interpolated to every pixel.

    A tile whose darkness is censored at 0 (a quarter or more of it exactly 0: its low
    quantiles give no spread, :func:`~calibration.detection.ray_kernels.tile_thresholds`)
    learns nothing either. At the first scale (``floor`` None) that may be print so dense
    that the paper between its lines is its own closing (randomised view 18:57, 8 rings 6 px
    apart): such a tile takes the floor, since the whole area's level, raised by those very
    lines, would lose them. At a smaller scale it is mostly the closing following the noise,
    and the floor let a third of noisy paper through (21:39): such a tile takes the whole
    area's level.

    No threshold goes below ``floor``: where a closing follows the noise (a narrow one, the
    detector's smaller scales), most of the paper's darkness is exactly 0 and its median and
    MAD say nothing. ``None``: this map sets it, from the whole lit area's level (at the
    detector's first, widest closing; where even that is 0, the level of the darkness above
    0), kept between ``MIN_DARKNESS_STEP / lit level`` and ``MAX_DARKNESS_FLOOR`` (the lower
    bound wins on dim paper). ``lit``: the paper's level from :func:`_darkness` (``None``:
    found again in ``bg``).

    Returns
    -------
    ndarray, shape (H, W), float32, and float
        The threshold map and the floor it used.
    """
    h, w = d.shape
    if lit is None:
        lit = _lit_level(bg, hidden)
    live = _live_mask(bg, lit, hidden)
    level = _noise_threshold(d, live)
    first_scale = floor is None
    if floor is None:
        # (more than half of the paper exactly 0 even here: the level of the rest)
        paper = level if level > 0 else _noise_threshold(d, live & (d > 0))
        step = MIN_DARKNESS_STEP / lit if lit > 0 else MIN_DARKNESS_STEP
        floor = max(step, min(MAX_DARKNESS_FLOOR, paper))
    glob = max(floor, level)
    t = max(16, int(tile_px))
    ny, nx = max(1, h // t), max(1, w // t)
    th, tw = (h // ny) // 2 * 2, (w // nx) // 2 * 2
    # Every other pixel is enough for the statistics (and halves the work).
    sub = np.where(live[: ny * th : 2, : nx * tw : 2], d[: ny * th : 2, : nx * tw : 2], np.nan)
    blocks = sub.reshape(ny, sub.shape[0] // ny, nx, sub.shape[1] // nx).transpose(0, 2, 1, 3)
    blocks = blocks.reshape(ny, nx, -1)
    count = np.sum(np.isfinite(blocks), axis=2)
    # Printed lines are outliers on the dark side: clipped out before the statistics (dense
    # thick rings may cover half a tile).
    thr = tile_thresholds(blocks)
    enough = count >= 0.25 * blocks.shape[2]
    censored = floor if first_scale else glob
    thr = np.where(enough, np.where(np.isfinite(thr), np.maximum(thr, floor), censored), glob)
    thr = thr.astype(np.float32)
    # (float32: a float64 darkness divided by it is the same as by its float64 copy)
    return cv2.resize(thr, (w, h), interpolation=cv2.INTER_LINEAR), floor


# --------------------------------------------------------------------------------------------
# Candidate centres


def _hough_lines(mask: NDArray, min_votes: int) -> NDArray:
    """Every Hough line of ``mask`` (``(rho, theta)``, 1 px and 0.25 deg steps) with more
    than ``max(min_votes, 10)`` pixels, strongest first:
    shape ``(N, 2)``, float32 as OpenCV gives them (OpenCV's lines, computed faster:
    :func:`~calibration.detection.hough.hough_lines`), N may be 0. The distinct ones are
    :func:`_distinct_lines`."""
    return hough_lines(mask, np.pi / 720, max(min_votes, 10))


def _distinct_lines(
    lines: NDArray, size: tuple[int, int], max_lines: int
) -> list[tuple[float, float]]:
    """The ``max_lines`` strongest distinct lines of :func:`_hough_lines`'s ``(N, 2)`` output
    in an image of ``size`` (width, height) px, strongest first.

    A line within 4 deg of a stronger one that crosses it inside the image widened by half
    its size on each side, or passes within 15 px of it at the image's centre, is the same
    line and is left out. The first ``k`` of ``max_lines`` are the ``k`` strongest: a later
    pass can ask for more lines of the same output.
    """
    w, h = size
    mid = np.array([w / 2, h / 2, 1.0])
    out: list[tuple[float, float]] = []
    for rho, theta in lines:
        if len(out) >= max_lines:
            break
        dup = False
        l1 = _line_from_hough(rho, theta)
        for r2, t2 in out:
            dth = abs((theta - t2 + np.pi / 2) % np.pi - np.pi / 2)
            if dth > np.radians(4):
                continue
            l2 = _line_from_hough(r2, t2)
            x = intersect_lines(l1, l2)
            crossing_inside = abs(x[2]) > 1e-12 and (
                -w / 2 <= x[0] / x[2] <= 1.5 * w and -h / 2 <= x[1] / x[2] <= 1.5 * h
            )
            if crossing_inside or abs(float(l1 @ mid) - float(l2 @ mid)) < 15:
                dup = True
                break
        if not dup:
            out.append((float(rho), float(theta)))
    return out


def _line_from_hough(rho: float, theta: float) -> NDArray:
    return np.array([np.cos(theta), np.sin(theta), -rho])


def _sample(img: NDArray, u: NDArray, v: NDArray) -> NDArray:
    """Bilinear samples of ``img`` at ``(u, v)`` (0 outside the image), float64, same shape.

    OpenCV's remap: several times faster than ``map_coordinates`` for these scattered
    samples; its weights are quantised to 1/32 px, far below what the ray profiles and the
    level medians sampled here resolve.
    """
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    h, w = img.shape
    src = img if img.dtype in (np.float32, np.float64) else img.astype(np.float32)
    n, cols = u.size, 1024
    rows = max(1, -(-n // cols))
    map_u = np.full(rows * cols, -10.0, np.float32)
    map_v = np.full(rows * cols, -10.0, np.float32)
    map_u[:n], map_v[:n] = u.ravel(), v.ravel()
    out = cv2.remap(
        src,
        map_u.reshape(rows, cols),
        map_v.reshape(rows, cols),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    values = out.reshape(-1)[:n].astype(np.float64).reshape(u.shape)
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    return np.where(inside, values, 0.0)


def _fitted_rays(
    d: NDArray,
    c: NDArray,
    radii: NDArray,
    thr: float,
    axis_angles: list[float],
    n_rays: int,
    ring0_hidden: bool,
    bundle_step_px: float,
) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """The rays of :func:`_label_rays`: their angles, crossings labelled (count, distances
    ``(R, K)``) and whether they fit the projectivity."""
    angles = np.linspace(0, 2 * np.pi, n_rays, endpoint=False) + 0.013
    # (not within 6 deg of a diameter)
    off_axes = (angles[:, None] - np.asarray(axis_angles)[None, :] + np.pi) % (2 * np.pi) - np.pi
    angles = angles[np.all(np.abs(off_axes) > np.radians(6), axis=1)]
    count, peaks, err = label_rays(
        d, c, angles, radii, thr, FIT_TOL_PX, FIT_TOL_FRACTION, ring0_hidden, bundle_step_px
    )
    last = np.max(np.nan_to_num(peaks, nan=0.0), axis=1)  # the farthest labelled crossing
    ok = (count >= 3) & (err <= FIT_TOL_PX + FIT_TOL_FRACTION * last)
    return angles, count, peaks, ok


def starts_hidden(d: NDArray, c: NDArray) -> bool:
    """Whether rays from ``c`` start under hidden print (a laser stripe or glare over it):
    whether any map value that their first samples' bilinear corners read (a pixel around
    ``c``) is negative in ``d`` ``(H, W)``; such rays start where they leave it
    (:func:`~calibration.detection.ray_kernels.label_rays`)."""
    u0, v0 = int(np.floor(c[0])), int(np.floor(c[1]))
    around = d[max(v0 - 1, 0) : max(v0 + 3, 0), max(u0 - 1, 0) : max(u0 + 3, 0)]
    return bool(np.any(around < 0))


def _ray_support(
    d: NDArray,
    c: NDArray,
    radii: NDArray,
    thr: float,
    axis_angles: list[float],
    n_rays: int = 96,
    ring0_hidden: bool = False,
    bundle_step_px: float = 0.0,
) -> int:
    """The support of ``c``: :func:`_label_rays`'s second result, without its rings."""
    _, count, _, ok = _fitted_rays(
        d, c, radii, thr, axis_angles, n_rays, ring0_hidden, bundle_step_px
    )
    return int(np.sum(count[ok] - 2))


def _label_rays(
    d: NDArray,
    c: NDArray,
    radii: NDArray,
    thr: float,
    axis_angles: list[float],
    n_rays: int = 96,
    ring0_hidden: bool = False,
    bundle_step_px: float = 0.0,
) -> tuple[list[list[tuple[float, NDArray]]], int]:
    """Ring crossings labelled by the 1-D projectivity along rays from ``c``.

    Returns per ring a list of (angle, point px) and the support of ``c``: over the rays
    whose crossings fit the projectivity, the crossings beyond the two that any fit of its
    two parameters takes (three crossings fit nearly any point near a target; a centre whose
    rays cross every ring in order is the target's; :func:`_ray_support` gives it alone).
    ``ring0_hidden``, ``bundle_step_px``: see
    :func:`~calibration.detection.ray_kernels.label_rays`.
    """
    angles, count, peaks, ok = _fitted_rays(
        d, c, radii, thr, axis_angles, n_rays, ring0_hidden, bundle_step_px
    )
    fitted, fitted_angles = peaks[ok], angles[ok]
    dirs = np.column_stack([np.cos(fitted_angles), np.sin(fitted_angles)])
    per_ring: list[list[tuple[float, NDArray]]] = []
    for k in range(len(radii)):
        seen = np.isfinite(fitted[:, k])
        points = c + fitted[seen, k, None] * dirs[seen]
        per_ring.append(list(zip(fitted_angles[seen].tolist(), points, strict=True)))
    return per_ring, int(np.sum(count[ok] - 2))
