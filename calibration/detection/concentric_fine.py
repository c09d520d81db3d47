"""Concentric-circles detector, the fine stage: the target measured to sub-pixel and labelled.

Steps 5 and 6 of :mod:`calibration.detection.concentric`, from the coarse stage's ring conics
and centre: every ring measured along its normals and refitted, the pencil's centre again,
the rings checked against the radii along the rays from O (:func:`ray_departure`), the two
diameters located between the rings and checked to be conjugate with respect to them, the
tilt and the diameters' crossing checked, the orientation marker read
(:mod:`calibration.detection.concentric_labels`) and the points named. Where the windows were
sized by a ring the first refinement dropped, the rings it kept are measured again with
windows of their own spacing, and that measurement is taken where the two disagree
(:data:`RESIZE_SPACING`, :data:`RESIZED_AGREE_PX`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np
from numpy.typing import NDArray

from calibration.detection.concentric_axes import (
    Refit,
    _diameter_lines,
    _line_evidence,
    _lines_angle_deg,
    _refine_axes,
    _settled_axes,
    conjugacy_deg,
    conjugate_diameter,
)
from calibration.detection.concentric_labels import (
    _combine_centre,
    _label_by_marker,
    _named_points,
    label_up_to_symmetry,
)
from calibration.detection.concentric_missing import RingRecovery, recovered_rings
from calibration.detection.concentric_rays import (
    BrightMasks,
    _coarse_darkness,
    _darkness,
    _sample,
)
from calibration.detection.concentric_rings import (
    ConcentricDetectorSettings,
    _conic_axes_ratio,
    _conic_point_on_ray,
    _consistent_rings,
    _min_spacing_px,
    _pencil_centre,
    _perimeter_px,
    _prune_by_pencil,
    _refine_ring,
    _unit_line,
    spline_window,
)
from calibration.detection.conics import (
    circle_tilt_deg,
    harmonic_conjugate,
    intersect_lines,
    line_conic_intersections,
)
from calibration.detection.observations import AxisObservation, RingObservation, TargetObservation
from scanner.core.targets import ConcentricCirclesTarget

KIND = "concentric_circles"

#: Largest angle between a diameter's image and the other's conjugate with respect to the
#: rings (:func:`~calibration.detection.concentric_axes.conjugacy_deg`) for two lines to be
#: the target's diameters. Over 1421 rightly labelled views of the randomised benchmark
#: (seeds 0-11) the true pairs stay within 1.7 deg (median 0.012 deg), the modern cell's
#: lens (k1 = -0.12) within 0.12 deg; a clutter line through O once taken for a diameter
#: was 44 deg off.
MAX_CONJUGACY_DEG = 5.0

#: Least evidence of print (:func:`~calibration.detection.concentric_axes._line_evidence`),
#: as a share of the rings' darkness, of a diameter that replaces a line through O that was
#: not the printed one's conjugate (:func:`_conjugate_of_printed`); 0.3 for diameters the
#: scan found. Such replacements on the randomised benchmark's views showed 1.10-1.43 times
#: the rings' darkness where right, 0.69 where a wrong ring pencil put the conjugate 3 deg
#: off the print (a view of contrast over noise 2.5, below the domain's 3).
MIN_CONJUGATE_EVIDENCE = 0.8

#: Rings flatter than the cosine of this much less than the detector's tilt limit have the
#: tilt read off them (:func:`~calibration.detection.conics.circle_tilt_deg`), which alone
#: then decides: off the image's centre the image plane's obliquity makes a steep target's
#: rings flatter or rounder by up to the cosine of the ray's angle (0.87 at 30 deg, a lens of
#: 0.9 widths' focal length in a corner), and a target 70 deg off there looks 0.40 flat, as
#: one 66 deg off on the axis. Nearer frontal the circular points run off to infinity and
#: the focal length they give, and so the tilt, is ill-determined: the flatness decides.
TILT_READ_MARGIN_DEG = 15.0


#: Largest departure of a ring's crossing with a ray from O from where the spec's radii put
#: it along that ray (:func:`ray_departure`), in ring gaps, for the measured rings to be
#: the spec's. Over 1777 rightly labelled views of the randomised benchmark (seeds 0-13)
#: the median was 0.003 and 99 % were within 0.053; of the three beyond 0.15, two held a
#: ring whose conic was off where it was not seen (1.23: cut by the image's corner; 0.32:
#: the innermost, seen over a short arc, naming a point 2.1 px off), one a noisy ring
#: (0.17). The modern cell's lens (k1 = -0.12) gave at most 0.017. Rings whose coarse
#: conics were a ring off over a sector (a faint, blurred view with a stripe), refined into
#: mixtures of two neighbours' lines, gave 0.21.
MAX_RAY_DEPARTURE = 0.15

#: How well the rings left must agree along the rays (:data:`MAX_RAY_DEPARTURE`) when one
#: ring is dropped for breaking it: as well as 99 % of right views do. Without the ring cut
#: by the corner above the rest give 0.01; rings mixed together leave no subset agreeing so
#: well (0.12 without the best one to drop).
AGREED_RAY_DEPARTURE = 0.05

#: Rings :func:`_rings_along_rays` may drop for breaking the radii's projectivity. Two: a
#: laser stripe tangent to the innermost ring (randomised view 21:50, 13 rings, the stripe
#: 47 px from O) pulls both it and the next one off their lines where it runs along them;
#: without the first the rest depart by 0.055 ring gaps, without both by 0.018.
MAX_DROPPED_RINGS = 2

#: The fine stage's windows and search are sized by the smallest ring spacing of the coarse
#: conics (:func:`~calibration.detection.concentric_rings._min_spacing_px`). Where the rings
#: the first refinement keeps are spaced more than this many times wider, a ring it dropped
#: had sized them, and a search that narrow may only confirm coarse conics that are off the
#: print (randomised view 21:118: an outer ring cut by the image's border, its coarse conic
#: within 3 px of the next one's; a 1 px search kept coarse conics 6 px off, a wrong
#: labelling). The kept rings are refined again with windows of their own spacing; where
#: one moves by more than :data:`RESIZED_AGREE_PX`, they are measured again, from their
#: coarse conics, with maps and windows of their scale.
RESIZE_SPACING = 1.5

#: How far (px, along the rays from O) a kept ring may move when refined with windows of the
#: kept rings' spacing (:data:`RESIZE_SPACING`) and the measurement stand; and where it is
#: measured again, how far the two measurements' rings may be apart for the first to stand
#: still. On the randomised benchmark's seeds 0-21, 56 views had the two measurements
#: differ: 11 moved by more when refined again, and of their measurements again 3 were 1.35,
#: 7.2 and 26 px apart from the first, which was 0.74-6.0 px off the truth at its worst
#: point, and were taken. On the other 53 (up to 0.91 px apart) the narrow windows' worst
#: point was the nearer to the truth on 42, and it is what the detector measured before.
RESIZED_AGREE_PX = 1.0


def ray_departure(
    conics: dict[int, NDArray], radii: NDArray, c: NDArray, n_rays: int = 64
) -> NDArray:
    """How far the rings' crossings with rays from O are from the projectivity of the radii.

    Along a ray from the image of O, the image of the circle of radius ``r`` lies at
    ``t = a r / (1 + b r)`` (the target's line through O maps to the ray by a projectivity
    fixing O), the same ``a`` and ``b`` for every ring. Each ray's crossings are fitted so
    (linear least squares in ``a`` and ``b``); the departure is the largest residual over
    the local gap between rings, ``(dt/dr) * min(diff(radii))``. A ring whose points
    follow its neighbour's line over part of its length breaks this on the rays there,
    though its conic's ratios agree with the others.

    Parameters
    ----------
    conics : dict of int to ndarray, shape (3, 3)
        Ring conics by ring index.
    radii : ndarray, shape (K,)
        The spec's radii, mm.
    c : ndarray, shape (2,)
        The image of O (px): the pencil's centre, not a coarse guess (rays from a point ``d``
        px beside O depart by about ``0.4 d`` over the smallest gap).
    n_rays : int
        Rays, evenly spread over the turn.

    Returns
    -------
    ndarray, shape (n_rays,)
        The departure per ray in ring gaps; NaN where fewer than three rings cross the ray.
    """
    angles = np.linspace(0, 2 * np.pi, n_rays, endpoint=False)
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    keys = sorted(conics)
    r = np.asarray(radii, dtype=np.float64)[keys][:, None]  # (K, 1)
    t = np.array([_conic_point_on_ray(conics[k], c, dirs) for k in keys])  # (K, n)
    seen = np.isfinite(t)
    t0 = np.where(seen, t, 0.0)
    w = seen.astype(np.float64)
    # Normal equations of t = a r - b r t, per ray (column)
    a11 = np.sum(w * r * r, axis=0)
    a12 = -np.sum(w * r * r * t0, axis=0)
    a22 = np.sum(w * (r * t0) ** 2, axis=0)
    y1 = np.sum(w * r * t0, axis=0)
    y2 = -np.sum(w * r * t0 * t0, axis=0)
    det = a11 * a22 - a12 * a12
    out = np.full(n_rays, np.nan)
    ok = (seen.sum(axis=0) >= 3) & (np.abs(det) > 0)
    if not ok.any():
        return out
    a = (a22 * y1 - a12 * y2)[ok] / det[ok]
    b = (a11 * y2 - a12 * y1)[ok] / det[ok]
    fit = a * r / (1.0 + b * r)
    gap = a / (1.0 + b * r) ** 2 * float(np.min(np.diff(radii)))
    resid = np.where(seen[:, ok], np.abs(t0[:, ok] - fit) / np.abs(gap), 0.0)
    out[ok] = resid.max(axis=0)
    return out


def _worst_departure(conics: dict[int, NDArray], radii: NDArray, c: NDArray) -> float:
    # Rays with fewer than three crossings say nothing (NaN); the rings reaching here are
    # ellipses around c that passed the pencil's checks, so most rays cross them all.
    departure = ray_departure(conics, radii, c)
    return float(np.nanmax(departure)) if np.isfinite(departure).any() else 0.0


def _rings_along_rays(
    rings: dict[int, tuple[NDArray, NDArray, NDArray]],
    radii: NDArray,
    c: NDArray,
    min_rings: int,
    max_departure: float = MAX_RAY_DEPARTURE,
) -> dict[int, tuple[NDArray, NDArray, NDArray]] | str:
    """The measured rings, less one or two that break the radii's projectivity along the rays
    from O (:func:`ray_departure`, beyond ``max_departure``), or why not.

    The ring dropped is the one without which the rest agree best, and only if they then
    agree as right views do (:data:`AGREED_RAY_DEPARTURE`); where no single ring does, the
    pair so (every pair tried: with two rings off, the worst ring alone may not be the one
    whose loss helps most). At least three and ``min_rings`` are left, one more where a pair
    is dropped: rings mixed with their neighbours over a sector (all of them a ring off
    there) refuse the view.
    """
    conics = {k: v[1] for k, v in rings.items()}
    worst = _worst_departure(conics, radii, c)
    if worst <= max_departure:
        return rings
    for n_dropped in range(1, MAX_DROPPED_RINGS + 1):
        # (a pair dropped from five would leave three rings, which check each other on one
        # residual a ray: a mixture's three agree so (13:89, rings 1.5 px off O))
        if len(conics) - n_dropped < max(3, min_rings) + n_dropped - 1:
            break
        without = {
            dropped: _worst_departure(
                {k: cn for k, cn in conics.items() if k not in dropped}, radii, c
            )
            for dropped in itertools.combinations(conics, n_dropped)
        }
        best = min(without, key=lambda d: without[d])
        if without[best] <= AGREED_RAY_DEPARTURE:
            return {k: v for k, v in rings.items() if k not in best}
    return (
        f"rings not the spec's along the rays from O: a crossing {worst:.2f} ring gaps from "
        "where the radii put it (rings on their neighbours' lines)"
    )


def _conjugate_of_printed(
    axis_lines: list[NDArray],
    c: NDArray,
    conics: dict[int, NDArray],
    refit: Refit,
    d: NDArray,
    rings: dict[int, tuple[NDArray, NDArray, NDArray]],
    offset_px: float,
    bright: NDArray,
) -> tuple[list[NDArray], list[NDArray], int | None] | str:
    """Diameters that are conjugate with respect to the rings, from two that are not.

    The line with more evidence of print (:func:`_line_evidence`) stays; the other gives way
    to its conjugate (:func:`conjugate_diameter`), and both are settled again
    (:func:`_settled_axes` with ``refit``); where the conjugate's refit turns off it by more
    than :data:`MAX_CONJUGACY_DEG`, the conjugate is held as it is. The conjugate must show
    the print as plainly as the rings (:data:`MIN_CONJUGATE_EVIDENCE`). Returns the settled
    lines, their points and the hidden (or held) one's index, or why not.
    """
    outer = conics[max(conics)]
    ring_pts = np.vstack([r[0] for r in rings.values()])
    ring_dark = float(np.median(_sample(d, ring_pts[:, 0], ring_pts[:, 1])))
    evidence = []
    for ln in axis_lines:
        ends = line_conic_intersections(ln, outer)
        ok = len(ends) == 2
        evidence.append(
            _line_evidence(d, ln, c, ends, offset_px, ring_dark, bright) if ok else -np.inf
        )
    keep = int(np.argmax(evidence))
    lines = list(axis_lines)
    lines[1 - keep] = conjugate_diameter(lines[keep], c, conics)
    settled = _settled_axes(refit, lines, c, conics)
    off = conjugacy_deg(axis_lines, c, conics)
    if settled is None:
        return (
            f"diameter lines not conjugate with respect to the rings ({off:.1f} deg off), "
            "and the printed one's conjugate not measurable: not the target's diameters"
        )
    if settled[2] is None and conjugacy_deg(settled[0], c, conics) > MAX_CONJUGACY_DEG:
        # The conjugate's refit turned off it: something dark beside it pulls its centroids
        # (randomised view 27:66: a stripe through O 13 deg from a diameter, thick rings 17 px
        # apart leaving one sample a gap, ring 0 near O). The conjugate itself is held, then
        # judged by its print like any replaced line.
        held = _settled_axes(refit, lines, c, conics, 1 - keep)
        if held is None or held[2] != 1 - keep:
            return (
                f"diameter lines not conjugate with respect to the rings ({off:.1f} deg off, "
                f"{conjugacy_deg(settled[0], c, conics):.1f} deg with the printed one's "
                "conjugate): not the target's diameters"
            )
        settled = held
    elif settled[2] == 1 - keep:  # (nothing to judge it by: not taken on the rings' word alone)
        return (
            f"diameter lines not conjugate with respect to the rings ({off:.1f} deg off), and "
            "the printed one's conjugate hidden under a stripe: not the target's diameters"
        )
    # A diameter put where the rings say it is, not found by the scan, must show the print
    # as plainly as the rings do (a wrong pencil's conjugate misses the printed line).
    new = settled[0][1 - keep]
    ends = line_conic_intersections(new, outer)
    ev = _line_evidence(d, new, c, ends, offset_px, ring_dark, bright) if len(ends) == 2 else 0.0
    if ev < MIN_CONJUGATE_EVIDENCE * ring_dark:
        return (
            f"diameter lines not conjugate with respect to the rings ({off:.1f} deg off), and "
            f"the printed one's conjugate not printed: darkness {ev:.2f} on it against "
            f"{ring_dark:.2f} on the rings"
        )
    return settled


def measure_and_label(
    img: NDArray,
    target: ConcentricCirclesTarget,
    s: ConcentricDetectorSettings,
    conics: dict[int, NDArray],
    c: NDArray,
    hough_pair: tuple[NDArray, NDArray],
    z_rays: NDArray,
    kernel: int,
    coarse_maps: tuple[NDArray, NDArray] | None,
    reached: Callable[[int], None],
    bright: BrightMasks,
    max_departure: float = MAX_RAY_DEPARTURE,
    recovery: RingRecovery | None = None,
) -> TargetObservation:
    """The target measured to sub-pixel, checked and labelled, from the coarse stage's pencil.

    Parameters
    ----------
    img : ndarray, shape (H, W)
        The grey image, float.
    target : ConcentricCirclesTarget
    s : ConcentricDetectorSettings
    conics : dict of int to ndarray, shape (3, 3)
        The coarse ring conics by ring index (at least ``s.min_rings``).
    c : ndarray, shape (2,)
        Their pencil's centre (px).
    hough_pair : tuple of two ndarray, shape (3,)
        The two lines whose crossing gave the candidate centre: the diameters' first guess
        where the angular scan finds neither.
    z_rays : ndarray, shape (H, W)
        The coarse stage's darkness over its threshold, -1 where the print is hidden.
    kernel : int
        The coarse stage's closing kernel (px).
    coarse_maps : tuple of two ndarray, shape (H, W), or None
        The coarse stage's darkness and background where this pass made them (they are not
        kept between passes): made again if the fine stage needs them.
    reached : callable
        Told each stage passed (4: rings and diameters measured, 5: tilt, 6: diameters'
        crossing and print), so the caller can show the most telling of several refusals.
    bright : BrightMasks
        The image's bright masks (laser stripe, glare), made once for every pass.
    max_departure : float
        How far the rings may depart from the radii along the rays from O, in ring gaps
        (:func:`ray_departure`): a last pass asks for :data:`AGREED_RAY_DEPARTURE`, as
        well as right views agree.
    recovery : RingRecovery, optional
        Whether rings the coarse stage missed are measured from two measured ones
        (:func:`~calibration.detection.concentric_missing.recovered_rings`), and where to
        note that a measurement stopped at two rings without it.

    Returns
    -------
    TargetObservation
        As :func:`~calibration.detection.concentric.detect_concentric`, or falsy with the
        reason.
    """
    args = (img, target, s)
    recovery = recovery or RingRecovery()
    later = (hough_pair, z_rays, kernel, coarse_maps, reached, bright, max_departure, recovery)
    wider = _WiderSpacing()
    first = _measure(*args, conics, c, *later, wider)
    if wider.conics is None:
        return first
    again = _measure(*args, wider.conics, c, *later, None)
    if not again:  # (nothing to check the first against: it stands, as before the check)
        return first
    if not first or _rings_apart_px(first, again) > RESIZED_AGREE_PX:
        return again
    return first


@dataclass
class _WiderSpacing:
    """Set by :func:`_measure`: the coarse conics of the rings its first refinement kept,
    where their spacing says its windows were too narrow (:data:`RESIZE_SPACING`)."""

    conics: dict[int, NDArray] | None = None


def _rings_apart_px(a: TargetObservation, b: TargetObservation) -> float:
    """How far the rings of two measurements of one view are apart along 64 rays from the
    first's O, px: the largest over the rings both kept (inf for none)."""
    theirs = {r.index: r.conic for r in b.rings}
    apart = [
        _conics_apart_px(r.conic, theirs[r.index], a.center_px)
        for r in a.rings
        if r.index in theirs
    ]
    return max(apart, default=np.inf)


def _conics_apart_px(a: NDArray, b: NDArray, c: NDArray) -> float:
    """How far two conics ``(3, 3)`` around ``c`` are apart along 64 rays from it, px."""
    angles = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    apart = np.abs(_conic_point_on_ray(a, c, dirs) - _conic_point_on_ray(b, c, dirs))
    return float(np.nanmax(apart)) if np.any(np.isfinite(apart)) else np.inf


def _line_and_window_px(line_frac: float, spacing_px: float) -> tuple[float, float]:
    """A printed line's width and the fine stage's half window, px, for rings
    ``spacing_px`` apart whose lines are ``line_frac`` of a gap wide: the window reaches the
    paper on both sides of a line but not the neighbouring rings."""
    line_px = line_frac * spacing_px
    return line_px, max(1.5, min(1.6 * line_px + 2.0, 0.45 * spacing_px), 0.5 * line_px + 1.0)


def _measure(
    img: NDArray,
    target: ConcentricCirclesTarget,
    s: ConcentricDetectorSettings,
    conics: dict[int, NDArray],
    c: NDArray,
    hough_pair: tuple[NDArray, NDArray],
    z_rays: NDArray,
    kernel: int,
    coarse_maps: tuple[NDArray, NDArray] | None,
    reached: Callable[[int], None],
    bright_masks: BrightMasks,
    max_departure: float,
    recovery: RingRecovery,
    wider: _WiderSpacing | None,
) -> TargetObservation:
    """:func:`measure_and_label` with the fine stage's windows sized by ``conics``; sets
    ``wider.conics`` where the rings its first refinement kept are spaced wider."""
    h, w = img.shape
    size = (int(w), int(h))
    radii = np.asarray(target.ring_radii_mm, dtype=np.float64)
    l1, l2 = hough_pair
    d, bg = coarse_maps if coarse_maps is not None else (None, None)
    # -- line width in px estimate, for windows
    coarse, coarse_c = conics, c
    spacing_px = _min_spacing_px(conics, c)
    line_frac = target.line_width_mm / float(np.min(np.diff(radii)))
    line_px, half_window = _line_and_window_px(line_frac, spacing_px)
    # Finer darkness map now that the scale is known (kernel several line widths, < spacing).
    kernel2 = int(np.clip(4 * half_window + 3, 9, max(9, 0.8 * spacing_px)))
    bright = bright_masks(kernel2)
    if kernel2 != kernel:
        d, bg, _ = _darkness(img, kernel2, bright > 0)
    elif d is None or bg is None:  # a later pass: the coarse maps again (not kept)
        d, bg, _, _ = _coarse_darkness(img, kernel, bright > 0)
    # The spline over the part the profiles reach: a ring point moves by up to a search
    # (3 half windows) when refined, and its profile spans a search and a window beyond it.
    spline = spline_window(d, list(conics.values()), c, 2 * (4 * half_window + 1) + 8)

    # -- sub-pixel rings
    axis_lines = [l1 / np.linalg.norm(l1[:2]), l2 / np.linalg.norm(l2[:2])]
    rings: dict[int, tuple[NDArray, NDArray, NDArray]] = {}
    scanned_at: NDArray | None = None
    hidden_axis: int | None = None  # a diameter under a laser stripe: see _diameter_lines
    for refinement in range(2):
        rings = {}
        n_rays = int(np.clip(_perimeter_px(conics[max(conics)], c) / 3.0, 180, 1440))
        angles = np.linspace(0, 2 * np.pi, n_rays, endpoint=False)
        dirs = np.column_stack([np.cos(angles), np.sin(angles)])
        refine = partial(
            _refine_ring,
            spline,
            c=c,
            dirs=dirs,
            angles=angles,
            axis_lines=axis_lines,
            half_window=half_window,
            spacing_px=spacing_px,
            s=s,
            size=(w, h),
            bright=bright,
        )
        for k in sorted(conics):
            res = refine(conics[k])
            if res is not None:
                rings[k] = res
        if refinement == 0 and 2 <= len(rings) < s.min_rings:
            if recovery.enabled:
                rings = recovered_rings(rings, radii, c, refine)
            else:
                recovery.wanted = True
        if len(rings) < s.min_rings:
            return TargetObservation.failed(
                f"no ring pencil found: {len(rings)} rings measured, expected >= {s.min_rings}",
                size,
                KIND,
            )
        # The refitted conics replace the coarse ones; the pencil gives the centre again.
        # A ring whose conic is not a member of the spec's pencil (noise, a neighbour's
        # points) is dropped rather than allowed to name wrong points.
        conics = {k: v[1] for k, v in rings.items()}
        keep = _consistent_rings(conics, radii)
        rings = _prune_by_pencil({k: rings[k] for k in keep}, radii, c, spacing_px)
        conics = {k: v[1] for k, v in rings.items()}
        if len(rings) < s.min_rings:
            return TargetObservation.failed(
                f"no ring pencil found: {len(rings)} ring conics agree with the spec's radius "
                f"ratios, expected >= {s.min_rings}",
                size,
                KIND,
            )
        if refinement == 0 and wider is not None and all(k in coarse for k in rings):
            # (rings named or measured from the pencil have no coarse conics to start from)
            kept = {k: coarse[k] for k in rings}
            kept_spacing_px = _min_spacing_px(kept, coarse_c)
            if kept_spacing_px > RESIZE_SPACING * spacing_px:
                # (checked on this measurement's maps first: the whole measurement again,
                # with maps of the kept rings' scale, only where the rings move)
                hw = _line_and_window_px(line_frac, kept_spacing_px)[1]
                moved = 0.0
                for k in rings:
                    res = _refine_ring(
                        spline,
                        coarse[k],
                        coarse_c,
                        dirs,
                        angles,
                        axis_lines,
                        hw,
                        kept_spacing_px,
                        s,
                        (w, h),
                        bright,
                    )
                    apart = np.inf if res is None else _conics_apart_px(conics[k], res[1], c)
                    moved = max(moved, apart)
                if moved > RESIZED_AGREE_PX:
                    wider.conics = kept
        c_new = _pencil_centre(conics, radii, c, strict=True)
        if c_new is None:
            return TargetObservation.failed(
                "no ring pencil found: refined ring conics disagree with the spec's radius ratios",
                size,
                KIND,
            )
        # Rings a ring off over a sector (their coarse conics were) agree with each other's
        # pencil there, but not with the radii along the rays from O. Judged on the second
        # refinement's conics: the first's, measured along the coarse conics' normals, are
        # rougher (right views up to 0.24 ring gaps off).
        along = (
            rings
            if refinement == 0
            else _rings_along_rays(rings, radii, c_new, s.min_rings, max_departure)
        )
        if isinstance(along, str):
            return TargetObservation.failed(along, size, KIND)
        if len(along) < len(rings):
            rings = along
            conics = {k: v[1] for k, v in rings.items()}
            c_new = _pencil_centre(conics, radii, c_new, strict=True)
            if c_new is None:
                return TargetObservation.failed(
                    "no ring pencil found: refined ring conics disagree with the spec's "
                    "radius ratios",
                    size,
                    KIND,
                )
        # The diameters through the refined centre (the coarse one may be pixels off, and a
        # line through it then misses a thin diameter; the Hough pair that gave it may hold
        # a stripe's edge), then refined from the rings' geometry.
        if scanned_at is None or np.linalg.norm(c_new - scanned_at) > 0.5:
            scanned = _diameter_lines(z_rays, c_new, conics, line_px, spacing_px)
            if scanned is not None:
                (axis_lines, hidden_axis), scanned_at = scanned, c_new
        c = c_new

        def refit(
            lines: list[NDArray],
            hidden: int | None,
            c: NDArray = c,
            conics: dict[int, NDArray] = conics,
        ) -> tuple[list[NDArray], list[NDArray]] | None:
            return _refine_axes(
                spline, lines, c, conics, radii, half_window, line_px, (w, h), bright, hidden
            )

        axis_res = _settled_axes(refit, axis_lines, c, conics, hidden_axis)
        if axis_res is None:
            return TargetObservation.failed(
                "diameter lines not measurable between the rings", size, KIND
            )
        if axis_res[2] is None and conjugacy_deg(axis_res[0], c, conics) > MAX_CONJUGACY_DEG:
            # Not the images of perpendicular diameters: where the angular scan saw neither
            # diameter (a steep target), the Hough pair may hold a clutter line through O.
            axis_res = _conjugate_of_printed(
                axis_res[0], c, conics, refit, d, rings, 2.0 * half_window + 2.0, bright
            )
            if isinstance(axis_res, str):
                return TargetObservation.failed(axis_res, size, KIND)
        axis_lines, axis_pts, hidden_axis = axis_res
        if _lines_angle_deg(*axis_lines) < 12.0:
            return TargetObservation.failed(
                "diameter lines not measurable: both converged on one line", size, KIND
            )
        # (A ring the coarse ray labelling missed is not recovered: only measured rings count.)

    reached(4)
    ratio = min(_conic_axes_ratio(cn) for cn in conics.values())
    limit = np.cos(np.radians(s.max_tilt_deg))
    tilt = None
    if ratio < np.cos(np.radians(s.max_tilt_deg - TILT_READ_MARGIN_DEG)):
        # Off the image's centre the image plane foreshortens the rings by the ray's own
        # obliquity too, flatter or rounder: judged by the tilt from the line of sight that
        # the outer ring gives (the principal point assumed at the image's centre).
        tilt = circle_tilt_deg(conics[max(conics)], c, ((w - 1) / 2, (h - 1) / 2))
    if (tilt is None and ratio < limit) or (tilt is not None and tilt[0] > s.max_tilt_deg):
        seen = "" if tilt is None else f", tilted {tilt[0]:.1f} deg from the line of sight"
        return TargetObservation.failed(
            f"too oblique: ring images flattened to {ratio:.2f}{seen}, expected "
            f"tilt <= {s.max_tilt_deg} deg (flattened to >= {limit:.2f})",
            size,
            KIND,
        )

    reached(5)
    # -- centre O: intersection of the diameter lines, checked against the pencil centre
    x = intersect_lines(axis_lines[0], axis_lines[1])
    o_lines = x[:2] / x[2]
    if np.linalg.norm(o_lines - c) > max(2.0, 0.05 * spacing_px):
        return TargetObservation.failed(
            f"diameter lines cross {np.linalg.norm(o_lines - c):.1f} px from the ring pencil's "
            "centre: not the target's diameters",
            size,
            KIND,
        )
    center = _combine_centre(o_lines, c, conics, axis_lines)

    # -- ends of each ring on both lines, in a consistent orientation
    kmax = max(conics)
    ends = []
    for ln in axis_lines:
        pts = line_conic_intersections(ln, conics[kmax])
        if len(pts) != 2:
            return TargetObservation.failed("diameter line misses the largest ring", size, KIND)
        ends.append(pts)
    ring_pts = np.vstack([r[0] for r in rings.values()])
    line_dark = float(np.median(_sample(d, ring_pts[:, 0], ring_pts[:, 1])))
    paper = float(np.median(_sample(bg, ring_pts[:, 0], ring_pts[:, 1])))
    # Both diameters must be printed lines, not any two lines through the centre.
    # (A diameter hidden under a stripe was found hidden, not dark: its conjugate is printed.)
    for index, (ln, ends_ln) in enumerate(zip(axis_lines, ends, strict=True)):
        if index == hidden_axis:
            continue
        ev = _line_evidence(d, ln, center, ends_ln, 2.0 * half_window + 2.0, line_dark, bright)
        if ev < 0.3 * line_dark:
            return TargetObservation.failed(
                f"diameter line not printed: darkness {ev:.2f} on it against "
                f"{line_dark:.2f} on the rings",
                size,
                KIND,
            )
    reached(6)
    labelled = _label_by_marker(
        img, bg, target, center, ends, conics, radii, axis_lines, line_dark, paper
    )
    labelling = "unique"
    if isinstance(labelled, str):
        if not labelled.startswith("orientation marker"):
            return TargetObservation.failed(labelled, size, KIND)
        # No marker to tell A: the view is still good for the intrinsics and the light
        # plane, labelled up to the target's four-fold symmetry (and says so).
        labelled = label_up_to_symmetry(center, ends, axis_lines)
        labelling = "symmetry"
    ix, sign_x, sign_y, marker_px = labelled
    xline, yline = _unit_line(axis_lines[ix]), _unit_line(axis_lines[1 - ix])
    axis_pts_xy = (axis_pts[ix], axis_pts[1 - ix])

    points_px, points_t, names, named = _named_points(
        center,
        conics,
        rings,
        radii,
        (xline, yline),
        (sign_x, sign_y),
        axis_pts_xy,
        spacing_px,
        size,
    )

    vps: dict[str, NDArray] = {}
    if all(n in named for n in "ABCD"):
        vps["p"] = harmonic_conjugate(named["A"], named["B"], center)
        vps["q"] = harmonic_conjugate(named["C"], named["D"], center)

    ring_obs = [
        RingObservation(
            radius_mm=float(radii[k]),
            edge_points_px=rings[k][0],
            conic=conics[k],
            index=int(k),
        )
        for k in sorted(rings)
    ]
    axes = [
        AxisObservation("x", axis_pts_xy[0], _unit_line(xline)),
        AxisObservation("y", axis_pts_xy[1], _unit_line(yline)),
    ]
    return TargetObservation(
        ok=True,
        reason="",
        image_size=size,
        kind=KIND,
        points_px=np.asarray(points_px, dtype=np.float64),
        points_target=np.asarray(points_t, dtype=np.float64),
        point_names=names,
        rings=ring_obs,
        axis_points=axes,
        center_px=center,
        named_px=named,
        vanishing_points=vps,
        marker_px=marker_px,
        labelling=labelling,
    )
