"""Concentric-circles detector, sub-pixel stage: the ring conics, their pencil, the diameters.

Steps 4-5 of :mod:`calibration.detection.concentric`: the image of O from the pencil of ring
conics (:func:`_pencil_centre`); then, for every ring, profiles along the conic's normals
whose printed line's centre is the fixed point of a symmetric-window centroid
(:func:`_locate_centres`), the conic refitted with outlier rejection (:func:`_refine_ring`),
checked against the other rings' pencil (:func:`_prune_by_pencil`). The diameters, located
the same way between the rings, are in :mod:`calibration.detection.concentric_axes`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from calibration.detection.bspline import spline_filter
from calibration.detection.conics import (
    conic_ray_distances,
    fit_conic,
    pencil_center,
    pencil_member,
    sampson_distances,
)
from calibration.detection.profile_kernels import profile_line_centres, window_touches

__all__ = [
    "MIN_CONIC_POINTS",
    "ConcentricDetectorSettings",
    "SplineWindow",
    "concentric_affine_conics",
    "concentric_affine_linear",
]

#: Fewest points a ring's conic is fitted to (five pin a conic; a few more outvote a bad one).
MIN_CONIC_POINTS = 8


@dataclass(frozen=True)
class ConcentricDetectorSettings:
    """Tuning of :func:`detect_concentric` (defaults suit 0.3 to 20 Mpx images)."""

    max_tilt_deg: float = 67.0
    """Views tilted more than this from the line of sight through O are refused. The tilt is
    read off the outer ring with the principal point at the image's centre
    (:func:`~calibration.detection.conics.circle_tilt_deg`) where the rings are flattened to
    under ``cos(max_tilt_deg - 15)``; rounder views are judged by their flatness against
    ``cos(max_tilt_deg)``. The detector is specified for tilts up to 65 deg; the estimate is
    within 0.6 deg on 95 % of the randomised benchmark's detected views over 40 deg (seeds
    0-2; at most 1.5 deg over, 4.1 deg under, on 3-ring views), and a principal point 2 % of
    the width off moves it by up to 0.6 deg: hence the margin."""
    min_rings: int = 3
    """Fewest rings with a fitted conic for a detection."""
    ray_step_px: float = 0.125
    """Sampling step of the sub-pixel profiles."""
    max_conic_rms_px: float = 0.6
    """Rings whose refitted conic leaves a larger RMS are dropped; on widely spaced rings the
    limit is ``max_conic_rms_fraction`` of the spacing, on noisy ones 1.5 times the scatter
    from one centre-line point to the next, where those are larger."""
    max_conic_rms_fraction: float = 0.05
    """The limit's share of the ring spacing: a faint line's centre scatters by a few % of
    the spacing, a conic through points of a neighbouring ring is off by half of it."""
    min_arc_fraction: float = 0.25
    """A ring needs edge points over at least this fraction of its directions."""


@dataclass
class SplineWindow:
    """Cubic-spline coefficients of the part of the darkness map the fine stage samples.

    The prefilter runs over the whole of an image otherwise, though the profiles across the
    rings and diameters only reach a little beyond the rings (:func:`spline_window`). A profile
    that comes nearer than :data:`SPLINE_WINDOW_GUARD_PX` to an edge of the window inside the
    image is sampled on the whole map's spline instead (prefiltered once, when first needed):
    the values are the whole map's either way.
    """

    darkness: NDArray
    """Shape (H, W): the whole darkness map."""
    coef: NDArray
    """Shape (H', W'): :func:`scipy.ndimage.spline_filter` (order 3) of the window."""
    origin_px: tuple[int, int]
    """The window's first pixel ``(u, v)`` in the image."""
    whole: NDArray | None = field(default=None, repr=False)
    """The whole map's coefficients, once a profile needed them."""

    def covering(
        self, points: NDArray, normals: NDArray, span_px: float
    ) -> tuple[NDArray, tuple[int, int]]:
        """Coefficients and their origin for the samples ``points + t normals``,
        ``|t| <= span_px``: the window's where all of them keep the guard from its edges inside
        the image, else the whole map's.

        Parameters
        ----------
        points, normals : ndarray, shape (N, 2)
        span_px : float
        """
        h, w = self.darkness.shape
        hh, ww = self.coef.shape
        u0, v0 = self.origin_px
        g = SPLINE_WINDOW_GUARD_PX
        with np.errstate(invalid="ignore"):
            reach = span_px * np.abs(normals)
            lo = np.nanmin(points - reach, axis=0) if len(points) else np.zeros(2)
            hi = np.nanmax(points + reach, axis=0) if len(points) else np.zeros(2)
        inside = (
            (u0 == 0 or lo[0] >= u0 + g)
            and (v0 == 0 or lo[1] >= v0 + g)
            and (u0 + ww == w or hi[0] <= u0 + ww - 1 - g)
            and (v0 + hh == h or hi[1] <= v0 + hh - 1 - g)
        )
        if inside:
            return self.coef, self.origin_px
        if self.whole is None:
            self.whole = spline_filter(self.darkness)
        return self.whole, (0, 0)


#: Pixels kept between a profile's farthest sample and a window's edge inside the image: the
#: cubic spline's prefilter decays as 0.268 per pixel, so there the coefficients are those of
#: the whole image to 1e-17.
SPLINE_WINDOW_GUARD_PX = 32


def spline_window(
    darkness: NDArray, conics: list[NDArray], c: NDArray, reach_px: float
) -> SplineWindow:
    """The spline of ``darkness`` over the box of the ring ``conics`` (around ``c``) widened by
    ``reach_px`` (the farthest a profile samples from a ring point) and a guard; the whole
    map where a conic does not close around ``c``.

    Parameters
    ----------
    darkness : ndarray, shape (H, W)
    conics : list of ndarray, shape (3, 3)
        The rings' coarse conics (their labels may still be wrong: all of them).
    c : ndarray, shape (2,)
        A point inside them (the centre's image).
    reach_px : float
    """
    h, w = darkness.shape
    angles = np.linspace(0, 2 * np.pi, 256, endpoint=False)
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    t = np.array([_conic_point_on_ray(conic, c, dirs) for conic in conics]).reshape(-1, 256)
    u0, v0, u1, v1 = 0, 0, w, h
    if t.size and np.all(np.isfinite(t)):
        pts = c + t.reshape(-1, 1) * np.tile(dirs, (len(t), 1))
        # (the 256 directions' points may miss the box's edge by a little: 1 % of the size;
        # a profile that reaches further is sampled on the whole map, see SplineWindow)
        grow = reach_px + SPLINE_WINDOW_GUARD_PX + 0.01 * float(np.max(t)) + 2.0
        lo = np.floor(pts.min(axis=0) - grow).astype(int)
        hi = np.ceil(pts.max(axis=0) + grow).astype(int) + 1
        u0, v0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
        u1, v1 = min(int(hi[0]), w), min(int(hi[1]), h)
        if u1 - u0 < 8 or v1 - v0 < 8:
            u0, v0, u1, v1 = 0, 0, w, h
    coef = spline_filter(darkness[v0:v1, u0:u1])
    return SplineWindow(darkness, coef, (u0, v0))


def _locate_centres(
    spline: SplineWindow,
    points: NDArray,
    normals: NDArray,
    half_window: float,
    search: float,
    step: float,
    bright: NDArray | None = None,
) -> tuple[NDArray, NDArray, NDArray]:
    """Sub-pixel centre of a dark line near each of ``points`` along its ``normals``.

    ``spline`` is the cubic-spline prefiltered darkness map. Returns (offset along the normal,
    peak contrast above the local baseline, ok mask).
    """
    span = search + half_window + 1.0
    tau = np.arange(-span, span + step / 2, step)
    coef, origin = spline.covering(points, normals, span)
    c, contrast = profile_line_centres(coef, points, normals, tau, half_window, search, origin)
    ok = np.isfinite(c) & (np.abs(c) < search) & (contrast > 0)
    if bright is not None:
        # A line whose window touches something brighter than the paper (laser stripe,
        # glare) is biased; beyond the window (where the search went) it does no harm.
        ok &= ~window_touches(bright, points, normals, tau, c, half_window + 1.0)
    return c, contrast, ok


def _conic_point_on_ray(conic: NDArray, c: NDArray, dirs: NDArray) -> NDArray:
    """Positive t where ``c + t dir`` meets the conic, per direction (NaN if none):
    :func:`~calibration.detection.conics.conic_ray_distances`."""
    return conic_ray_distances(conic, c, dirs)


def _conic_normals(conic: NDArray, pts: NDArray) -> NDArray:
    x = np.column_stack([pts, np.ones(len(pts))])
    g = (x @ conic)[:, :2]
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def _conic_axes_ratio(conic: NDArray) -> float:
    """minor/major axis ratio of an ellipse conic (0 if not an ellipse)."""
    a = conic[:2, :2]
    w = np.linalg.eigvalsh(a)
    if w[0] * w[1] <= 0:
        return 0.0
    w = np.abs(w)
    return float(np.sqrt(min(w) / max(w)))


def _ellipse_ok(conic: NDArray, c: NDArray) -> bool:
    a = conic[:2, :2]
    if np.linalg.det(a) <= 0:
        return False
    x = np.array([c[0], c[1], 1.0])
    # The centre must be inside: sign of x^T C x opposite to the sign of the quadratic part.
    return float(x @ conic @ x) * float(np.trace(a)) < 0


def concentric_affine_linear(pts: NDArray, r_mm: NDArray) -> tuple[NDArray, NDArray] | None:
    """Concentric ellipses ``(p - o)^T M (p - o) = r^2`` through ``pts`` ``(N, 2)`` named
    ``r_mm`` ``(N,)``, linear in ``M``, ``M o`` and a free constant: ``M`` ``(2, 2)`` and
    ``o`` ``(2,)`` in the points' frame, or None where ``M`` is no ellipse's."""
    x, y = pts.T
    a = np.column_stack([x * x, 2 * x * y, y * y, -2 * x, -2 * y, np.ones_like(x)])
    norm = np.linalg.norm(a, axis=0)
    if np.any(norm == 0) or not np.all(np.isfinite(a)):
        return None
    lin = np.linalg.lstsq(a / norm, r_mm * r_mm, rcond=None)[0] / norm
    m = np.array([[lin[0], lin[1]], [lin[1], lin[2]]])
    if np.linalg.det(m) <= 0 or m[0, 0] <= 0:
        return None
    return m, np.linalg.solve(m, lin[3:5])


def concentric_affine_conics(
    points_px: dict[int, NDArray], radii: NDArray, centre_px: NDArray, tol_px: float
) -> tuple[dict[int, NDArray], NDArray] | None:
    """The ring conics of one joint fit: concentric ellipses of one shape, ``r_k`` to scale.

    Where each ring is seen over a short arc (a laser stripe over the centre hides the rest),
    its own conic is not pinned down, but together the rings are: a small target's image is
    nearly affine, and the affine image of concentric circles is the concentric ellipses
    ``(p - o)^T M (p - o) = r_k^2`` of one ``M`` and ``o`` (five parameters for all rings;
    started from the fit linear in ``M``, ``M o`` and a free constant, refined by least
    squares on the points' radial distances, px, with a robust loss). Over short arcs a
    labelling one ring off fits nearly as well, with ``o`` moved by most of a ring spacing:
    ``o`` must be where the points were found from.

    Parameters
    ----------
    points_px : dict of int to ndarray, shape (N_k, 2)
        Each ring's points, by ring index.
    radii : ndarray, shape (K,)
        The spec's ring radii, mm.
    centre_px : ndarray, shape (2,)
        Where the points were found from (the rays' origin): ``o`` must be within
        :func:`pencil_tolerance_px` of the ring spacing from it.
    tol_px : float
        The fit is refused where a ring's median distance from its ellipse, or the 90th
        percentile over all points, exceeds this.

    Returns
    -------
    tuple of (dict of int to ndarray, shape (3, 3); ndarray, shape (2,)), or None
        The conic of each ring in ``points_px`` with at least :data:`MIN_CONIC_POINTS` points
        (image coordinates) and their centre ``o``, px; or ``None``: fewer than two such
        rings, points not finite, no ellipse, a fit beyond ``tol_px`` or a centre away from
        ``centre_px``.

    Notes
    -----
    The model is affine: under a perspective whose vanishing line is near the target (a
    steep tilt, a near target) the rings' images are no longer one shape, and the fit is
    refused or its conics are off by a part of a ring spacing (about 0.15 of it at 12 deg
    tilt, 0.4-0.6 at 35-50 deg, for a 105 deg arc), which the fine stage's search may not
    reach. A homography's two more parameters would lift that.
    """
    keys = [k for k in sorted(points_px) if len(points_px[k]) >= MIN_CONIC_POINTS]
    if len(keys) < 2:
        return None
    pts = np.vstack([points_px[k] for k in keys]) - centre_px
    if not np.all(np.isfinite(pts)) or tol_px <= 0:
        return None
    r = np.concatenate([np.full(len(points_px[k]), radii[k]) for k in keys])
    linear = concentric_affine_linear(pts, r)
    if linear is None:
        return None
    m0, o0 = linear

    def radial_px(params: NDArray) -> NDArray:
        m = np.array([[params[0], params[1]], [params[1], params[2]]])
        d = pts - params[3:5]
        q = np.maximum(np.einsum("ni,ij,nj->n", d, m, d), 1e-12)
        # (sqrt(q) - r) mm along the ray from o, in px: times |d| / sqrt(q)
        return (1.0 - r / np.sqrt(q)) * np.linalg.norm(d, axis=1)

    x0 = np.array([m0[0, 0], m0[0, 1], m0[1, 1], *o0])
    fit = least_squares(radial_px, x0, loss="soft_l1", f_scale=0.5 * tol_px, x_scale="jac")
    m = np.array([[fit.x[0], fit.x[1]], [fit.x[1], fit.x[2]]])
    if not fit.success or np.linalg.det(m) <= 0 or m[0, 0] <= 0:
        return None
    o = centre_px + fit.x[3:5]
    mo = m @ o
    conics = {
        k: np.array(
            [
                [m[0, 0], m[0, 1], -mo[0]],
                [m[1, 0], m[1, 1], -mo[1]],
                [-mo[0], -mo[1], float(o @ mo) - radii[k] ** 2],
            ]
        )
        for k in keys
    }
    dist = np.abs(radial_px(fit.x))
    bounds = np.cumsum([0] + [len(points_px[k]) for k in keys])
    per_ring = [float(np.median(dist[bounds[i] : bounds[i + 1]])) for i in range(len(keys))]
    if max(per_ring) > tol_px or float(np.percentile(dist, 90)) > tol_px:
        return None
    if np.linalg.norm(o - centre_px) > pencil_tolerance_px(_min_spacing_px(conics, o)):
        return None
    return conics, o


def _unit_line(ln: NDArray) -> NDArray:
    return ln / np.linalg.norm(ln[:2])


def _perimeter_px(conic: NDArray, c: NDArray) -> float:
    angles = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    t = _conic_point_on_ray(conic, c, dirs)
    t = np.where(np.isfinite(t), t, np.nanmedian(t))
    return float(np.sum(t) * 2 * np.pi / 64)


def _min_spacing_px(conics: dict[int, NDArray], c: NDArray) -> float:
    angles = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    ts = {k: _conic_point_on_ray(cn, c, dirs) for k, cn in conics.items()}
    keys = sorted(ts)
    gaps = [np.nanmin((ts[b] - ts[a]) / (b - a)) for a, b in itertools.pairwise(keys)]
    gaps.append(float(np.nanmin(ts[keys[0]])) / (keys[0] + 1))
    return float(max(np.nanmin(gaps), 3.0))


def _nested_rings(conics: dict[int, NDArray], c: NDArray) -> dict[int, NDArray]:
    """The ring conics left when those crossing another are dropped, one at a time.

    The images of concentric circles are nested: along every ray from the image of O, ring
    ``j > i`` lies beyond ring ``i``. A coarse conic that crosses another was fitted to
    crossings of other rings or clutter; kept, it would set the smallest ring spacing
    (:func:`_min_spacing_px`) to its 3 px floor, and with it every window of the fine stage.
    The conic dropped first is the one whose crossings, summed over the others (how far the
    inner one reaches beyond the outer along 64 rays), go deepest; of two equal ones, the
    inner.

    Parameters
    ----------
    conics : dict of int to ndarray, shape (3, 3)
        Coarse conics by ring index.
    c : ndarray, shape (2,)
        Image of the centre O, px.

    Returns
    -------
    dict of int to ndarray, shape (3, 3)
        The conics that cross no other.
    """
    angles = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    ts = {k: _conic_point_on_ray(cn, c, dirs) for k, cn in conics.items()}
    keys = sorted(ts)
    while len(keys) > 1:
        depth = dict.fromkeys(keys, 0.0)
        for a, b in itertools.combinations(keys, 2):
            inside_out = ts[a] - ts[b]  # > 0 where the inner ring lies beyond the outer
            inside_out = inside_out[np.isfinite(inside_out)]
            over = max(float(np.max(inside_out)), 0.0) if inside_out.size else 0.0
            depth[a] += over
            depth[b] += over
        worst = max(keys, key=lambda k: depth[k])
        if depth[worst] <= 0:
            break
        keys.remove(worst)
    return {k: conics[k] for k in keys}


#: The 16 directions :func:`_ratio_tolerance` measures a ring's radius along.
_RATIO_ANGLES = np.linspace(0, 2 * np.pi, 16, endpoint=False)
_RATIO_DIRS = np.column_stack([np.cos(_RATIO_ANGLES), np.sin(_RATIO_ANGLES)])


def _ratio_tolerance(
    conic_i: NDArray, conic_j: NDArray, c: NDArray, expect: float, strict: bool
) -> float:
    """Relative tolerance on the pencil ratio of rings i < j (expected ``expect``).

    5 % for the lens and the fit, a little more for distant rings (up to a ratio of 4), and
    what a centre line ``sigma`` px off does to a ratio of squared radii: twice the relative
    error of each ring's radius in the image (``sigma`` 1 px for coarse ray crossings, 0.25 px
    for refined lines). A small inner ring's error counts as much as it weighs, not in
    proportion to the ratio, which would let a wrong inner ring pass against large outer ones.
    """
    sigma = 0.25 if strict else 1.0
    r_i = float(np.mean(_conic_point_on_ray(conic_i, c, _RATIO_DIRS)))
    r_j = float(np.mean(_conic_point_on_ray(conic_j, c, _RATIO_DIRS)))
    if not (np.isfinite(r_i) and np.isfinite(r_j)):
        return 0.0  # a conic that does not surround the centre: no ring of this pencil
    return 0.05 + 0.02 * min(expect, 4.0) + 2 * sigma * (1 / max(r_i, 1.0) + 1 / max(r_j, 1.0))


def _pencil_centre(
    conics: dict[int, NDArray], radii: NDArray, c0: NDArray, strict: bool = False
) -> NDArray | None:
    """Image of O from the pencil of ring conics; None if the radius ratios disagree.

    ``strict`` (sub-pixel conics): each pair's ratio must also be nearer its own
    ``(r_j / r_i)^2`` than to that of the pairs one ring in or out, so that rings labelled one
    off (evenly spaced rings give close ratios) are refused, not accepted.
    """
    keys = sorted(conics)
    centres, bad = [], 0
    for a in range(len(keys)):
        for b in range(a + 1, len(keys)):
            i, j = keys[a], keys[b]
            try:
                ctr, ratio = pencil_center(conics[i], conics[j])
            except np.linalg.LinAlgError:
                bad += 1
                continue
            expect = (radii[j] / radii[i]) ** 2
            tol = _ratio_tolerance(conics[i], conics[j], ctr[:2], expect, strict)
            if strict:
                for sh in (-1, 1):
                    if 0 <= i + sh < len(radii) and 0 <= j + sh < len(radii):
                        alt = (radii[j + sh] / radii[i + sh]) ** 2
                        tol = min(tol, 0.4 * abs(alt / expect - 1))
            if not np.isfinite(ratio) or abs(ratio / expect - 1) > tol:
                bad += 1
                continue
            centres.append(ctr[:2])
    if not centres or bad > len(centres):
        return None
    centres_a = np.asarray(centres)
    med = np.median(centres_a, axis=0)
    if np.linalg.norm(med - c0) > 50 + 0.1 * np.linalg.norm(c0):
        return None
    return med


def _refine_ring(
    spline: SplineWindow,
    conic: NDArray,
    c: NDArray,
    dirs: NDArray,
    angles: NDArray,
    axis_lines: list[NDArray],
    half_window: float,
    spacing_px: float,
    s: ConcentricDetectorSettings,
    size: tuple[int, int],
    bright: NDArray | None = None,
) -> tuple[NDArray, NDArray, NDArray] | None:
    """Sub-pixel centre-line points of one ring and its refitted conic."""
    w, h = size
    t = _conic_point_on_ray(conic, c, dirs)
    ok = np.isfinite(t)
    pts = c + t[ok, None] * dirs[ok]
    # Away from the image border and from the diameter lines.
    margin = half_window + 3
    inside = (
        (pts[:, 0] > margin)
        & (pts[:, 0] < w - 1 - margin)
        & (pts[:, 1] > margin)
        & (pts[:, 1] < h - 1 - margin)
    )
    clear = np.ones(len(pts), bool)
    for ln in axis_lines:
        dist = np.abs(pts @ ln[:2] + ln[2])
        clear &= dist > 1.5 * half_window + 2
    pts = pts[inside & clear]
    if len(pts) < 16:
        return None
    normals = _conic_normals(conic, pts)
    search = max(1.0, min(0.3 * spacing_px, 3.0 * half_window))
    off, contrast, good = _locate_centres(
        spline, pts, normals, half_window, search, s.ray_step_px, bright
    )
    med = np.median(contrast[good]) if good.any() else 0.0
    good &= contrast > 0.5 * med
    found = pts + off[:, None] * normals
    found = found[good]
    if len(found) < max(16, s.min_arc_fraction * len(dirs) * 0.5):
        return None
    conic_new = fit_conic(found)
    for _ in range(3):
        dist = sampson_distances(conic_new, found)
        sig = 1.4826 * np.median(np.abs(dist)) + 1e-3
        keep = np.abs(dist) < max(4 * sig, 0.05)
        if keep.all():
            break
        found = found[keep]
        if len(found) < 16:
            return None
        conic_new = fit_conic(found)
    dist = sampson_distances(conic_new, found)
    rms = float(np.sqrt(np.mean(dist**2)))
    # The scatter from one point to the next around the ring is the line's own noise; a
    # conic through a neighbour's points or bent by clutter leaves smooth residuals instead.
    order = np.argsort(np.arctan2(found[:, 1] - c[1], found[:, 0] - c[0]))
    noise = 1.4826 * float(np.median(np.abs(np.diff(dist[order])))) / np.sqrt(2.0)
    limit = max(s.max_conic_rms_px, s.max_conic_rms_fraction * spacing_px, 1.5 * noise)
    if rms > limit or not _ellipse_ok(conic_new, c):
        return None
    return found, conic_new, np.array([rms])


def _pair_agrees(conics: dict[int, NDArray], radii: NDArray, i: int, j: int) -> bool:
    """Whether rings i < j have the pencil ratio of the spec (strictly, see _pencil_centre)."""
    try:
        ctr, ratio = pencil_center(conics[i], conics[j])
    except np.linalg.LinAlgError:
        return False
    expect = (radii[j] / radii[i]) ** 2
    tol = _ratio_tolerance(conics[i], conics[j], ctr[:2], expect, strict=True)
    for sh in (-1, 1):
        if 0 <= i + sh < len(radii) and 0 <= j + sh < len(radii):
            tol = min(tol, 0.4 * abs((radii[j + sh] / radii[i + sh]) ** 2 / expect - 1))
    return bool(np.isfinite(ratio) and abs(ratio / expect - 1) <= tol)


def _relabel_by_ratios(conics: dict[int, NDArray], radii: NDArray) -> dict[int, NDArray]:
    """The coarse conics renamed to the spec's rings their sizes fit, when the rays' labels
    are off (a ring missed or an extra dark curve counted shifts every label after it).

    Each conic's radius relative to a reference conic comes from the pencil (concentric
    conics keep their circles' radius ratios); the reference is tried as every spec ring and
    the assignment that puts the most conics near a spec radius (within a third of the local
    ring spacing, one conic per ring, best fits first) wins, with each conic tried as the
    reference. Conics that fit no ring are dropped. Returns an
    empty dict when no assignment fits at least two conics.
    """
    keys = sorted(conics)
    if len(keys) < 2:
        return {}
    gaps = np.diff(radii)
    # Half-gap to the nearer neighbour of each spec ring: a conic closer than a third of it
    # names that ring.
    near_gap = np.minimum(np.r_[gaps[:1], gaps], np.r_[gaps, gaps[-1:]])
    best: tuple[int, float, dict[int, int]] = (0, np.inf, {})
    for ref in keys:  # a spurious largest conic (the card's edge) must not decide
        rel = {ref: 1.0}
        for k in keys:
            if k == ref:
                continue
            try:
                _, ratio = pencil_center(conics[k], conics[ref])
            except np.linalg.LinAlgError:
                continue
            if np.isfinite(ratio) and ratio > 0:
                rel[k] = float(np.sqrt(ratio))  # r_ref / r_k
        for m in range(len(radii)):
            r = {k: radii[m] / q for k, q in rel.items()}
            nearest = {k: int(np.argmin(np.abs(radii - rk))) for k, rk in r.items()}
            err = {k: abs(radii[n] - r[k]) / near_gap[n] for k, n in nearest.items()}
            assigned: dict[int, int] = {}
            error = 0.0
            for k in sorted(err, key=err.get):  # best fits first, one conic per ring
                if err[k] < 1 / 3 and nearest[k] not in assigned.values():
                    assigned[k] = nearest[k]
                    error += err[k]
            if len(assigned) > best[0] or (len(assigned) == best[0] and error < best[1]):
                best = (len(assigned), error, assigned)
    if best[0] < 2:
        return {}
    return {n: conics[k] for k, n in sorted(best[2].items(), key=lambda kv: kv[1])}


def _consistent_rings(conics: dict[int, NDArray], radii: NDArray) -> list[int]:
    """Rings whose conic agrees with most of the others as a member of the spec's pencil."""
    keys = sorted(conics)
    agrees = {(i, j): _pair_agrees(conics, radii, i, j) for i, j in itertools.combinations(keys, 2)}
    keep = []
    for i in keys:
        votes = [agrees[min(i, j), max(i, j)] for j in keys if j != i]
        if votes and sum(votes) > 0.5 * len(votes):
            keep.append(i)
    return keep


def pencil_tolerance_px(spacing_px: float) -> float:
    """How far a ring's point may be from where the other rings' pencil puts it, px (beside
    the ring's own offset from it): well below a ring spacing, above the lens's share."""
    return max(1.5, 0.25 * spacing_px)


def _pencil_predictions(conics: dict[int, NDArray], radii: NDArray, k: int) -> list[NDArray]:
    """Ring ``k``'s conic as the pencil of each pair of the four rings nearest it predicts
    it (:func:`pencil_member`); empty with fewer than two other rings."""
    others = sorted((i for i in conics if i != k), key=lambda i: abs(radii[i] - radii[k]))[:4]
    predicted = []
    for i, j in itertools.combinations(others, 2):
        try:
            member = pencil_member(conics[i], radii[i], conics[j], radii[j], radii[k])
        except np.linalg.LinAlgError:
            continue
        if np.all(np.isfinite(member)):
            predicted.append(member)
    return predicted


def _pencil_offsets(predicted: list[NDArray], points_px: NDArray) -> NDArray:
    """Signed Sampson distance of ``(M, 2)`` points to the predicted conics, the median over
    them (one wrong ring among the pairs does not decide), px."""
    return np.median([sampson_distances(m, points_px) for m in predicted], axis=0)


def _prune_by_pencil(
    rings: dict[int, tuple[NDArray, NDArray, NDArray]],
    radii: NDArray,
    c: NDArray,
    spacing_px: float,
) -> dict[int, tuple[NDArray, NDArray, NDArray]]:
    """Each ring's points kept only where the other rings' pencil puts that ring.

    A ring whose points follow something else over part of its length (a stripe's halo
    where the ring is hidden, a neighbour's blur) gives a conic whose radius ratio may still
    agree with the others while its curve is pixels off there, and a point named on it
    would be wrong. The other rings predict this one (:func:`pencil_member`, from the pairs
    of the nearest four, the median per point); points whose Sampson distance to the
    prediction differs from the ring's median by more than :func:`pencil_tolerance_px` (or
    4 sigma of that difference) are dropped and the conic refitted. A ring left with fewer than 16 points, or
    whose refitted conic no longer surrounds ``c``, is dropped.

    Parameters
    ----------
    rings : dict
        Ring index -> (points ``(M, 2)`` px, conic ``(3, 3)``, ``[rms]``).
    radii : ndarray, shape (K,)
        The spec's radii, mm.
    c : ndarray, shape (2,)
        The image of O.
    spacing_px : float
        The smallest ring spacing in the image.

    Returns
    -------
    dict
        The same form; unchanged where fewer than three rings are given.
    """
    keys = sorted(rings)
    if len(keys) < 3:
        return rings
    conics = {k: v[1] for k, v in rings.items()}
    out = {}
    for k in keys:
        pts = rings[k][0]
        predicted = _pencil_predictions(conics, radii, k)
        if not predicted:
            out[k] = rings[k]
            continue
        off = _pencil_offsets(predicted, pts)
        off = off - np.median(off)
        sigma = 1.4826 * float(np.median(np.abs(off)))
        keep = np.abs(off) < max(pencil_tolerance_px(spacing_px), 4.0 * sigma)
        if keep.all():
            out[k] = rings[k]
            continue
        if np.count_nonzero(keep) < 16:
            continue
        pts = pts[keep]
        conic = fit_conic(pts)
        if not _ellipse_ok(conic, c):
            continue
        rms = np.array([float(np.sqrt(np.mean(sampson_distances(conic, pts) ** 2)))])
        out[k] = (pts, conic, rms)
    return out
