"""Concentric-circles detector, the diameters: found, measured between the rings, checked.

Step 5 of :mod:`calibration.detection.concentric`: the two diameter lines through the pencil's
centre from an angular scan of the darkness (:func:`_diameter_lines`), each located to
sub-pixel between the rings by the rings' centroid profiles (:func:`_refine_axes`), and shown
to be printed (:func:`_line_evidence`). A diameter a laser stripe hides (the paper's set-up
puts the stripe along A-O-B) is the other one's conjugate (:func:`conjugate_diameter`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from calibration.detection.concentric_rings import (
    SplineWindow,
    _conic_point_on_ray,
    _locate_centres,
    _perimeter_px,
    _unit_line,
)
from calibration.detection.conics import fit_line, line_through

__all__ = ["Refit", "conjugacy_deg", "conjugate_diameter"]

#: Least share of a diameter's samples between the rings that are dark (over the noise
#: threshold) for the angular scan (:func:`_diameter_lines`) to take its direction.
MIN_DARK_SHARE = 0.3

#: The share that will do for the second diameter within :data:`CONJUGATE_WINDOW_DEG` of the
#: first one's conjugate, where the rings put it: randomised view 17:101 (a faint print,
#: contrast over noise 3.5, under 1.7 px of blur) shows 15-25 % there, paper 0-4 %.
CONJUGATE_DARK_SHARE = 0.15

#: How far from the first diameter's conjugate (deg) the second is looked for: the coarse
#: rings' conjugate is within 1.7 deg of the print on right views (MAX_CONJUGACY_DEG's data).
CONJUGATE_WINDOW_DEG = 3.0

#: A refit of the two diameters (:func:`_refine_axes` with the rest of its arguments bound):
#: from the lines and the index of one hidden under a stripe, the refitted lines and their
#: points, or ``None``.
Refit = Callable[[list[NDArray], int | None], tuple[list[NDArray], list[NDArray]] | None]


def _diameter_lines(
    z: NDArray, c: NDArray, conics: dict[int, NDArray], line_px: float, spacing_px: float
) -> tuple[list[NDArray], int | None] | None:
    """The two diameter lines through the pencil's centre ``c``, from an angular scan.

    For every direction through ``c`` (steps of about half a line width at the outer ring,
    at most 1440 over 180 deg; samples every other pixel along it)
    the mean darkness ``z`` (in units of its noise threshold; negative where the print is
    hidden, which is left out) on the paper between the rings, inside the largest ring; the
    diameters are the two darkest directions at least 12 deg apart, each dark (over the
    threshold) on at least :data:`MIN_DARK_SHARE` of its samples and on 3 times the median
    direction's share (two perpendicular diameters stay over 45 deg apart in the image up to
    a 65 deg tilt). Where no second direction is that dark, the darkest within
    :data:`CONJUGATE_WINDOW_DEG` of the first one's conjugate (:func:`conjugate_diameter`)
    will do with :data:`CONJUGATE_DARK_SHARE`. The Hough lines that gave the candidate
    centre may be a laser stripe's edge or clutter through it; these are the print's. None
    when no two directions pass. At least 360 directions are scanned; samples run to the
    outer ring or the image's farthest corner.

    A laser stripe along a diameter hides it whole (the paper's set-up puts the stripe on
    A-O-B): where only one direction is dark, the other diameter is its conjugate
    (:func:`conjugate_diameter`), taken when the print is hidden on most of its samples.

    Returns
    -------
    (list of two ndarray, shape (3,), int or None) or None
        Homogeneous lines ``(a, b, c)`` with ``a^2 + b^2 = 1``, and the index of a line
        hidden under a stripe (``None``: both seen).
    """
    h, w = z.shape
    outer = conics[max(conics)]
    r_out = _perimeter_px(outer, c) / (2 * np.pi)
    n_ang = int(np.clip(np.ceil(np.pi * r_out / max(0.5 * line_px, 0.5)), 360, 1440))
    theta = np.arange(n_ang) * (np.pi / n_ang)
    dirs = np.column_stack([np.cos(theta), np.sin(theta)])
    both = np.vstack([dirs, -dirs])
    ts = np.array([_conic_point_on_ray(conics[k], c, both) for k in sorted(conics)])
    t_out = ts[-1]
    if not np.isfinite(t_out).any():
        return None
    step = 2.0  # (a line is long: every other px)
    corner = float(
        np.max(np.hypot(np.array([0.0, w - 1.0]) - c[0], np.array([0.0, h - 1.0])[:, None] - c[1]))
    )
    t = np.arange(1.0, min(float(np.nanmax(t_out)), corner) + 1.0, step)
    clear = max(1.0, min(0.5 * line_px + 2.0, 0.35 * spacing_px))
    with np.errstate(invalid="ignore"):
        valid = (t[None, :] < t_out[:, None]) & (t[None, :] > max(2.0 * line_px + 3.0, clear))
    # samples within ``clear`` of a ring's crossing are left out (each ring's few, by index)
    rows = np.arange(len(both))[:, None]
    reach = np.arange(-int(clear / step) - 1, int(clear / step) + 2)
    for tk in ts:
        near = np.floor((np.nan_to_num(tk, nan=-1e6) - t[0]) / step).astype(np.intp)[:, None]
        idx = near + reach[None, :]
        hit = (idx >= 0) & (idx < len(t))
        hit &= np.abs(t[np.clip(idx, 0, len(t) - 1)] - tk[:, None]) <= clear
        valid[np.broadcast_to(rows, idx.shape)[hit], idx[hit]] = False
    u = np.rint(c[0] + t[None, :] * both[:, 0:1]).astype(np.intp)
    v = np.rint(c[1] + t[None, :] * both[:, 1:2]).astype(np.intp)
    valid &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    zs = z[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)]
    covered = valid & (zs < 0)
    valid &= zs >= 0

    def per_line(x: NDArray) -> NDArray:
        total = np.where(valid, x, 0).sum(axis=1)
        return total[:n_ang] + total[n_ang:]

    n_valid = per_line(np.ones_like(zs))
    usable = n_valid >= 10
    dark = np.where(usable, per_line(zs > 1.0) / np.maximum(n_valid, 1), 0.0)
    # where on the line: the mean darkness (clipped), which peaks on the line's middle
    # where the share of dark samples is flat
    strength = np.where(usable, per_line(np.clip(zs, 0.0, 4.0)) / np.maximum(n_valid, 1), 0.0)
    strength = (np.roll(strength, 1) + 2 * strength + np.roll(strength, -1)) / 4
    lines = []
    taken = np.zeros(n_ang, bool)
    common = 3 * float(np.median(dark))
    for found in range(2):
        i = int(np.argmax(np.where(taken, -1.0, strength)))
        if dark[i] < MIN_DARK_SHARE or dark[i] < common:
            if found == 0:
                return None
            other = conjugate_diameter(lines[0], c, conics)
            angle = float(np.arctan2(other[0], -other[1])) % np.pi
            j = int(np.rint(angle / (np.pi / n_ang))) % n_ang
            # (hidden: the samples the stripe covers, of all within the rings)
            n_covered = np.count_nonzero(covered[[j, j + n_ang]])
            n_seen = np.count_nonzero(valid[[j, j + n_ang]])
            if n_covered >= 10 and n_covered >= 1.5 * n_seen:
                return [lines[0], other], 1
            # A faint second diameter where the rings put it: the geometry vouches for the
            # direction, so a smaller share of dark samples will do.
            near = np.abs((theta - angle + np.pi / 2) % np.pi - np.pi / 2) < np.radians(
                CONJUGATE_WINDOW_DEG
            )
            i = int(np.argmax(np.where(near & ~taken, strength, -1.0)))
            if not (near & ~taken)[i] or dark[i] < CONJUGATE_DARK_SHARE or dark[i] < common:
                return None
        a, b0, cc = strength[i - 1], strength[i], strength[(i + 1) % n_ang]
        curv = a - 2 * b0 + cc
        off = 0.5 * (a - cc) / curv if curv < 0 else 0.0
        ang = (i + off) * (np.pi / n_ang)
        lines.append(line_through(c, ang))
        near = np.abs((theta - ang + np.pi / 2) % np.pi - np.pi / 2) < np.radians(12)
        taken |= near
    return lines, None


def conjugate_diameter(line: NDArray, c: NDArray, conics: dict[int, NDArray]) -> NDArray:
    """The image of the diameter perpendicular to the one imaged as ``line``.

    Exact for images of concentric circles, lens distortion aside: the polar of the image
    of O with respect to a ring's conic is the vanishing line; ``line`` meets it at its
    diameter's vanishing point, whose polar is the perpendicular diameter (through O). Each
    ring gives it; their mean direction is taken, through ``c``.

    Parameters
    ----------
    line : ndarray, shape (3,)
        A diameter's image, homogeneous, through (or near) ``c``.
    c : ndarray, shape (2,)
        The image of O, px.
    conics : dict of int to ndarray, shape (3, 3)
        Ring conics.

    Returns
    -------
    ndarray, shape (3,)
        Homogeneous line through ``c`` with ``a^2 + b^2 = 1``.
    """
    ch = np.array([c[0], c[1], 1.0])
    normals = []
    for conic in conics.values():
        vanishing = conic @ ch
        other = conic @ np.cross(line, vanishing)
        n = other[:2] / max(float(np.hypot(other[0], other[1])), 1e-300)
        if normals and float(n @ normals[0]) < 0:
            n = -n
        normals.append(n)
    n = np.mean(normals, axis=0)
    n /= np.linalg.norm(n)
    return np.array([n[0], n[1], -float(n @ c)])


def conjugacy_deg(lines: list[NDArray], c: NDArray, conics: dict[int, NDArray]) -> float:
    """How far two lines through ``c`` are from being the images of perpendicular diameters.

    The largest angle, deg, between either line and the other's conjugate with respect to the
    ring conics (:func:`conjugate_diameter`): 0 for the target's two diameters but for noise
    and lens distortion (at most 0.12 deg on the modern cell's lens, k1 = -0.12), tens of
    degrees for a line through the centre that is not a diameter.

    Parameters
    ----------
    lines : list of two ndarray, shape (3,)
        Homogeneous lines through (or near) ``c``.
    c : ndarray, shape (2,)
        The image of O, px.
    conics : dict of int to ndarray, shape (3, 3)
        Ring conics.

    Returns
    -------
    float
        The larger of the two angles, deg (0 to 90).
    """
    return max(
        _lines_angle_deg(lines[1 - i], conjugate_diameter(lines[i], c, conics)) for i in range(2)
    )


def _lines_angle_deg(line_a: NDArray, line_b: NDArray) -> float:
    """The angle between two homogeneous image lines, deg (0 to 90)."""
    na, nb = _unit_line(line_a)[:2], _unit_line(line_b)[:2]
    return float(np.degrees(np.arccos(np.clip(abs(float(na @ nb)), 0.0, 1.0))))


def _normal_clear_of(conic: NDArray, points: NDArray, normal: NDArray, reach: float) -> NDArray:
    """Whether the segments ``p + tau normal``, ``|tau| <= reach``, through each of the
    ``(M, 2)`` points stay off the conic (``(M,)`` bool)."""
    x = np.column_stack([points, np.ones(len(points))])
    nh = np.array([normal[0], normal[1], 0.0])
    a = float(nh @ conic @ nh)
    b = x @ (conic @ nh)
    cc = np.einsum("ij,jk,ik->i", x, conic, x)
    disc = b * b - a * cc
    clear = disc < 0
    # roots of a tau^2 + 2 b tau + cc = 0 in the stable form (q / a and cc / q)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = -(b + np.copysign(np.sqrt(np.maximum(disc, 0.0)), b))
        taus = [q / a, cc / q]
    near = np.zeros(len(points), bool)
    for tau in taus:
        near |= np.abs(tau) <= reach
    return clear | ~near


def _refine_axes(
    spline: SplineWindow,
    axis_lines: list[NDArray],
    c: NDArray,
    conics: dict[int, NDArray],
    radii: NDArray,
    half_window: float,
    line_px: float,
    size: tuple[int, int],
    bright: NDArray | None = None,
    hidden_axis: int | None = None,
) -> tuple[list[NDArray], list[NDArray]] | None:
    """Sub-pixel points on both diameter lines, between the rings; refitted lines.

    A profile across a diameter runs along the rings beside it, so it only has to stay clear
    of their printed lines and blur: between closely spaced rings the points keep half a
    line width and 1.5 px from them rather than a whole profile window. The line
    ``hidden_axis`` under a laser stripe, or one that gives too few points where the stripe
    covers most of it, has no points: it is the refitted other one's conjugate
    (:func:`conjugate_diameter`).
    """
    w, h = size
    keys = sorted(conics)
    new_lines, new_pts = [], []
    for index, ln in enumerate(axis_lines):
        if index == hidden_axis:
            new_lines.append(ln)
            new_pts.append(np.zeros((0, 2)))
            continue
        ln = _unit_line(ln)
        # Re-anchor the line through the current centre (keeps its direction).
        ln = np.array([ln[0], ln[1], -(ln[0] * c[0] + ln[1] * c[1])])
        dirv = np.array([-ln[1], ln[0]])
        samples = []
        for sgn in (1.0, -1.0):
            ts = [0.0]
            for k in keys:
                t = _conic_point_on_ray(conics[k], c, (sgn * dirv)[None, :])[0]
                ts.append(float(t) if np.isfinite(t) else np.nan)
            ts_a = np.asarray(ts)
            for a, b in itertools.pairwise(ts_a):
                if not (np.isfinite(a) and np.isfinite(b)):
                    continue
                gap = b - a
                clear = max(0.5 * line_px + 1.5, min(half_window + 1.5, 0.5 * gap - 1.0))
                if gap < 2 * clear:
                    continue
                n = max(1, int((gap - 2 * clear) / 2))
                for tt in np.linspace(a + clear, b - clear, n):
                    samples.append(c + sgn * tt * dirv)
        if len(samples) < 4:
            return None
        pts = np.asarray(samples)
        pts = pts[_inside(pts, half_window + 3, (w, h))]
        search = max(1.0, 2 * half_window)
        # The centroid's window across the diameter must not reach a ring: where a ring runs
        # nearly along the diameter (a steep tilt puts its flank there) it would, though the
        # sample is well clear of the crossing along the line, and pull the centre towards
        # it. (A ring further out but within the search is the line fit's outlier to drop.)
        reach = half_window + 0.5 * line_px + 1.5
        for conic in conics.values():
            pts = pts[_normal_clear_of(conic, pts, ln[:2], reach)]
        found = np.zeros((0, 2))
        if len(pts) >= 4:
            normals = np.tile(ln[:2], (len(pts), 1))
            off, contrast, good = _locate_centres(
                spline, pts, normals, half_window, search, 0.125, bright
            )
            med = np.median(contrast[good]) if good.any() else 0.0
            good &= contrast > 0.5 * med
            found = (pts + off[:, None] * normals)[good]
        if len(found) < 4:
            # too few points: refused, unless a stripe covers the line (its conjugate then)
            covered = (
                bright is not None
                and hidden_axis is None
                and _under_stripe(bright, np.asarray(samples), ln[:2], half_window + 1.0)
            )
            if not covered:
                return None
            hidden_axis = index
            new_lines.append(ln)
            new_pts.append(np.zeros((0, 2)))
            continue
        # Trimmed from the line through the centre it came as (right to a line's width), not
        # from a first fit to all points: centres caught by a ring's flank along a stretch of
        # the diameter would turn that fit, and the trimming would keep them.
        line, kept = ln, found
        for i in range(4):
            dist = found @ line[:2] + line[2]
            sig = 1.4826 * float(np.median(np.abs(dist))) + 1e-3
            # (first from the incoming line, a few px: a direction off by a fraction of a
            # degree must not cut the far points of one side)
            keep = np.abs(dist) < max(3 * sig, 2.0 if i == 0 else 0.5)
            if keep.sum() < 4:
                if i == 0:  # too few near the incoming line: a fit to all of them
                    line = fit_line(found)
                break
            same = len(kept) == keep.sum() and np.array_equal(kept, found[keep])
            kept = found[keep]
            line = fit_line(kept)
            if same:
                break
        new_lines.append(line)
        new_pts.append(kept)
    if hidden_axis is not None:
        if len(new_pts[1 - hidden_axis]) == 0:
            return None
        new_lines[hidden_axis] = conjugate_diameter(new_lines[1 - hidden_axis], c, conics)
    return new_lines, new_pts


def _settled_axes(
    refit: Refit,
    axis_lines: list[NDArray],
    c: NDArray,
    conics: dict[int, NDArray],
    hidden_axis: int | None = None,
    tol_px: float = 0.1,
    max_rounds: int = 6,
) -> tuple[list[NDArray], list[NDArray], int | None] | None:
    """``refit`` (:func:`_refine_axes` of the lines and the hidden one's index) repeated until
    neither line moves by more than ``tol_px`` within the outer ring, at most ``max_rounds``
    times: the lines, their points and the index of a line hidden under a stripe (``None``:
    both seen); ``None`` if not even the first round measures them.

    Each round samples the diameter along the line it was given, so a line that came in
    degrees off (a Hough line through a small, steeply tilted target: 26 deg on one
    benchmark view) is only turned part of the way in one round. A line may also settle into
    a small oscillation, its trimmed points changing by one from round to round; a later
    round that measures nothing (its samples moved onto a ring) leaves the last one's.
    """
    r_out = _perimeter_px(conics[max(conics)], c) / (2 * np.pi)
    settled = None
    for _ in range(max_rounds):
        res = refit(axis_lines, hidden_axis)
        if res is None:
            break
        moved = max(_line_shift_px(a, b, c, r_out) for a, b in zip(axis_lines, res[0]))
        axis_lines, axis_pts = res
        hidden_axis = next((i for i, pts in enumerate(axis_pts) if len(pts) == 0), None)
        settled = (axis_lines, axis_pts, hidden_axis)
        if moved <= tol_px:
            break
    return settled


def _line_shift_px(old: NDArray, new: NDArray, c: NDArray, reach_px: float) -> float:
    """Largest distance, px, from ``new`` to the points of ``old`` within ``reach_px`` of the
    foot of ``c`` on it (the lines pass near ``c``, the centre)."""
    old, new = _unit_line(old), _unit_line(new)
    dirv = np.array([-old[1], old[0]])
    foot = c - (old[:2] @ c + old[2]) * old[:2]
    ends = np.vstack([foot + reach_px * dirv, foot - reach_px * dirv])
    return float(np.max(np.abs(ends @ new[:2] + new[2])))


def _inside(points: NDArray, margin: float, size: tuple[int, int]) -> NDArray:
    """Whether each of the ``(M, 2)`` points lies over ``margin`` px inside the image."""
    w, h = size
    return (
        (points[:, 0] > margin)
        & (points[:, 0] < w - margin - 1)
        & (points[:, 1] > margin)
        & (points[:, 1] < h - margin - 1)
    )


def _under_stripe(bright: NDArray, points: NDArray, normal: NDArray, reach: float) -> bool:
    """Whether a laser stripe or glare (``bright``) lies within ``reach`` px across the line
    (unit ``normal``) of most of its ``(M, 2)`` points: their centroid windows would touch it."""
    h, w = bright.shape
    blocked = np.zeros(len(points), bool)
    for tau in np.linspace(-reach, reach, 5):
        q = points + tau * normal
        iu = np.clip(np.rint(q[:, 0]).astype(np.intp), 0, w - 1)
        iv = np.clip(np.rint(q[:, 1]).astype(np.intp), 0, h - 1)
        blocked |= bright[iv, iu] > 0
    return bool(np.mean(blocked) >= 0.6)


def _line_evidence(
    d: NDArray,
    line: NDArray,
    c: NDArray,
    ends_px: NDArray,
    offset_px: float,
    ring_dark: float,
    bright: NDArray | None = None,
) -> float:
    """Median darkness on ``line`` minus that on its two parallels ``offset_px`` away.

    Sampled every pixel between the line's two crossings ``ends_px`` ``(2, 2)`` of the
    largest ring (beyond them the diameter is not printed; on a steeply tilted target a
    fixed reach would take mostly paper or surroundings along the short diameter), inside
    the image. The rings cross the line and its parallels alike, so only the samples whose
    parallels are on paper (darker than half ``ring_dark``, the rings' darkness, on neither)
    count: there a printed diameter shows its own darkness, a line through the centre that
    is not a diameter shows none. Closely spaced thick rings would otherwise fill the median.
    Samples where the print is hidden (``bright``, a laser stripe along the line) on the line
    or its parallels tell nothing and are left out.
    """
    h, w = d.shape
    ln = _unit_line(line)
    n = ln[:2]
    e = np.array([-n[1], n[0]])
    foot = c - (float(n @ c) + ln[2]) * n
    t_ends = (np.asarray(ends_px, dtype=np.float64) - foot) @ e
    t = np.arange(float(t_ends.min()), float(t_ends.max()) + 0.5, 1.0)
    pts = foot + t[:, None] * e
    pts = pts[_inside(pts, offset_px + 1, (w, h))]
    if len(pts) < 10:
        return 0.0

    def along(img: NDArray, p: NDArray) -> NDArray:
        # (a uint8 mask's samples in float64, not rounded to its integers)
        out = np.float64 if img.dtype == np.uint8 else None
        return ndimage.map_coordinates(img, [p[:, 1], p[:, 0]], order=1, output=out)

    sides = np.stack([along(d, pts + offset_px * n), along(d, pts - offset_px * n)])
    seen = np.ones_like(sides, dtype=bool)
    on_line = np.ones(len(pts), dtype=bool)
    if bright is not None:
        seen[0] = along(bright, pts + offset_px * n) == 0
        seen[1] = along(bright, pts - offset_px * n) == 0
        on_line = along(bright, pts) == 0
    # each sample against the parallels that are seen (one, where a stripe covers the other)
    paper = on_line & seen.any(axis=0) & np.all((sides < 0.5 * ring_dark) | ~seen, axis=0)
    if np.count_nonzero(paper) < 10:
        return 0.0
    side = np.sum(np.where(seen, sides, 0.0), axis=0) / np.maximum(seen.sum(axis=0), 1)
    return float(np.median(along(d, pts[paper]) - side[paper]))
