"""Detection over the randomised domain of :mod:`scanner.virtual_cell.randomised`."""

import re
from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from calibration.detection import concentric_fine, concentric_rings
from calibration.detection.concentric_axes import conjugacy_deg
from calibration.detection.concentric_fine import AGREED_RAY_DEPARTURE, ray_departure
from calibration.detection.detect import detect_target
from calibration.detection.observations import TargetObservation
from calibration.symmetry import relabel
from scanner.virtual_cell.randomised import (
    RenderedView,
    draw_conditions,
    paper_dark_surroundings,
    render_view,
)


def _errors(v: RenderedView, obs) -> tuple[float, float]:
    """Centre error and worst named-point error against the truth, px (a view labelled up to
    the target's symmetry: with the quarter turn that fits best)."""
    index = {n: i for i, n in enumerate(v.point_names)}
    turns = range(4) if obs.labelling == "symmetry" else [0]
    worst = min(
        max(
            float(np.linalg.norm(p - v.points_px[index[n]])) if n in index else np.inf
            for n, p in zip(o.point_names, o.points_px)
        )
        for o in (relabel(obs, k) if k else obs for k in turns)
    )
    return float(np.linalg.norm(obs.center_px - v.center_px)), worst


def _check_slice(n: int, seed: int, min_rate: float) -> None:
    detected, detectable = 0, 0
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        v = render_view(draw_conditions(rng), rng)
        obs = detect_target(v.image, v.spec)
        if obs:
            centre, worst = _errors(v, obs)
            # A wrong label moves a point by a ring spacing or a quarter turn.
            assert worst < max(1.5, 0.3 * v.min_spacing_px), (i, worst)
            assert centre < 0.5, (i, centre)
        else:
            assert obs.reason
        if v.detectable:
            detectable += 1
            detected += bool(obs)
    assert detected >= min_rate * detectable, (detected, detectable)


def test_paper_target_with_dark_surroundings_is_detected():
    # Issue #15: a frontal, clean 1024x768 view of the paper's target, dark around the card
    # over most of the frame, was refused ("no ring pencil found").
    v = render_view(paper_dark_surroundings(), np.random.default_rng(0))
    assert v.detectable
    assert v.surround_frac > 0.4
    obs = detect_target(v.image, v.spec)
    assert obs, obs.reason
    centre, worst = _errors(v, obs)
    assert centre < 0.05
    assert worst < 0.3
    for name in "ABCD":
        assert np.linalg.norm(obs.named_px[name] - v.named_px[name]) < 0.3


def _detected_view(
    seed: int, view: int, what: str
) -> tuple[RenderedView, TargetObservation, float, float]:
    """Benchmark view ``seed:view`` (a detectable one), detected: the view, the observation,
    its centre and worst named-point errors (px)."""
    rng = np.random.default_rng([seed, view, 1])
    return _detected(render_view(draw_conditions(rng, has_target=True), rng), what)


def _detected(v: RenderedView, what: str) -> tuple[RenderedView, TargetObservation, float, float]:
    """A detectable rendered view, detected: as :func:`_detected_view` gives it."""
    assert v.detectable
    obs = detect_target(v.image, v.spec)
    assert obs, f"{what}: {obs.reason}"
    return (v, obs, *_errors(v, obs))


@pytest.mark.parametrize(
    ("seed", "view", "what"),
    [
        # refused before 2026-11-25
        (0, 1, "dense rings over bright paper taken for glare by a median paper level"),
        (0, 2, "faint wide lines: the conic fit's RMS is the noise of a low-contrast line"),
        (0, 8, "steep tilt: the short diameter's evidence diluted by paper beyond the rings"),
        (0, 21, "a laser stripe running beside a diameter"),
        (0, 47, "a small target whose diameters were outvoted by clutter lines"),
        (0, 93, "ray crossings mislabelled by one ring in a few rays"),
        # refused before 2026-11-26 (3:117 detected with a diameter turned 5 deg, a wrong
        # labelling, once the faint views were mended; 5:82 and 7:115 refused by first
        # versions of the learnt floor)
        (4, 1, "a faint print (27 grey levels, 1 px lines): darkness under a fixed floor"),
        (5, 17, "a faint print on a 640x480 view: darkness under a fixed floor"),
        (9, 59, "21 grey levels of contrast under blurred 1 px lines"),
        (3, 117, "a Hough line 26 deg off the diameter, turned only part of the way in one fit"),
        (5, 82, "most of the paper's darkness exactly 0 at the first scale: no floor learnt"),
        (7, 115, "a 16-bit view whose paper is quieter than one 8-bit grey level"),
        # refused until the eighteenth session: the innermost ring's image merges with the
        # diameters' crossing at O and every ray names ring 1 as ring 0 (the second pass
        # labels rays from ring 1 where the fit puts ring 0 inside their blind start)
        (0, 94, "a 61 deg tilt: the innermost ring's image merges with the diameters' crossing"),
        (7, 52, "a small steep 4-ring target whose innermost ring merges with O's crossing"),
        (6, 89, "the innermost ring lost at the rays' start"),
        (9, 97, "the innermost ring lost at the rays' start, and a false centre"),
        # refused until the twenty-first session
        (7, 1, "a coarse conic crossing the others set the ring spacing to nothing"),
        (8, 117, "a single ray's crossings too few for coarse conics the fine stage can use"),
        (3, 50, "a 62 deg tilt: single rays' crossings give no pencil, bundles do"),
        (3, 92, "grain and a stripe: single rays' crossings give no pencil, bundles do"),
        (1, 17, "14 thin rings 10 px apart, 21 grey levels in grain: at the threshold itself"),
        (5, 21, "a 59 deg tilt, 24 grey levels in grain: bundles below the single threshold"),
        # refused until the twenty-third session: no Hough line along the short diameter,
        # so no crossing of two lines at O (the sixth pass climbs to the most rings)
        (3, 34, "a 58 deg tilt, small among clutter: the short diameter gives no Hough line"),
        # refused until the twenty-sixth session: long clutter edges outrank the diameters
        # (22nd-43rd among the Hough lines; the last pass tries lines after the 16th)
        (5, 1, "a small target among long clutter edges: its diameters not among 16 lines"),
        # refused until the thirty-fourth session: whole sectors of rays named a ring or two
        # off, every ring's coarse conic a mixture (the last pass names the crossings again
        # by one homography of the target)
        (16, 11, "small, frontal, faint: only bundles find rings, inner ones missed at left"),
        (19, 76, "a clean 4-ring target whose rays start 20 px from O"),
        (14, 3, "a 50 deg tilt, contrast over noise 3.3"),
        # refused until 2026-12-03: rays around another pass's centre named sectors a ring
        # off (the last sweep names the crossings again there)
        (11, 73, "a small target in a corner among clutter: a third of the rays a ring off"),
        (20, 3, "a small target among clutter: its diameters after the first Hough lines"),
        (1, 64, "a 62 deg tilt: the innermost ring merges with O, rays a ring off"),
        (16, 59, "a faint steep target under a stripe: bundles' centre, rays a ring off"),
        (1, 38, "a steep target whose centre the rays from ring 1 climb to"),
        (14, 89, "weaker Hough lines' rays from ring 1, a ring off over a sector"),
        # refused until the forty-sixth session: no crossing of Hough lines at O (the last
        # sweep takes the centres the printed lines' edges vote for)
        (1, 104, "86 px across among clutter, a stripe: the diameters 78th Hough line on"),
        (2, 54, "faint, 11 thin rings: the second diameter gives no Hough line"),
        (22, 81, "small, cut by the border, ring 0 merged with O: voted, from ring 1"),
        # seed 27 was first run by the forty-sixth session: a clean frontal view whose
        # second diameter's refit the stripe through O, 13 deg off, turned onto itself
        (27, 66, "4 bold rings, a stripe through O: the conjugate diameter held"),
        # refused until the forty-eighth session: 8 grey levels of noise, a third of the
        # paper's darkness exactly 0 under the smaller closings, whose tiles learnt the floor;
        # clutter's crossings in order then outranked a steep 4-ring target's O
        (21, 39, "a 65 deg tilt, half outside, in noise: smaller scales' tiles censored at 0"),
    ],
)
def test_views_the_benchmark_missed_are_detected_and_labelled_right(
    seed: int, view: int, what: str
):
    # Views of benchmarks/bench_detection.py the detector refused, each for the reason
    # ``what``.
    v, _, centre, worst = _detected_view(seed, view, what)
    assert centre < 0.5
    assert worst < max(1.5, 0.3 * v.min_spacing_px), what


def _detected_stripe_view(
    seed: int, view: int, what: str
) -> tuple[RenderedView, TargetObservation, float, float]:
    """:func:`_detected_view` of a view with a laser stripe."""
    detected = _detected_view(seed, view, what)
    assert detected[0].conditions.laser
    return detected


@pytest.mark.parametrize(
    ("seed", "view", "what"),
    [
        (1, 40, "tiles filled by a stripe learnt a threshold below the paper's noise"),
        (1, 71, "a stripe along a diameter: the evidence from the parallel it leaves"),
        (1, 105, "the Hough pair that gave the centre held the stripe's edge"),
        (0, 20, "the outer ring's conic, extrapolated past the stripe, named a wrong point"),
        (6, 81, "a stripe far brighter than the paper was taken for its lit level"),
        # refused until the twentieth session: a wide stripe 4 px from O leaves each ring
        # over about 105 deg, too short an arc for a conic of its own (fitted jointly now)
        (0, 25, "a stripe over O: each ring seen over too short an arc for its own conic"),
        # refused until the forty-third session: a wide stripe over O hides ring 0 and the
        # rays name ring 1 as ring 0; the outermost ring too faint for them. Two rings
        # measured, named by their ratio, predict the others (the last sweep)
        (3, 69, "a stripe over a small target's O: two rings measured, a ring off"),
        # and until then: single rays find more rings in order around a crossing of clutter
        # than around a faint target's O (the last sweep judges the centres by bundles)
        (12, 39, "contrast 21 under 1.9 px of blur, a stripe by O: the centre 74 px off"),
        (23, 38, "11 rings, O 64 px from the border, the stripe by O: a clutter crossing"),
        # refused until the forty-sixth session: a faint print (contrast over noise 3.5,
        # 1.7 px of blur), the second diameter dark on a fifth of its samples only (the
        # angular scan takes it where the rings put it, the first one's conjugate)
        (17, 101, "a faint print, a stripe through O: the second diameter under the scan's bar"),
        # refused until the forty-seventh session: a 30 px stripe 8 deg off a diameter over a
        # faint print; the rays along it start beyond the inner rings and name the first
        # ring they see ring 0 (the renaming shifts each ray's names as a whole)
        (18, 66, "a stripe along a diameter over O: most rays name their rings a shift off"),
        # detected by a renaming 2 px off O before; named right, the two inner rings under a
        # stripe tangent to ring 0 broke the radii along the rays (both are dropped now)
        (21, 50, "13 rings, a stripe tangent to the innermost: two rings off their lines"),
    ],
)
def test_views_with_a_laser_stripe_over_the_target_are_detected_and_labelled_right(
    seed: int, view: int, what: str
):
    # Views of benchmarks/bench_detection.py refused (or, for 0:20, mislabelled while the
    # others were mended) before 2026-11-26; each for the reason ``what``.
    v, _, centre, worst = _detected_stripe_view(seed, view, what)
    assert centre < 1.0  # (a stripe over O leaves few points near it)
    assert worst < max(1.5, 0.3 * v.min_spacing_px), what


@pytest.mark.parametrize(
    ("seed", "view", "what"),
    [
        (8, 55, "a stripe along a diameter hides it whole"),
        (5, 89, "a stripe over most of a diameter leaves it too few points"),
    ],
)
def test_a_diameter_under_a_laser_stripe_is_the_printed_ones_conjugate(
    seed: int, view: int, what: str
):
    # Views of benchmarks/bench_detection.py refused before 2026-11-26 ("diameter line not
    # printed", "not measurable"): the hidden diameter has no points of its own, its line is
    # the conjugate of the printed one, and the points named on it are right.
    _, obs, centre, worst = _detected_stripe_view(seed, view, what)
    assert sorted(len(a.points_px) for a in obs.axis_points)[0] == 0, what
    assert centre < 0.3
    assert worst < 1.0, what


def test_a_clutter_line_through_o_gives_way_to_the_printed_diameters_conjugate():
    # View 11:2 of benchmarks/bench_detection.py (seed 11: not looked at while the detector
    # was changed): a 64 deg tilt among clutter, whose diameters the angular scan did not
    # see. The Hough pair kept held a clutter line through O, 44 deg off the printed
    # diameter's conjugate; the points named on it were 131 px off, a wrong labelling, until
    # the thirty-second session. The printed one's conjugate replaces it.
    v, obs, centre, worst = _detected_view(11, 2, "a clutter line through O")
    assert v.conditions.tilt_deg > 60
    conics = {i: r.conic for i, r in enumerate(obs.rings)}
    assert conjugacy_deg([a.line for a in obs.axis_points], obs.center_px, conics) < 0.5
    assert obs.labelling == "unique"
    assert centre < 0.3
    assert worst < 1.0


def test_a_wrong_pencils_conjugate_does_not_name_points():
    # View 4:60 (contrast over noise 2.5: below the domain's 3, not called detectable), a
    # target in the corner whose ring pencil is one ring off: the conjugate of its printed
    # diameter misses the other printed one by 3 deg and shows 0.69 of the rings' darkness.
    # Taken for a diameter, it named points 23 px off; it must be refused, or labelled right.
    rng = np.random.default_rng([4, 60, 1])
    v = render_view(draw_conditions(rng, has_target=True), rng)
    assert not v.detectable
    obs = detect_target(v.image, v.spec)
    if obs:
        _, worst = _errors(v, obs)
        assert worst < max(1.5, 0.3 * v.min_spacing_px), worst


def test_rings_a_ring_off_over_a_sector_name_no_point():
    # View 13:89 of benchmarks/bench_detection.py (seed 13: not looked at while the detector
    # was changed): a faint, blurred 640x480 view (contrast over noise 4.5, rings 6.6 px
    # apart) with a stripe across it. The first pass's coarse conics were a ring off over a
    # sector; refined there on their inner neighbours' lines, five rings agreed with each
    # other's pencil, and points named on them were 10-11 px off, a wrong labelling, until
    # the thirty-third session. They depart 0.21 ring gaps from the radii along the rays
    # from O: refused, and a later pass measures the view.
    v, obs, centre, worst = _detected_view(13, 89, "rings on their neighbours' lines")
    assert v.conditions.laser and v.line_snr < 5
    radii = np.asarray(v.spec.ring_radii_mm)
    conics = {r.index: r.conic for r in obs.rings}
    assert np.nanmax(ray_departure(conics, radii, obs.center_px)) < AGREED_RAY_DEPARTURE
    assert centre < 1.0
    assert worst < max(1.5, 0.3 * v.min_spacing_px)


@pytest.mark.parametrize(
    ("seed", "view"),
    [(5, 77), (3, 100)],
)
def test_a_ring_flank_along_a_diameter_does_not_turn_it(seed: int, view: int):
    # Steep tilts (58 and 64 deg) put the rings' flanks nearly along one diameter: centres
    # caught by them turned the fitted line by 1.3-2.8 deg, and the points named on it were
    # 3-6 px off (one labelling counted wrong by the benchmark) before 2026-11-26.
    rng = np.random.default_rng([seed, view, 1])
    v = render_view(draw_conditions(rng, has_target=True), rng)
    assert v.detectable and v.conditions.tilt_deg > 55
    obs = detect_target(v.image, v.spec)
    assert obs, obs.reason
    centre, worst = _errors(v, obs)
    assert centre < 0.2
    assert worst < 1.0


def test_a_last_resorts_rings_agree_along_the_rays_as_right_views_do():
    # View 2:5 (62 deg, contrast over noise 4.5, rings 7.4 px apart) is measured by the last
    # pass only. Its four rings first departed 0.11 ring gaps from the radii along the rays
    # from O, within what other passes allow (0.15) but not what right views show (0.05),
    # and a point was named 2.3 px off, a wrong labelling; the last pass asks for 0.05, and
    # the innermost ring, seen over short arcs beside O, is dropped.
    v, obs, centre, worst = _detected_view(2, 5, "the last pass's rings")
    assert sorted(r.index for r in obs.rings) == [1, 2, 3]
    radii = np.asarray(v.spec.ring_radii_mm)
    conics = {r.index: r.conic for r in obs.rings}
    # (judged at the centre before the last refinement; 0.051 at the final one)
    assert np.nanmax(ray_departure(conics, radii, obs.center_px)) < 1.1 * AGREED_RAY_DEPARTURE
    assert centre < 0.5
    assert worst < max(1.5, 0.3 * v.min_spacing_px)


def test_a_ring_cut_by_the_border_names_no_point_the_other_rings_disagree_with():
    # Seed 2, view 13 of the benchmark (its marker is outside the image, so the spec does not
    # count it, but a detection must still be right): ring 5, cut by the image's corner,
    # was fitted where it was seen and named crossings 10-16 px off where it was not.
    rng = np.random.default_rng([2, 13, 1])
    v = render_view(draw_conditions(rng, has_target=True), rng)
    obs = detect_target(v.image, v.spec)
    assert obs, obs.reason
    _, worst = _errors(v, obs)
    assert worst < max(1.5, 0.3 * v.min_spacing_px)
    # Since the thirty-third session the ring is dropped whole: its conic departs 1.2 ring
    # gaps from the radii along the rays from O, the other six agree within 0.01.
    assert 5 not in {r.index for r in obs.rings}
    assert len(obs.rings) == 6
    assert worst < 0.2


@pytest.mark.parametrize(
    ("seed", "view", "first_worst_px"),
    [
        # (seed 21: not looked at before the thirty-fifth session; the marker is outside the
        # image, so the spec does not count the view, but a detection must still be right)
        (21, 118, 6.0),
        (0, 20, 2.0),
    ],
)
def test_windows_sized_by_a_ring_the_fine_stage_dropped_are_sized_again(
    seed: int, view: int, first_worst_px: float
):
    # On view 21:118 two outer rings cut by the image's top were fitted by coarse conics
    # within 3 px of each other: the fine stage's windows, sized by the smallest spacing,
    # searched 1 px around coarse conics that were 6 px off the print over two sectors, and
    # the three rings kept confirmed them (points 6.0 px off, a wrong labelling). Their own
    # spacing is 18 px: measured again with windows of it, they are right. View 0:20 was
    # counted right with a point 2.0 px off.
    rng = np.random.default_rng([seed, view, 1])
    v = render_view(draw_conditions(rng, has_target=True), rng)
    obs = detect_target(v.image, v.spec)
    assert obs, obs.reason
    centre, worst = _errors(v, obs)
    assert centre < 0.2
    assert worst < 0.5 < first_worst_px


def test_where_windows_of_the_kept_rings_spacing_agree_the_first_measurement_stands(
    monkeypatch,
):
    # View 0:42: a coarse conic the fine stage dropped sized its windows at 4.6 px against
    # the kept rings' 11.8. Refined with windows of that spacing, the kept rings move by
    # under a pixel: the first measurement, whose worst point is the nearer to the truth
    # (0.09 px against 0.41 measured again), stands, and the view is not measured again.
    rng = np.random.default_rng([0, 42, 1])
    v = render_view(draw_conditions(rng, has_target=True), rng)
    moved, measured = [], []
    apart, measure = concentric_fine._conics_apart_px, concentric_fine._measure
    monkeypatch.setattr(
        concentric_fine, "_conics_apart_px", lambda *a: moved.append(apart(*a)) or moved[-1]
    )
    monkeypatch.setattr(concentric_fine, "_measure", lambda *a: measured.append(a) or measure(*a))
    obs = detect_target(v.image, v.spec)
    assert obs, obs.reason
    assert 0.0 < max(moved) < concentric_fine.RESIZED_AGREE_PX
    assert all(a[-1] is not None for a in measured)  # (a measurement again passes None)
    assert _errors(v, obs)[1] < 0.15
    monkeypatch.setattr(concentric_fine, "RESIZE_SPACING", np.inf)
    alone = detect_target(v.image, v.spec)
    np.testing.assert_array_equal(obs.points_px, alone.points_px)


def _steep_off_axis_view(axis_deg: float, tilt_deg: float) -> RenderedView:
    """The paper's target through a wide lens (f = 0.9 widths, the randomised domain's
    shortest) ``tilt_deg`` from its line of sight, near the top left corner."""
    c = replace(
        paper_dark_surroundings(),
        focal_px=930.0,
        distance_mm=300.0,
        tilt_deg=tilt_deg,
        tilt_axis_deg=axis_deg,
        centre_px=(190.0, 190.0),
    )
    return render_view(c, np.random.default_rng(0))


@pytest.mark.parametrize("axis_deg", [30.0, 210.0])
def test_a_steep_target_off_the_axis_is_judged_by_its_tilt_not_its_flatness(axis_deg: float):
    # 64.5 deg from the line of sight: the image plane's own obliquity near the corner
    # flattens the rings to 0.40, as a target 66.4 deg off on the axis would be; such views
    # were refused as too oblique.
    _, _, centre, worst = _detected(_steep_off_axis_view(axis_deg, 64.5), "64.5 deg off axis")
    assert centre < 0.1
    assert worst < 0.5


def test_a_target_steeper_than_the_limit_is_refused_with_its_tilt():
    v = _steep_off_axis_view(30.0, 69.0)
    obs = detect_target(v.image, v.spec)
    assert not obs
    read = re.search(r"tilted ([0-9.]+) deg from the line of sight", obs.reason)
    assert read, obs.reason
    assert abs(float(read.group(1)) - 69.0) < 1.5


def test_fast_randomised_slice_never_mislabels():
    _check_slice(12, seed=7, min_rate=0.85)  # 9 of 9 detectable detected (2026-11-24)


def test_target_free_views_are_refused():
    for i in range(6):
        rng = np.random.default_rng([11, i])
        v = render_view(draw_conditions(rng, has_target=False), rng)
        obs = detect_target(v.image, v.spec)
        assert not obs
        assert obs.reason


def test_the_last_sweep_accepts_no_target_without_its_marker():
    # The last sweep's weaker checks are trusted only with the orientation marker. Randomised
    # view 25:75 has its marker outside the image, and only the last sweep finds its rings.
    rng = np.random.default_rng([25, 75, 1])
    v = render_view(draw_conditions(rng, has_target=True), rng)
    assert v.why_not == "orientation marker outside the image"
    obs = detect_target(v.image, v.spec)
    assert not obs
    assert "last sweep without its orientation marker" in obs.reason
    # Target-free dark paper (seed 2, view 14), where bundles of rays found three rings of the
    # four-ring spec around a crossing of grain and the marker rule refused them; since the
    # forty-eighth session the smaller scales' thresholds keep that grain out before.
    rng = np.random.default_rng([2, 14, 0])
    v = render_view(draw_conditions(rng, has_target=False), rng)
    assert not detect_target(v.image, v.spec)


@pytest.mark.slow
def test_larger_randomised_slice_never_mislabels():
    _check_slice(60, seed=8, min_rate=0.9)  # 46 of 50 (2026-11-25; 44 on 2026-11-24)


@pytest.mark.parametrize(("seed", "view"), [(0, 21), (0, 47), (3, 117)])
def test_the_fine_stages_spline_window_detects_as_the_whole_map_does(monkeypatch, seed, view):
    # (a laser stripe beside a diameter, a small target, a diameter found 26 deg off)
    rng = np.random.default_rng([seed, view, 1])
    v = render_view(draw_conditions(rng, has_target=True), rng)
    windowed = detect_target(v.image, v.spec)

    def whole_map(darkness, conics, c, reach_px):
        whole = ndimage.spline_filter(darkness, order=3)
        return concentric_rings.SplineWindow(darkness, whole, (0, 0), whole)

    monkeypatch.setattr(concentric_fine, "spline_window", whole_map)
    whole = detect_target(v.image, v.spec)
    assert windowed and whole
    np.testing.assert_array_equal(windowed.points_px, whole.points_px)
    for a, b in zip(windowed.rings, whole.rings, strict=True):
        np.testing.assert_array_equal(a.edge_points_px, b.edge_points_px)
