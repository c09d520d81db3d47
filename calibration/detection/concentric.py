"""Detection of the concentric-circles target in one grey image.

The pipeline, every geometric fact coming from the target spec:

1. *Darkness map*: ``D = 1 - I / background`` with the background from a grey closing, so
   uneven light, vignetting and a bright laser stripe do not look like printed lines.
2. *Candidate centres*: the long straight thin dark lines (Hough) are candidates for the two
   diameters; each crossing of two of them is a candidate image of O.
3. *Ring labelling along rays*: from a candidate centre, rays in every direction cross the
   images of the rings in order (each ring's image is a convex curve around the image of
   O). A ray's first crossings are accepted only when they obey the 1-D projectivity
   ``t = a r / (1 + b r)`` of the known radii, which labels the rings and rejects rays that
   a laser stripe, the diameter lines or clutter disturb. Lines too faint for single rays
   (at the threshold itself, in paper grain) are found by bundles of parallel rays.
4. *Pencil*: conics fitted to each ring; the image of O is the eigenvector of ``C_i^-1 C_j``
   with the non-repeated eigenvalue, which must equal ``(r_j / r_i)^2`` of the spec. Ring
   images are nested: a conic crossing another is dropped. Rings seen over arcs too short
   for conics of their own (a laser stripe over O) are fitted together, as concentric
   ellipses of one shape centred where the rays start.
5. *Sub-pixel*: for every ring, profiles along the conic's normals are sampled (bicubic) and
   the centre line of the printed line found as the fixed point of a symmetric-window
   centroid; the conic is refitted (algebraic, then Sampson distance) with outlier rejection.
   The diameter lines are located the same way between the rings; a diameter that a laser
   stripe hides (the paper's set-up puts the stripe on A-O-B) is the printed one's
   conjugate with respect to the ring conics (exact for concentric circles). The two
   diameters must be conjugate: a line through O that is not (clutter) gives way to the
   printed one's conjugate, which must then show the print.
6. *Labelling*: the orientation disc, looked for where each of the four candidate labellings
   puts it, must be dark at exactly one of them; A is that end, and C follows from z out of
   the face. Any doubt gives ``ok=False`` with a reason.

The less usual paths (rays from ring 1, the joint fit, bundles, a centre moved off the
crossings of the Hough lines, the crossings of weaker Hough lines) are later passes over the
closing scales, run only where the first refused the view, so that a view the first pass
measures is never exposed to their weaker checks.

Steps 1-3 are in :mod:`calibration.detection.concentric_rays` (the candidate centres in
:mod:`calibration.detection.concentric_centre`), 4-5 in
:mod:`calibration.detection.concentric_rings` (the diameters in
:mod:`calibration.detection.concentric_axes`) and 6 in
:mod:`calibration.detection.concentric_labels`; :func:`detect_concentric` here runs them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import cv2
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
from calibration.detection.concentric_centre import (
    HOUGH_LINES,
    WIDE_HOUGH_LINES,
    Z_LINE,
    _best_centre,
    _Centre,
    _climbed_centre,
)
from calibration.detection.concentric_labels import (
    _axis_dir,
    _combine_centre,
    _label_by_marker,
    _local_crossing,
    _locally_biased,
    label_up_to_symmetry,
)
from calibration.detection.concentric_rays import (
    _bright_mask,
    _darkness,
    _distinct_lines,
    _hough_lines,
    _label_rays,
    _sample,
    _threshold_map,
)
from calibration.detection.concentric_rings import (
    MIN_CONIC_POINTS,
    ConcentricDetectorSettings,
    _conic_axes_ratio,
    _conic_normals,
    _consistent_rings,
    _ellipse_ok,
    _min_spacing_px,
    _nested_rings,
    _pencil_centre,
    _pencil_offsets,
    _pencil_predictions,
    _perimeter_px,
    _prune_by_pencil,
    _refine_ring,
    _relabel_by_ratios,
    _unit_line,
    concentric_affine_conics,
    pencil_tolerance_px,
    spline_window,
)
from calibration.detection.conics import (
    fit_conic,
    harmonic_conjugate,
    intersect_lines,
    line_conic_intersections,
    sampson_distances,
)
from calibration.detection.observations import AxisObservation, RingObservation, TargetObservation
from calibration.detection.ray_kernels import FIT_TOL_PX
from scanner.core.images import to_gray_float
from scanner.core.targets import ConcentricCirclesTarget

__all__ = ["ConcentricDetectorSettings", "detect_concentric"]

log = logging.getLogger(__name__)

KIND = "concentric_circles"

#: The fourth and fifth passes sample the chosen centre's rays as bundles of five parallel rays
#: this far apart (px), each sample their mean but for the darkest and the lightest
#: (:func:`~calibration.detection.ray_kernels.label_rays`): a line too faint for one ray's
#: samples (grain, a thin print) adds up along its ring.
BUNDLE_STEP_PX = 2.0

#: The fifth pass's threshold on a bundle's samples. The trimmed mean of five samples 2 px
#: apart on a map blurred by 1 px, in paper grain correlated over a few px, has some 0.5-0.7
#: times a single sample's noise; ``z`` is the darkness over its paper level plus 6 MAD, so
#: the same false-crossing rate sits at about 0.65-0.8 of ``Z_LINE``. Chosen on the
#: randomised benchmark's refused views: at 0.5 one of the views 0.7 detects is lost.
BUNDLE_Z_LINE = 0.7

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


@dataclass(frozen=True)
class _CoarseMaps:
    """What the coarse stage's rays need at one closing scale: kept for the later passes (the
    darkness and background, needed only by a fine stage at this scale, are not kept: a
    float64 map of a 12 MP image is 100 MB)."""

    z_rays: NDArray
    """``(H, W)`` float64: darkness over its local threshold; -1 where the print is hidden
    (stripe, glare)."""
    lines: list[tuple[float, float]]
    """The :data:`HOUGH_LINES` strongest distinct long lines of ``z_rays > Z_LINE`` (Hough
    ``(rho, theta)``), strongest first."""
    hough: NDArray
    """``(N, 2)``: every Hough line, strongest first, for the last pass's weaker distinct
    lines (sorting them out costs about half the Hough transform's time: only that pass
    pays it)."""


@dataclass
class _ScaleState:
    """What one closing scale of :func:`detect_concentric` tells the next, and each pass over
    the scales the later ones."""

    progress: int = 0
    """Stages the scale passed (lines, centre, coarse pencil, rings measured, tilt,
    diameters): of several refusals the most telling is shown."""
    floor: float | None = None
    """The darkness threshold's floor (:func:`_threshold_map`), set by the first scale."""
    ring0_hidden: bool = False
    """Rays may start at ring 1 (:func:`~calibration.detection.ray_kernels.label_rays`): the
    second pass, for views every scale refused."""
    joint: bool = False
    """Rings seen over arcs too short for conics of their own may be fitted together
    (:func:`~calibration.detection.concentric_rings.concentric_affine_conics`): the third
    pass, for views both others refused."""
    bundle_z_line: float = 0.0
    """If > 0, the chosen centre's rays are sampled as bundles of parallel rays
    (:data:`BUNDLE_STEP_PX`) with this threshold: the fourth and fifth passes, for views the
    first three refused."""
    climb: bool = False
    """The chosen candidate centre is moved to where its rays find the most ring crossings
    (:func:`_climbed_centre`): the sixth pass, for views the first five refused."""
    wide: bool = False
    """The candidates are the crossings of the Hough lines after the first
    :data:`HOUGH_LINES` (up to :data:`WIDE_HOUGH_LINES`): the last pass, for views all others
    refused."""
    centres: dict[tuple[int, bool, bool, bool], _Centre | None] = field(default_factory=dict)
    """The candidate centre each scale (closing kernel, px; rays from ring 1 or not; climbed
    or not; from the wide lines or not) chose, None for none: the same in every pass that
    labels the candidates' rays alike."""
    coarse: dict[int, _CoarseMaps] = field(default_factory=dict)
    """The coarse maps of each scale (closing kernel, px) the first pass made: the later
    passes label other rays on the same maps."""


def detect_concentric(
    image: NDArray,
    target: ConcentricCirclesTarget,
    settings: ConcentricDetectorSettings | None = None,
) -> TargetObservation:
    """Find, label and measure the concentric-circles target in one grey image.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        8/16-bit or float grey image (colour is reduced to grey).
    target : ConcentricCirclesTarget
        The spec: ring diameters, line width, orientation marker.
    settings : ConcentricDetectorSettings, optional

    Returns
    -------
    TargetObservation
        With rings (sub-pixel centre-line points and conics), both diameter lines, O, A-D,
        the vanishing points p, q, the marker, and the exact correspondences
        O, (+-r, 0, 0), (0, +-r, 0) per ring; or falsy with the reason.
    """
    s = settings or ConcentricDetectorSettings()
    img = to_gray_float(image)
    h, w = img.shape
    size = (int(w), int(h))
    if min(h, w) < 32:
        return TargetObservation.failed(f"image too small ({w}x{h})", size, KIND)
    # The coarse darkness map's closing must be wider than a printed line but narrower than
    # the paper between two rings, and the target's scale in the image is not known yet: a
    # kernel for a target filling a good part of the frame first, then smaller ones (a small
    # or far target, closely spaced rings) when that finds no target.
    first = max(9, min(h, w) // 40)
    kernels = sorted({first, max(5, first // 2), max(5, first // 4)}, reverse=True)
    refused, furthest = None, -1
    state = _ScaleState()
    # On a small, steep target the innermost ring's image can merge with the diameters'
    # crossing at O, and every ray then names ring 1 as ring 0. Rays starting at ring 1 are
    # a second pass only: a ray's three crossings check such a labelling weakly, so a view
    # the first pass measures is never exposed to it. A laser stripe over O may leave each
    # ring seen over an arc too short for its own conic: a third pass fits them together
    # (on an affine model, which a finer scale's own conics beat where they are there).
    # Crossings a single ray misses (a faint line in paper grain) may show in the mean of
    # a bundle of parallel rays: a fourth pass at the usual threshold, a fifth at one for the
    # bundle's lower noise (BUNDLE_Z_LINE). Late, because a bundle blurs a steep target's
    # close rings: with bundles in the first pass, two views it measures were lost. On a
    # steep target the diameter along the short axis may be too short for a Hough line of
    # its own, and no crossing of two lines is at O: the sixth pass climbs from the chosen
    # crossing to where the rays find the most rings. Long clutter edges may outrank a small
    # target's diameters among the Hough lines: the last pass tries the weaker lines too.
    for ring0_hidden, joint, bundle_z_line, climb, wide in (
        (False, False, 0.0, False, False),
        (True, False, 0.0, False, False),
        (False, True, 0.0, False, False),
        (False, False, Z_LINE, False, False),
        (False, False, BUNDLE_Z_LINE, False, False),
        (False, False, 0.0, True, False),
        (False, False, 0.0, False, True),
    ):
        state.ring0_hidden, state.joint, state.bundle_z_line = ring0_hidden, joint, bundle_z_line
        state.climb, state.wide = climb, wide
        for kernel in kernels:
            state.progress = 0
            obs = _detect_with_kernel(img, target, s, kernel, size, state)
            if obs:
                return obs
            if state.progress > furthest:  # the reason of the scale that got furthest
                if ring0_hidden:
                    obs = replace(obs, reason=f"{obs.reason} (rays labelled from ring 1)")
                elif joint:  # (further than the first pass: the rings were fitted together)
                    obs = replace(obs, reason=f"{obs.reason} (rings fitted together)")
                elif bundle_z_line:
                    obs = replace(obs, reason=f"{obs.reason} (rays in bundles)")
                elif climb:
                    obs = replace(obs, reason=f"{obs.reason} (centre moved to the most rings)")
                elif wide:
                    obs = replace(obs, reason=f"{obs.reason} (weaker Hough lines tried)")
                refused, furthest = obs, state.progress
    return refused  # type: ignore[return-value]


def _coarse_pencil(
    per_ring: list[list[tuple[float, NDArray]]],
    radii: NDArray,
    c: NDArray,
    min_rings: int,
    joint: bool = False,
) -> tuple[dict[int, NDArray], NDArray] | str:
    """The rings' coarse conics from their ray crossings and the pencil's centre, or why not.

    Each ring's conic is fitted to all its crossings and, should their pencil disagree with
    the spec's radius ratios, to the crossings that remain when those far from the fit are
    dropped; with either, conics whose labels are off by a ring are named by their sizes.
    ``joint``: where too few rings give conics of their own, all of them are fitted together
    (:func:`~calibration.detection.concentric_rings.concentric_affine_conics`).
    """
    # Rings with crossings over at least a quarter turn (fewer or closer points pin no conic)
    arcs: dict[int, NDArray] = {}
    for k, pts in enumerate(per_ring):
        if len(pts) >= MIN_CONIC_POINTS:
            if np.ptp(np.unwrap(np.sort(np.array([p[0] for p in pts])))) >= np.pi / 2:
                arcs[k] = np.array([p[1] for p in pts])
    fitted = 0
    for fit in (lambda p: fit_conic(p, geometric=False), _trimmed_conic):
        conics: dict[int, NDArray] = {}
        for k, points in arcs.items():
            conic = fit(points)
            if conic is not None and _ellipse_ok(conic, c):
                conics[k] = conic
        fitted = max(fitted, len(conics))
        if len(conics) < min_rings:
            continue
        centre = _pencil_centre(conics, radii, c)
        if centre is not None:
            return conics, centre
        # The rays' labels may be off by a ring: name the conics by their sizes instead.
        renamed = _relabel_by_ratios(conics, radii)
        if len(renamed) >= min_rings:
            centre = _pencil_centre(renamed, radii, c)
            if centre is not None:
                return renamed, centre
    if fitted < min_rings:
        if joint and len(arcs) >= min_rings:
            # Each ring seen over too short an arc for a conic of its own (a laser stripe
            # over the centre): all of them at once, as concentric ellipses of one shape
            # (members of the spec's pencil by construction: their centre is the pencil's).
            together = concentric_affine_conics(arcs, radii, c, FIT_TOL_PX)
            if together is not None:
                return together
        return f"no ring pencil found: {fitted} rings fitted, expected >= {min_rings}"
    return (
        "no ring pencil found: the ring conics are not images of the spec's concentric "
        "circles (radius ratios disagree)"
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
    (:func:`_settled_axes` with ``refit``). The conjugate must show the print as plainly as
    the rings (:data:`MIN_CONJUGATE_EVIDENCE`). Returns the settled lines, their points and
    the hidden one's index, or why not.
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
        return (
            f"diameter lines not conjugate with respect to the rings ({off:.1f} deg off, "
            f"{conjugacy_deg(settled[0], c, conics):.1f} deg with the printed one's "
            "conjugate): not the target's diameters"
        )
    if settled[2] == 1 - keep:  # (nothing to judge it by: not taken on the rings' word alone)
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


def _trimmed_conic(points: NDArray) -> NDArray | None:
    """A ring's coarse conic from its ray crossings, points far from the fit dropped: a ray
    that missed one crossing names the next ring's point as this one's."""
    conic = fit_conic(points, geometric=False)
    for _ in range(3):
        dist = np.abs(sampson_distances(conic, points))
        keep = dist < max(3.0 * 1.4826 * float(np.median(dist)), 1.0)
        if keep.all():
            break
        points = points[keep]
        if len(points) < MIN_CONIC_POINTS:
            return None
        conic = fit_conic(points, geometric=False)
    return conic


def _coarse_darkness(
    img: NDArray, kernel: int, hidden: NDArray | None = None
) -> tuple[NDArray, NDArray, float, NDArray]:
    """The coarse stage's darkness, background, lit paper level and hidden (bright) pixels
    with the closing kernel ``kernel`` px; ``hidden``: the bright pixels where already known
    (``_bright_mask(img, kernel) > 0``)."""
    # Coarse stage on a lightly smoothed image: noise and grain drop about threefold, a
    # printed line keeps most of its darkness.
    if hidden is None:
        hidden = _bright_mask(img, kernel) > 0
    d, bg, lit = _darkness(cv2.GaussianBlur(img, (0, 0), 1.0), kernel, hidden)
    return d, bg, lit, hidden


def _coarse_maps(
    img: NDArray, kernel: int, state: _ScaleState
) -> tuple[_CoarseMaps, NDArray, NDArray]:
    """The coarse stage's maps with the closing kernel ``kernel`` px, its darkness and
    background; sets ``state.floor`` where it is ``None`` (the first scale)."""
    h, w = img.shape
    d, bg, lit, hidden = _coarse_darkness(img, kernel)
    # Darkness over its local noise threshold (> Z_LINE where a printed line may be).
    thr_map, state.floor = _threshold_map(d, bg, 4 * kernel, hidden, state.floor, lit)
    z = d / thr_map
    mask = (z > Z_LINE).astype(np.uint8) * 255
    # Rays stop where the print is hidden (laser stripe, glare): see label_rays.
    z_rays = np.where(hidden, -1.0, z)
    hough = _hough_lines(mask, min_votes=int(0.08 * min(h, w)))
    lines = _distinct_lines(hough, (w, h), HOUGH_LINES)
    z_rays.flags.writeable = False  # shared by every pass
    return _CoarseMaps(z_rays, lines, hough), d, bg


def _detect_with_kernel(
    img: NDArray,
    target: ConcentricCirclesTarget,
    s: ConcentricDetectorSettings,
    kernel: int,
    size: tuple[int, int],
    state: _ScaleState,
) -> TargetObservation:
    """:func:`detect_concentric` with the coarse stage's closing kernel ``kernel`` px.

    Sets ``state.progress`` to the stages passed, and ``state.floor`` where this is the first
    scale (it is ``None``).
    """
    h, w = img.shape
    radii = np.asarray(target.ring_radii_mm, dtype=np.float64)
    d: NDArray | None = None
    bg: NDArray | None = None
    if kernel not in state.coarse:
        state.coarse[kernel], d, bg = _coarse_maps(img, kernel, state)
    z_rays, lines = state.coarse[kernel].z_rays, state.coarse[kernel].lines
    if len(lines) < 2:
        return TargetObservation.failed("no pair of diameter lines found", size, KIND)
    if state.wide:
        lines = _distinct_lines(state.coarse[kernel].hough, size, WIDE_HOUGH_LINES)
        if len(lines) <= HOUGH_LINES:  # every crossing was tried
            return TargetObservation.failed("no weaker Hough lines to try", size, KIND)

    state.progress = 1
    # The candidates' rays are labelled alike in every pass with the same ``ring0_hidden``.
    key = (kernel, state.ring0_hidden, False, state.wide)
    if key not in state.centres:
        first_new = HOUGH_LINES if state.wide else 0
        state.centres[key] = _best_centre(z_rays, lines, radii, size, state.ring0_hidden, first_new)
    if state.climb:
        start, key = state.centres[key], (kernel, state.ring0_hidden, True, False)
        if key not in state.centres:
            state.centres[key] = (
                None
                if start is None
                else _climbed_centre(z_rays, start, radii, kernel, state.ring0_hidden)
            )
        climbed = state.centres[key]
        if climbed is None or np.array_equal(climbed[0], start[0]):
            # (no start gives no climb; the first pass measured an unmoved centre already)
            return TargetObservation.failed("the candidate centre did not move", size, KIND)
    chosen = state.centres[key]
    if chosen is None:
        return TargetObservation.failed(
            "no ring pencil found (no pair of lines with rings around their crossing)", size, KIND
        )
    state.progress = 2
    c, (l1, l2), axis_angles = chosen
    # the chosen centre's rings from many more rays (the kernel makes them cheap)
    per_ring, _ = _label_rays(
        z_rays,
        c,
        radii,
        state.bundle_z_line or Z_LINE,
        axis_angles,
        n_rays=384,
        ring0_hidden=state.ring0_hidden,
        bundle_step_px=BUNDLE_STEP_PX if state.bundle_z_line else 0.0,
    )

    # -- initial conics and the pencil centre
    pencil = _coarse_pencil(per_ring, radii, c, s.min_rings, state.joint)
    if isinstance(pencil, str):
        return TargetObservation.failed(pencil, size, KIND)
    conics, c = pencil
    # Ring images are nested: a coarse conic crossing another is no ring's image (and would
    # set the ring spacing, and every window after it, to the 3 px floor). Where the rest are
    # too few or not the spec's pencil, the fine stage's checks judge them all.
    nested = _nested_rings(conics, c)
    if s.min_rings <= len(nested) < len(conics):
        centre = _pencil_centre(nested, radii, c)
        if centre is not None:
            conics, c = nested, centre

    state.progress = 3
    # -- line width in px estimate, for windows
    spacing_px = _min_spacing_px(conics, c)
    line_frac = target.line_width_mm / float(np.min(np.diff(radii)))
    # The window reaches the paper on both sides of a line but not the neighbouring rings.
    line_px = line_frac * spacing_px
    half_window = max(1.5, min(1.6 * line_px + 2.0, 0.45 * spacing_px), 0.5 * line_px + 1.0)
    # Finer darkness map now that the scale is known (kernel several line widths, < spacing).
    kernel2 = int(np.clip(4 * half_window + 3, 9, max(9, 0.8 * spacing_px)))
    bright = _bright_mask(img, kernel2)
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
    for _ in range(2):
        rings = {}
        n_rays = int(np.clip(_perimeter_px(conics[max(conics)], c) / 3.0, 180, 1440))
        angles = np.linspace(0, 2 * np.pi, n_rays, endpoint=False)
        dirs = np.column_stack([np.cos(angles), np.sin(angles)])
        for k in sorted(conics):
            res = _refine_ring(
                spline,
                conics[k],
                c,
                dirs,
                angles,
                axis_lines,
                half_window,
                spacing_px,
                s,
                (w, h),
                bright,
            )
            if res is not None:
                rings[k] = res
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
        c_new = _pencil_centre(conics, radii, c, strict=True)
        if c_new is None:
            return TargetObservation.failed(
                "no ring pencil found: refined ring conics disagree with the spec's radius ratios",
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

    state.progress = 4
    ratio = min(_conic_axes_ratio(cn) for cn in conics.values())
    if ratio < np.cos(np.radians(s.max_tilt_deg)):
        return TargetObservation.failed(
            f"too oblique: ring images flattened to {ratio:.2f}, "
            f"expected >= {np.cos(np.radians(s.max_tilt_deg)):.2f} (tilt <= {s.max_tilt_deg} deg)",
            size,
            KIND,
        )

    state.progress = 5
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
    state.progress = 6
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

    # Lens distortion bends the lines and rings slightly: every crossing is refined by local
    # quadratic fits of the measured points around it (exact to second order).
    # O itself stays the mean of the pencil's centre and the lines' crossing: both use every
    # ring and line point, which beats a local fit at the noise level.
    pts_x, pts_y = axis_pts[ix], axis_pts[1 - ix]
    named: dict[str, NDArray] = {"O": center}
    points_px = [center]
    points_t = [np.zeros(3)]
    names = ["O"]
    for k in sorted(conics):
        r = radii[k]
        # The other rings' pencil checks every named point (see below).
        predicted = _pencil_predictions(conics, radii, k)
        bias = float(np.median(_pencil_offsets(predicted, rings[k][0]))) if predicted else 0.0
        for axis_name, ln, sgn, axis_idx in (("x", xline, sign_x, 0), ("y", yline, sign_y, 1)):
            pts = line_conic_intersections(ln, conics[k])
            if len(pts) != 2:
                continue
            dirv = _axis_dir(ln, sgn)
            apts = pts_x if axis_name == "x" else pts_y
            for p in pts:
                side = 1.0 if float((p - center) @ dirv) > 0 else -1.0
                if k in rings:
                    ring_pts = rings[k][0]
                    nrm = _conic_normals(conics[k], p[None])[0]
                    ring_line = np.array([nrm[0], nrm[1], -float(nrm @ p)])  # the tangent
                    reach = max(15.0, 0.35 * float(np.linalg.norm(p - center)))
                    # Only where the ring was measured near the crossing: a conic extrapolated
                    # over a part hidden by a stripe or cut by the border may be far off
                    # there, though its ratios agree with the other rings.
                    seen = min(reach, max(15.0, 3.0 * spacing_px))
                    if np.min(np.linalg.norm(ring_pts - p, axis=1)) > seen:
                        continue
                    # ... and where the other rings' pencil puts this ring there too
                    if predicted and abs(
                        float(_pencil_offsets(predicted, p[None])[0]) - bias
                    ) > pencil_tolerance_px(spacing_px):
                        continue
                    biased = _locally_biased(
                        sampson_distances(conics[k], ring_pts), ring_pts, p, reach
                    ) or _locally_biased(apts @ ln[:2] + ln[2], apts, p, reach)
                    q = _local_crossing(ring_pts, ring_line, apts, ln, p, reach) if biased else None
                    if q is not None and np.linalg.norm(q - p) < 2.0:
                        p = q
                if not (0 <= p[0] <= w - 1 and 0 <= p[1] <= h - 1):
                    continue
                pt = np.zeros(3)
                pt[axis_idx] = side * r
                points_px.append(p)
                points_t.append(pt)
                names.append(f"r{k}{'+' if side > 0 else '-'}{axis_name}")
                if k == kmax:
                    key = {("x", 1.0): "A", ("x", -1.0): "B", ("y", 1.0): "C", ("y", -1.0): "D"}
                    named[key[(axis_name, side)]] = p

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
    ax_pts_x, ax_pts_y = axis_pts[ix], axis_pts[1 - ix]
    axes = [
        AxisObservation("x", ax_pts_x, _unit_line(xline)),
        AxisObservation("y", ax_pts_y, _unit_line(yline)),
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
