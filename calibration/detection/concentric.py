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
   Along every ray from O the refined rings must lie where the radii's projectivity puts
   them (rings a ring off over a sector agree with each other's pencil, not with that): one
   ring that does not is dropped, rings mixed with their neighbours refuse the view.
   The diameter lines are located the same way between the rings; a diameter that a laser
   stripe hides (the paper's set-up puts the stripe on A-O-B) is the printed one's
   conjugate with respect to the ring conics (exact for concentric circles). The two
   diameters must be conjugate: a line through O that is not (clutter) gives way to the
   printed one's conjugate, which must then show the print.
6. *Labelling*: the orientation disc, looked for where each of the four candidate labellings
   puts it, must be dark at exactly one of them; A is that end, and C follows from z out of
   the face. Any doubt gives ``ok=False`` with a reason.

The less usual paths (rays from ring 1, the joint fit, bundles, a centre moved off the
crossings of the Hough lines, the crossings of weaker Hough lines, and last the rays'
crossings named again by one homography of the whole target, where rays named whole sectors
a ring or two off) are later passes over the closing scales, run only where the first
refused the view, so that a view the first pass measures is never exposed to their weaker
checks. A last sweep, where every pass refused the view, measures the rings that two
measured ones predict (:mod:`calibration.detection.concentric_missing`), judges the
candidate centres by bundles of rays and names the crossings again around the other passes'
centres, and last around the centres the printed lines' edges vote for; it accepts a view
only with its orientation marker.

Steps 1-3 are in :mod:`calibration.detection.concentric_rays` (the candidate centres in
:mod:`calibration.detection.concentric_centre`, the edges' votes in
:mod:`calibration.detection.concentric_votes`), 4-5 in
:mod:`calibration.detection.concentric_rings` (the diameters in
:mod:`calibration.detection.concentric_axes`, the checks of the rings along the rays and of
the diameters' conjugacy in :mod:`calibration.detection.concentric_fine`, the last pass's
naming in :mod:`calibration.detection.concentric_relabel`) and 6 in
:mod:`calibration.detection.concentric_labels`. :func:`detect_concentric` here runs the
passes over the closing scales and the coarse stage (steps 1-4);
:func:`~calibration.detection.concentric_fine.measure_and_label` runs the fine stage
(steps 5-6) from the coarse pencil.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from calibration.detection.concentric_centre import (
    HOUGH_LINES,
    WIDE_HOUGH_LINES,
    Z_LINE,
    _best_centre,
    _Centre,
    _climbed_centre,
    _voted_centre,
)
from calibration.detection.concentric_fine import (
    AGREED_RAY_DEPARTURE,
    KIND,
    MAX_RAY_DEPARTURE,
    measure_and_label,
)
from calibration.detection.concentric_missing import RingRecovery
from calibration.detection.concentric_rays import (
    BrightMasks,
    _coarse_darkness,
    _distinct_lines,
    _hough_lines,
    _label_rays,
    _threshold_map,
    starts_hidden,
)
from calibration.detection.concentric_relabel import relabelled_pencil
from calibration.detection.concentric_rings import (
    MIN_CONIC_POINTS,
    ConcentricDetectorSettings,
    _ellipse_ok,
    _nested_rings,
    _pencil_centre,
    _relabel_by_ratios,
    concentric_affine_conics,
)
from calibration.detection.concentric_votes import voted_centres
from calibration.detection.conics import (
    fit_conic,
    sampson_distances,
)
from calibration.detection.map_kernels import line_maps
from calibration.detection.observations import TargetObservation
from calibration.detection.ray_kernels import FIT_TOL_PX
from scanner.core.images import to_gray_float
from scanner.core.targets import ConcentricCirclesTarget

__all__ = ["ConcentricDetectorSettings", "detect_concentric"]

log = logging.getLogger(__name__)

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


@dataclass(frozen=True)
class _Pass:
    """How one pass of :func:`detect_concentric` over the closing scales finds the target; each
    pass runs only where every earlier one refused the view, so that a view an earlier pass
    measures is never exposed to a later one's weaker checks."""

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
    :data:`HOUGH_LINES` (up to :data:`WIDE_HOUGH_LINES`): the seventh pass, for views the
    first six refused."""
    relabel: bool = False
    """The candidate centre's rays' crossings named again by one homography of the whole
    target (:func:`relabelled_pencil`): the last regular pass, from the first pass's
    centres, for views all others refused; the last sweep's, from the other passes'."""
    bundle_fallback: bool = False
    """Where the pass has no candidate centre, the one bundles of rays at
    :data:`BUNDLE_Z_LINE` find rings around is taken: the last regular pass."""
    voted: bool = False
    """The candidate centre is the peak of the printed lines' edges' votes whose rays find
    the most rings (:func:`_voted_centre`): a small target among clutter whose diameters
    make no crossing of the Hough lines at O (randomised views 1:104, 2:54, 18:66, 22:81).
    The last sweep's last three passes."""
    bundle_centre: bool = False
    """The candidate centre is the crossing around which bundles of rays at
    :data:`BUNDLE_Z_LINE` find the most rings, and its rays are bundles too: a faint target
    whose lines reach the single rays' threshold only here and there (randomised view 12:39,
    contrast 21 grey levels under 1.9 px of blur, a stripe over O), where single rays find
    more rings in order around a crossing of clutter. The last sweep's."""
    note: str = ""
    """Added to the reason of a refusal this pass got furthest with."""


class _CentreKey(NamedTuple):
    """Which candidate centre of :attr:`_ScaleState.centres`: passes whose candidates' rays
    are labelled alike share it."""

    kernel: int
    """The scale's closing kernel, px."""
    ring0_hidden: bool
    """Rays from ring 1."""
    climbed: bool
    """Moved to where its rays find the most rings (:func:`_climbed_centre`)."""
    wide: bool
    """From the weaker Hough lines' crossings."""
    bundled: bool
    """Judged by bundles of rays."""
    voted: bool
    """Voted by the printed lines' edges (:func:`_voted_centre`)."""


@dataclass
class _ScaleState:
    """What one closing scale of :func:`detect_concentric` tells the next, and each pass over
    the scales the later ones."""

    progress: int = 0
    """Stages the scale passed (lines, centre, coarse pencil, rings measured, tilt,
    diameters): of several refusals the most telling is shown."""
    floor: float | None = None
    """The darkness threshold's floor (:func:`_threshold_map`), set by the first scale."""
    now: _Pass = field(default_factory=lambda: _Pass())
    """The pass being run."""
    centres: dict[_CentreKey, _Centre | None] = field(default_factory=dict)
    """The candidate centre each scale and kind of candidate chose, None for none: the same
    in every pass that labels the candidates' rays alike."""
    coarse: dict[int, _CoarseMaps] = field(default_factory=dict)
    """The coarse maps of each scale (closing kernel, px) the first pass made: the later
    passes label other rays on the same maps."""
    votes: dict[int, NDArray] = field(default_factory=dict)
    """The peaks of the printed lines' edges' votes at each scale (closing kernel, px), for
    every voted pass (:func:`~calibration.detection.concentric_votes.voted_centres`)."""
    bright: BrightMasks | None = None
    """The image's bright masks, each made once for every scale and pass (set with the
    image)."""
    recovery: RingRecovery = field(default_factory=RingRecovery)
    """Whether the fine stage measures rings the coarse stage missed from two it measured
    (the last sweep), and whether a scale's fine stage stopped at two rings without it."""
    two_rings: list[tuple[_Pass, int]] = field(default_factory=list)
    """The passes and scales (closing kernel, px) whose fine stage stopped at two rings: the
    last sweep's."""

    def reached(self, stage: int) -> None:
        """Told by the fine stage which of its stages the scale passed."""
        self.progress = stage


#: The regular passes over the closing scales, in order (see :func:`detect_concentric`).
REGULAR_PASSES = (
    _Pass(),
    _Pass(ring0_hidden=True, note="rays labelled from ring 1"),
    # (further than the first pass: the rings were fitted together)
    _Pass(joint=True, note="rings fitted together"),
    _Pass(bundle_z_line=Z_LINE, note="rays in bundles"),
    _Pass(bundle_z_line=BUNDLE_Z_LINE, note="rays in bundles"),
    _Pass(climb=True, note="centre moved to the most rings"),
    _Pass(wide=True, note="weaker Hough lines tried"),
    _Pass(relabel=True, bundle_fallback=True, note="crossings named again"),
)

#: The last sweep's passes after the repeated two-ring ones: the candidate centres the
#: bundles of rays judge, then the crossings named again by one homography (as in the last
#: regular pass) around the centres the other regular passes chose. Each is there for the
#: randomised views it alone measures: a 62 deg steep target whose innermost ring merges
#: with O (1:64); small targets in a corner among clutter whose diameters rank after the
#: first Hough lines, where some rays name a ring one off (11:73, 20:3) or start at ring 1
#: too (14:89); a steep target whose centre the rays from ring 1 climb to (1:38); a faint
#: steep target under a stripe (16:59). Last, the peaks of the votes the printed lines'
#: edges cast (:mod:`calibration.detection.concentric_votes`), for targets with no crossing
#: of Hough lines at O: a faint one whose second diameter gives no line (2:54), a small one
#: among clutter whose diameters rank after the 78th line (1:104, its crossings named
#: again), a small one cut by the border whose innermost ring merges with O (22:81, its rays
#: from ring 1 named again).
SWEEP_PASSES = (
    _Pass(bundle_z_line=BUNDLE_Z_LINE, bundle_centre=True, note="centre judged by bundles of rays"),
    _Pass(relabel=True, ring0_hidden=True, note="rays from ring 1 named again"),
    _Pass(relabel=True, wide=True, note="weaker Hough lines' crossings named again"),
    _Pass(relabel=True, bundle_centre=True, note="bundles' centre named again"),
    _Pass(
        relabel=True,
        wide=True,
        ring0_hidden=True,
        note="weaker Hough lines' rays from ring 1 named again",
    ),
    _Pass(relabel=True, climb=True, ring0_hidden=True, note="climbed rays from ring 1 named again"),
    _Pass(voted=True, note="centre voted by the rings' edges"),
    _Pass(voted=True, relabel=True, note="voted centre's crossings named again"),
    _Pass(
        voted=True,
        relabel=True,
        ring0_hidden=True,
        note="voted centre's rays from ring 1 named again",
    ),
)


def _regular_passes(kernels: list[int]) -> list[tuple[_Pass, int]]:
    """Every regular pass at every closing scale (px), in order."""
    return [(p, kernel) for p in REGULAR_PASSES for kernel in kernels]


def _sweep_passes(
    two_rings: list[tuple[_Pass, int]], kernels: list[int]
) -> list[tuple[_Pass, int]]:
    """The last sweep: the passes and scales that stopped at two rings again (their missing
    rings measured), then :data:`SWEEP_PASSES` at every scale."""
    again = [(replace(p, note="missing rings measured from two"), k) for p, k in two_rings]
    return again + [(p, kernel) for p in SWEEP_PASSES for kernel in kernels]


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
    state = _ScaleState(bright=BrightMasks(img))
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
    # target's diameters among the Hough lines: the seventh pass tries the weaker lines too.
    # Where rays named whole sectors a ring or two off (faint inner rings, a centre off O),
    # every ring's conic mixes rings: the last regular pass names the crossings again by one
    # homography of the whole target.
    # A last sweep, for views every regular pass refused: where a fine stage measured two
    # rings only (a small target's innermost ring under a laser stripe over O, its outermost
    # too faint for the rays), the rings those two predict are measured, over the passes and
    # scales that stopped so; and where single rays find more rings in order around a
    # crossing of clutter than around a faint target's O, the centre is judged by bundles;
    # and where rays around another pass's centre named sectors a ring off, the crossings are
    # named again there; and where no crossing of Hough lines is at O, the centre is where
    # the printed lines' edges vote for. The sweep accepts a view only with its orientation
    # marker found.
    refused, furthest = None, -1
    for sweep in (False, True):
        # (the sweep's passes depend on which regular ones stopped at two rings)
        todo = _sweep_passes(state.two_rings, kernels) if sweep else _regular_passes(kernels)
        state.recovery.enabled = sweep
        for state.now, kernel in todo:
            state.progress = 0
            state.recovery.wanted = False
            obs = _detect_with_kernel(img, target, s, kernel, size, state)
            if obs and sweep and obs.labelling != "unique":
                # The last sweep's checks are the weakest: the marker, found where the
                # labelling puts it, is the independent evidence it needs (a target-free view
                # of dark paper gave three rings of a four-ring spec around a crossing of
                # grain).
                obs = TargetObservation.failed(
                    "a target found only by the last sweep without its orientation marker: "
                    "not accepted",
                    size,
                    KIND,
                )
            elif obs:
                return obs
            if state.progress > furthest:  # the reason of the scale that got furthest
                if state.now.note:
                    obs = replace(obs, reason=f"{obs.reason} ({state.now.note})")
                refused, furthest = obs, state.progress
            if state.recovery.wanted:
                state.two_rings.append((state.now, kernel))
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


def _coarse_maps(
    img: NDArray, kernel: int, state: _ScaleState
) -> tuple[_CoarseMaps, NDArray, NDArray]:
    """The coarse stage's maps with the closing kernel ``kernel`` px, its darkness and
    background; sets ``state.floor`` where it is ``None`` (the first scale)."""
    h, w = img.shape
    d, bg, lit, hidden = _coarse_darkness(img, kernel, state.bright(kernel) > 0)
    # Darkness over its local noise threshold (> Z_LINE where a printed line may be).
    thr_map, state.floor = _threshold_map(d, bg, 4 * kernel, hidden, state.floor, lit)
    # Rays stop where the print is hidden (laser stripe, glare): see label_rays.
    mask, z_rays = line_maps(d, thr_map, hidden, Z_LINE)
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
    radii = np.asarray(target.ring_radii_mm, dtype=np.float64)
    d: NDArray | None = None
    bg: NDArray | None = None
    if kernel not in state.coarse:
        state.coarse[kernel], d, bg = _coarse_maps(img, kernel, state)
    z_rays, lines = state.coarse[kernel].z_rays, state.coarse[kernel].lines
    if len(lines) < 2 and not state.now.voted:  # (the edges' votes need no lines)
        return TargetObservation.failed("no pair of diameter lines found", size, KIND)
    if state.now.wide:
        lines = _distinct_lines(state.coarse[kernel].hough, size, WIDE_HOUGH_LINES)
        if len(lines) <= HOUGH_LINES:  # every crossing was tried
            return TargetObservation.failed("no weaker Hough lines to try", size, KIND)

    state.progress = 1
    # The candidates' rays are labelled alike in every pass with the same ``ring0_hidden``.
    key = _CentreKey(kernel, state.now.ring0_hidden, False, state.now.wide, False, state.now.voted)
    if key not in state.centres and state.now.voted:
        if kernel not in state.votes:
            state.votes[kernel] = voted_centres(z_rays)
        state.centres[key] = _voted_centre(
            z_rays, state.votes[kernel], radii, state.now.ring0_hidden
        )
    elif key not in state.centres:
        first_new = HOUGH_LINES if state.now.wide else 0
        state.centres[key] = _best_centre(
            z_rays, lines, radii, size, state.now.ring0_hidden, first_new
        )
    bundled = state.now.bundle_z_line
    if state.now.bundle_centre or (state.now.bundle_fallback and state.centres[key] is None):
        # Rings too faint for single rays around every crossing (their own density raises
        # the local threshold: view 16:11): the crossings judged by bundles of rays.
        key, bundled = _CentreKey(kernel, False, False, False, True, False), BUNDLE_Z_LINE
        if key not in state.centres:
            state.centres[key] = _best_centre(
                z_rays, lines, radii, size, False, 0, BUNDLE_Z_LINE, BUNDLE_STEP_PX
            )
    if state.now.climb:
        start = state.centres[key]
        key = _CentreKey(kernel, state.now.ring0_hidden, True, False, False, state.now.voted)
        if key not in state.centres:
            state.centres[key] = (
                None
                if start is None
                else _climbed_centre(z_rays, start, radii, kernel, state.now.ring0_hidden)
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
        bundled or Z_LINE,
        axis_angles,
        n_rays=384,
        ring0_hidden=state.now.ring0_hidden,
        bundle_step_px=BUNDLE_STEP_PX if bundled else 0.0,
    )

    # -- initial conics and the pencil centre
    if state.now.relabel:
        pencil = relabelled_pencil(per_ring, radii, c, s.min_rings, starts_hidden(z_rays, c))
    else:
        pencil = _coarse_pencil(per_ring, radii, c, s.min_rings, state.now.joint)
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
    return measure_and_label(
        img,
        target,
        s,
        conics,
        c,
        (l1, l2),
        z_rays,
        kernel,
        None if d is None or bg is None else (d, bg),
        state.reached,
        state.bright,
        # A last resort's rings must agree along the rays as right views do (randomised view
        # 2:5, 62 deg steep and faint, gave 0.11 gaps with a point 2.3 px off).
        AGREED_RAY_DEPARTURE if state.now.relabel else MAX_RAY_DEPARTURE,
        state.recovery,
    )
