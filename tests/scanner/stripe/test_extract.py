"""Stripe extraction on rendered frames with known centres (scanner.virtual_cell.analytic)."""

from __future__ import annotations

import numpy as np
import pytest

from scanner.stripe.background import flatten_background
from scanner.stripe.estimates import auto_half_window, estimate_noise
from scanner.stripe.extract import (
    StripeFlag,
    StripeOptions,
    StripeProfile,
    extract_stripe,
    orientation_from_calibration,
    orientation_from_image,
)
from scanner.virtual_cell.analytic import (
    StripeSegment,
    TableStepScene,
    draw_stripe_conditions,
    render_stripe_conditions,
    render_stripes,
)

SHAPE = (240, 320)


def _errors(profile: StripeProfile, lines: np.ndarray, pos: np.ndarray, across: bool = False):
    """Error of each extracted point against the truth of its line (NaN where the truth has none)."""
    truth = np.full(max(SHAPE) + 1, np.nan)
    truth[lines] = pos
    got = profile.v if across else profile.u
    return got - truth[profile.line]


def _single(seed: int = 0, noise: float = 1.0, sigma: float = 1.5, orientation: str = "rows"):
    seg = StripeSegment((0, SHAPE[0]), (140.3, 0.21, -2e-4), amplitude=170.0, sigma_px=sigma)
    return render_stripes(SHAPE, [seg], noise=noise, seed=seed, orientation=orientation)


@pytest.mark.parametrize(("mode", "rms_max"), [("fast", 0.03), ("precise", 0.015)])
def test_single_stripe_meets_accuracy_targets(mode, rms_max):
    img, truth = _single(seed=1)
    p = extract_stripe(img, mode=mode, orientation="rows")
    err = _errors(p, *truth[0])
    assert len(p) == SHAPE[0]
    assert np.sqrt(np.mean(err**2)) < rms_max
    assert abs(np.mean(err)) < 0.005
    assert np.all(p.flags == 0)
    np.testing.assert_array_equal(p.v, p.line)


@pytest.mark.parametrize("mode", ["fast", "precise"])
def test_column_scan_lines_match_row_scan_lines(mode):
    img, truth = _single(seed=2, orientation="cols")
    assert orientation_from_image(img) == "cols"
    p = extract_stripe(img, mode=mode, orientation="auto")
    assert p.orientation == "cols"
    err = _errors(p, *truth[0], across=True)
    assert np.sqrt(np.mean(err**2)) < (0.03 if mode == "fast" else 0.015)
    np.testing.assert_array_equal(p.u, p.line)


@pytest.mark.parametrize("mode", ["fast", "precise"])
def test_no_bias_at_the_image_border(mode):
    # A slanted stripe that runs within 2 px of the left border at the top rows.
    rng = np.random.default_rng(3)
    errs_edge, errs_top = [], []
    for seed in range(6):
        c0 = 1.2 + rng.uniform(0, 1)
        seg = StripeSegment((0, SHAPE[0]), (c0, 0.5), amplitude=170.0, sigma_px=1.3)
        img, truth = render_stripes(SHAPE, [seg], noise=1.0, seed=seed)
        p = extract_stripe(img, mode=mode, orientation="rows")
        err = _errors(p, *truth[0])
        edge = p.u < 4.5
        errs_edge.append(err[edge])
        errs_top.append(err[p.line < 3])
        assert np.all(p.flags[edge & (p.u < 2.5)] & StripeFlag.BORDER)
    e = np.concatenate(errs_edge)
    t = np.concatenate(errs_top)
    assert e.size > 20
    # Bias at the border: well inside the RMS targets (standard error ~0.01 px here).
    assert abs(np.mean(e)) < 0.02
    assert np.sqrt(np.mean(e**2)) < 0.06
    assert abs(np.mean(t)) < 0.03


def test_several_segments_on_one_line_are_all_kept():
    # An object's segment and the table's beside it share lines 90..119.
    table = StripeSegment((0, 120), (100.0, 0.05), amplitude=170.0)
    obj = StripeSegment((90, 240), (180.0, -0.05), amplitude=110.0)
    img, truth = render_stripes(SHAPE, [table, obj], noise=1.0, seed=4)
    for mode in ("fast", "precise"):
        p = extract_stripe(img, mode=mode, orientation="rows")
        shared = (p.line >= 90) & (p.line < 120)
        assert np.all(np.bincount(p.line[shared])[90:120] == 2)
        for lines, pos in truth:
            err = _errors(p, lines, pos)
            near = np.abs(err) < 2
            assert np.count_nonzero(near) == lines.size  # every line of the segment found
            assert np.sqrt(np.mean(err[near] ** 2)) < 0.05
        assert len(p) == 240 + 30  # and nothing else
        weaker = shared & (p.u > 140)
        assert np.all(p.flags[weaker] & StripeFlag.SECONDARY)


def test_dark_ink_gap_gives_no_false_points():
    seg = StripeSegment((0, SHAPE[0]), (150.0, 0.1), amplitude=170.0)
    img, truth = render_stripes(
        SHAPE, [seg], noise=1.5, seed=5, dark=[(80, 120, 0.0), (150, 170, 0.08)]
    )
    p = extract_stripe(img, mode="fast", orientation="rows")
    err = _errors(p, *truth[0])
    assert not np.any((p.line >= 80) & (p.line < 120))  # stripe absorbed: nothing
    dim = (p.line >= 150) & (p.line < 170)
    # Barely visible: each point either absent or on the stripe, and flagged.
    assert np.all(np.abs(err[dim]) < 1.0)  # noisy (SNR ~9) but on the stripe
    assert np.all(p.flags[dim] & StripeFlag.LOW_CONTRAST)
    assert np.all(np.abs(err[~dim]) < 0.15)


@pytest.mark.parametrize("mode", ["fast", "precise"])
def test_saturated_flat_tops_are_centred_and_flagged(mode):
    seg = StripeSegment((0, SHAPE[0]), (120.4, 0.3), amplitude=900.0, sigma_px=1.6)
    img, truth = render_stripes(SHAPE, [seg], noise=1.0, seed=6)
    assert (img == 255).sum(axis=1).min() >= 3
    p = extract_stripe(img, mode=mode, orientation="rows")
    err = _errors(p, *truth[0])
    assert len(p) == SHAPE[0]
    assert np.all(p.flags & StripeFlag.SATURATED)
    assert np.sqrt(np.mean(err**2)) < 0.1
    assert abs(np.mean(err)) < 0.03


@pytest.mark.parametrize("mode", ["fast", "precise"])
def test_saturated_stripe_on_a_bright_background_with_a_laser_off_frame(mode):
    # A white card under room light (grey 175) and a laser that clips at 255: after the
    # laser-off frame is subtracted the plateau is ~80 grey levels of noisy flat top. It must
    # stay one saturated run per line (as in real line-laser captures), not a row of ridges.
    seg = StripeSegment((0, SHAPE[0]), (120.4, 0.3), amplitude=400.0, sigma_px=3.0)
    img, truth = render_stripes(SHAPE, [seg], background=175.0, noise=2.0, seed=12)
    off, _ = render_stripes(SHAPE, [], background=175.0, noise=2.0, seed=13)
    assert (img == 255).sum(axis=1).min() >= 5
    p = extract_stripe(img, mode=mode, orientation="rows", background=off)
    err = _errors(p, *truth[0])
    assert len(p) == SHAPE[0]
    assert np.all(p.flags & StripeFlag.SATURATED)
    assert not np.any(p.flags & StripeFlag.SECONDARY)
    assert np.sqrt(np.mean(err**2)) < 0.15


def test_weaker_reflection_is_dropped_and_flagged():
    main = StripeSegment((0, SHAPE[0]), (120.0, 0.2), amplitude=170.0)
    ghost = StripeSegment((60, 140), (150.0, 0.2), amplitude=60.0, sigma_px=2.5)
    img, truth = render_stripes(SHAPE, [main, ghost], noise=1.0, seed=7)
    p = extract_stripe(img, mode="fast", orientation="rows")
    err = _errors(p, *truth[0])
    assert len(p) == SHAPE[0]
    assert np.sqrt(np.mean(err**2)) < 0.05
    amb = (p.flags & StripeFlag.AMBIGUOUS) != 0
    np.testing.assert_array_equal(np.unique(p.line[amb]), np.arange(60, 140))
    kept = extract_stripe(img, mode="fast", orientation="rows", keep_reflections=True)
    assert len(kept) == SHAPE[0] + 80


def test_laser_off_frame_removes_a_lit_target():
    seg = StripeSegment((0, SHAPE[0]), (160.0, 0.0), amplitude=120.0)
    lit = (40, 200, 60, 260, 110.0)
    # The stripe crosses dark ink (absent) on lines 100..130 inside the lit patch.
    img, truth = render_stripes(
        SHAPE, [seg], noise=1.0, seed=8, lit_region=lit, dark=[(100, 130, 0.0)]
    )
    off, _ = render_stripes(SHAPE, [], noise=1.0, seed=9, lit_region=lit)
    p = extract_stripe(img, mode="precise", orientation="rows", background=off)
    err = _errors(p, *truth[0])
    assert not np.any((p.line >= 100) & (p.line < 130))
    assert np.count_nonzero(p.line < 100) == 100
    assert np.sqrt(np.mean(err**2)) < 0.03


def test_noise_only_frame_gives_nothing():
    img, _ = render_stripes(SHAPE, [], noise=3.0, seed=10)
    assert len(extract_stripe(img, mode="fast")) == 0
    assert len(extract_stripe(img, mode="precise")) == 0


def test_sixteen_bit_frames():
    seg = StripeSegment((0, SHAPE[0]), (140.3, 0.21), amplitude=170.0 * 64)
    img, truth = render_stripes(
        SHAPE, [seg], noise=64.0, background=500.0, seed=11, dtype=np.uint16, full_scale=65535.0
    )
    p = extract_stripe(img, mode="precise", orientation="rows")
    err = _errors(p, *truth[0])
    assert len(p) == SHAPE[0]
    assert np.sqrt(np.mean(err**2)) < 0.015


def test_orientation_from_calibration_follows_the_light_plane():
    cal = TableStepScene().calibration()
    assert orientation_from_calibration(cal) == "rows"
    # Turn the plane about the optical axis by 90 degrees: its line now runs left to right.
    n = cal.light_plane.normal
    cal.light_plane = type(cal.light_plane)(np.array([n[1], n[0], n[2]]), cal.light_plane.d)
    assert orientation_from_calibration(cal) == "cols"


def test_bad_input_is_refused_saying_expected_and_got():
    img, _ = _single()
    with pytest.raises(ValueError, match="mode: expected"):
        extract_stripe(img, mode="slow")
    with pytest.raises(ValueError, match="orientation: expected"):
        extract_stripe(img, orientation="diagonal")
    with pytest.raises(ValueError, match="expected a 2-D grey image"):
        extract_stripe(np.dstack([img, img, img]))
    with pytest.raises(ValueError, match="background: expected the image's shape"):
        extract_stripe(img, background=img[:-1])


# --------------------------------------------------------------------------------------------
# The virtual cell's rendered laser images (lens, PSF, shot noise, speckle, shadows).


def _cell_frame(speckle: bool):
    vc = pytest.importorskip("scanner.virtual_cell.capture")
    from dataclasses import replace

    from scanner.virtual_cell.cell import load_cell
    from scanner.virtual_cell.poses import sweep_poses

    cell = load_cell("modern")
    if not speckle:
        cell = replace(cell, laser=replace(cell.laser, speckle_contrast=0.0))
    base_from_cam, _ = sweep_poses(cell, 400)
    img, truth = vc.render_laser_image(cell, base_from_cam[200], np.random.default_rng(200))
    return img, truth.uv, np.asarray(truth.surface_ids, dtype=object)[truth.surface]


def _cell_errors(profile: StripeProfile, uv_true: np.ndarray):
    """Along-line error against the true centre curve, and the distance to it."""
    from scanner.virtual_cell.truth import along_line_errors

    return along_line_errors(profile.uv, profile.orientation, uv_true)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["fast", "precise"])
def test_virtual_cell_frame_without_speckle(mode):
    img, uv_true, surface = _cell_frame(speckle=False)
    p = extract_stripe(img, mode=mode, orientation="auto")
    err, dist, nearest, ok = _cell_errors(p, uv_true)
    clean = p.flags == 0
    assert np.all(dist[clean] < 1.0)  # no false points among the unflagged ones
    table = clean & ok & (surface[nearest] == "table")
    assert np.count_nonzero(table) > 500
    assert np.sqrt(np.mean(err[table] ** 2)) < 0.035
    assert abs(np.mean(err[table])) < 0.01
    # The plate is bright enough to saturate: its interior still lands within 0.03 px.
    # Interior of the top: 15 lines away from the plate's ends. The box's lit sides (about 11
    # lines here) run along the scan lines, and at their corner with the top the PSF blends
    # the two faces: no single centre is right there.
    on_plate = surface == "plate"
    b = 0 if p.orientation == "cols" else 1
    lo, hi = uv_true[on_plate, b].min() + 15, uv_true[on_plate, b].max() - 15
    inner = (p.uv[:, b] > lo) & (p.uv[:, b] < hi)
    unflagged_but_saturation = (p.flags & ~np.uint8(StripeFlag.SATURATED)) == 0
    plate = ok & (surface[nearest] == "plate") & inner & unflagged_but_saturation
    assert np.count_nonzero(p.flags[plate] & StripeFlag.SATURATED) > 50
    assert np.sqrt(np.mean(err[plate] ** 2)) < 0.03


@pytest.mark.slow
def test_virtual_cell_frame_with_speckle_is_speckle_limited():
    img, uv_true, surface = _cell_frame(speckle=True)
    p = extract_stripe(img, mode="fast", orientation="auto")
    err, dist, nearest, ok = _cell_errors(p, uv_true)
    clean = p.flags == 0
    assert np.all(dist[clean] < 1.5)
    table = clean & ok & (surface[nearest] == "table")
    # Speckle (contrast 0.25) moves the centres by ~0.1 px, correlated along the stripe.
    assert np.sqrt(np.mean(err[table] ** 2)) < 0.15


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["fast", "precise"])
def test_stretch_ends_carry_the_mixed_pixels_and_are_flagged(mode):
    """On sweep frames of the virtual cell (a plate, a bar, spheres on the table), the
    points the flag marks lie where the stripe is cut, and their error against the truth is
    several times that of the clean points."""
    vc = pytest.importorskip("scanner.virtual_cell.capture")
    from scanner.virtual_cell.cell import load_cell
    from scanner.virtual_cell.poses import sweep_poses

    cell = load_cell("modern")
    base_from_cam, _ = sweep_poses(cell, 400)
    errs: dict[str, list[np.ndarray]] = {"end": [], "clean": []}
    for i in (100, 130, 160, 200, 230, 260, 290):
        img, truth = vc.render_laser_image(cell, base_from_cam[i], np.random.default_rng(i))
        p = extract_stripe(img, mode=mode, orientation="auto", end_lines=3)
        err, dist, _, ok = _cell_errors(p, truth.uv)
        ok &= dist < 2.0
        end = (p.flags & StripeFlag.STRETCH_END) != 0
        errs["end"].append(err[ok & (p.flags == StripeFlag.STRETCH_END)])
        errs["clean"].append(err[ok & (p.flags == 0)])
        assert 0 < end.sum() < 0.05 * len(p)  # a few lines at each cut, not the stripe
    rms = {k: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in errs.items()}
    n_end = sum(len(v) for v in errs["end"])
    assert n_end > 40
    # (0.43 px against 0.11 px in both modes)
    assert rms["end"] > 2.0 * rms["clean"], (rms, n_end)


def test_stretch_end_flag_marks_the_lines_at_a_depth_jump_only():
    # One stripe jumping 60 px at line 120 (a depth step), a one-line dropout at line 60, and
    # the image's first and last lines (the stripe goes on outside: no end there).
    segs = [
        StripeSegment((0, 60), (150.0, 0.05), amplitude=170.0),
        StripeSegment((61, 120), (150.0, 0.05), amplitude=170.0),
        StripeSegment((120, 240), (210.0, 0.05), amplitude=170.0),
    ]
    img, _ = render_stripes(SHAPE, segs, noise=1.0, seed=4)
    for mode in ("fast", "precise"):
        p = extract_stripe(img, mode=mode, orientation="rows", end_lines=3)
        end = (p.flags & StripeFlag.STRETCH_END) != 0
        assert sorted(p.line[end].tolist()) == [117, 118, 119, 120, 121, 122]
        p0 = extract_stripe(img, mode=mode, orientation="rows")  # off by default
        assert not np.any(p0.flags & StripeFlag.STRETCH_END)
        p5 = extract_stripe(img, mode=mode, orientation="rows", end_lines=5)
        assert np.count_nonzero(p5.flags & StripeFlag.STRETCH_END) == 10
    # A second stripe sharing lines 30-89 (several peaks per line: runs by linking).
    segs.append(StripeSegment((30, 90), (280.0, 0.0), amplitude=150.0))
    img, _ = render_stripes(SHAPE, segs, noise=1.0, seed=4)
    p = extract_stripe(img, mode="fast", orientation="rows", end_lines=3)
    end = (p.flags & StripeFlag.STRETCH_END) != 0
    second = p.u > 250
    assert sorted(p.line[end & ~second].tolist()) == [117, 118, 119, 120, 121, 122]
    assert sorted(p.line[end & second].tolist()) == [30, 31, 32, 87, 88, 89]
    with pytest.raises(ValueError, match="end_lines"):
        StripeOptions(end_lines=-1)


def test_stretch_end_flag_is_the_same_with_one_or_several_peaks_per_line():
    """A stray peak beside the stripe, and a dropout at the image's first line, are bridged
    alike whether the frame holds one peak per line or several (found by review)."""
    from scanner.stripe.peaks import _stretch_ends
    from scanner.stripe.profile import _Peaks

    line = np.arange(1, 240)  # line 0 dropped by noise
    pos = 155.0 + 0.05 * line
    pos[99] = 40.0  # line 100: a stray peak far from the stripe
    z = np.zeros(line.size)
    one = _Peaks(line, pos, z, z, z, np.zeros(line.size, np.uint8), z)
    ends_one = _stretch_ends(one, 3.0, 240, 3)
    assert line[ends_one].tolist() == [100]  # the stray peak alone, the stripe unbroken
    # The same with a second stripe on lines 0-19 (several peaks per line there).
    extra = np.arange(20)
    two = _Peaks.concat(
        [
            one,
            _Peaks(
                extra, 280.0 + 0 * extra, *(np.zeros(20),) * 3, np.zeros(20, np.uint8), np.zeros(20)
            ),
        ]
    )
    ends_two = _stretch_ends(two, 3.0, 240, 3)
    assert ends_two[: line.size].tolist() == ends_one.tolist()
    assert two.line[ends_two][two.pos[ends_two] > 250].tolist() == [17, 18, 19]


@pytest.mark.parametrize("background", [0.0, 60.0, 120.0])
def test_precise_mode_does_not_depend_on_the_background_level(background):
    # Sampled and truncated, the derivative kernels do not sum to zero: a uniform background
    # leaked into the gradient and moved the centres (0.021 px RMS at 120 grey levels).
    errs = []
    for seed in range(3):
        seg = StripeSegment((0, 240), (140.3 + 7.1 * seed, 0.21, -2e-4), amplitude=120.0)
        img, ((lines, pos),) = render_stripes(
            SHAPE, [seg], noise=0.3, background=background, seed=seed
        )
        p = extract_stripe(img, mode="precise", orientation="rows")
        errs.append(_errors(p, lines, pos))
    e = np.concatenate(errs)
    assert np.sqrt(np.nanmean(e**2)) < 0.006


@pytest.mark.parametrize("curvature", [0.01, 0.02])
def test_precise_mode_corrects_the_smoothing_bias_of_curved_stripes(curvature):
    # pos(line) = 150 + k (line - 120)^2: apex at line 120, radius 1 / (2 k) pixels.
    k = curvature / 2
    seg = StripeSegment((0, 240), (150 + k * 120**2, -2 * k * 120, k), amplitude=170, sigma_px=1.3)
    img, ((lines, pos),) = render_stripes((240, 320), [seg], noise=0.3, seed=1)
    p = extract_stripe(img, mode="precise", orientation="rows")
    truth = np.full(240, np.nan)
    truth[lines] = pos
    err = (p.u - truth[p.line])[np.abs(p.line - 120) < 20]
    # Uncorrected, Gaussian smoothing moves the ridge by ~sigma^2 pos'' / 2 (0.009-0.02 px).
    assert abs(np.mean(err)) < 0.004


# --------------------------------------------------------------------------------------------
# The vectorised common case against the general per-peak measurement.


def test_batched_window_measurement_matches_the_general_one():
    from scanner.stripe.fast import _measure, _measure_many

    # Ordinary peaks, peaks at both borders, saturated ones and two maxima in one window.
    segs = [
        StripeSegment((0, 240), (150.0, 0.1), amplitude=170.0),
        StripeSegment((0, 40), (1.0, 0.0), amplitude=150.0),
        StripeSegment((40, 80), (318.2, 0.0), amplitude=150.0),
        StripeSegment((80, 120), (60.0, 0.0), amplitude=900.0),
        StripeSegment((120, 160), (64.0, 0.0), amplitude=160.0),
        StripeSegment((120, 160), (69.0, 0.0), amplitude=150.0),
    ]
    for dtype, scale in ((np.uint8, 1.0), (np.uint16, 64.0)):
        img, _ = render_stripes(
            SHAPE,
            [StripeSegment(s.lines, s.coeffs, s.amplitude * scale, s.sigma_px) for s in segs],
            noise=1.0 * scale,
            seed=12,
            dtype=dtype,
            full_scale=255.0 * scale,
        )
        lines = np.repeat(np.arange(SHAPE[0]), 2)
        cols = np.stack([np.argmax(img[:, :100], axis=1), 100 + np.argmax(img[:, 100:], axis=1)])
        cols = cols.T.reshape(-1)
        sat = 255.0 * scale
        mask = np.ones(SHAPE, np.uint8)
        # The same "wider than usual" width (the default is the median over the windows
        # inside the image, the general function's over all of its batch).
        got = _measure_many(img, lines, cols, 4, sat, clear=mask, typical=3.5)
        want, _ = _measure(img, lines, cols, 4, sat, typical=3.5)
        default = _measure_many(img, lines, cols, 4, sat)
        assert np.mean(default.flags == want.flags) > 0.99
        np.testing.assert_array_equal(got.line, want.line)
        np.testing.assert_array_equal(got.flags, want.flags)
        for name in ("peak", "slope"):
            np.testing.assert_allclose(getattr(got, name), getattr(want, name), atol=1e-3 * scale)
        real = want.contrast > 20 * scale  # not the noise maxima of the lines' empty halves
        assert np.count_nonzero(real) > 300
        np.testing.assert_allclose(got.contrast[real], want.contrast[real], atol=1e-3 * scale)
        np.testing.assert_allclose(got.pos[real], want.pos[real], atol=1e-5)
        np.testing.assert_allclose(got.width[real], want.width[real], atol=1e-4)
        assert np.any(want.flags & StripeFlag.BORDER)
        assert np.any(want.flags & StripeFlag.SATURATED)
        assert np.any(want.flags & StripeFlag.AMBIGUOUS)
        # Exactly each window (clipped to the image) was cleared.
        expect = np.ones(SHAPE, np.uint8)
        for ln, c in zip(lines, cols, strict=True):
            expect[ln, max(c - 4, 0) : c + 5] = 0
        np.testing.assert_array_equal(mask, expect)


def test_a_second_stripe_just_outside_the_window_is_found():
    # The window is 4 px either side: a stripe 9 px away is another peak on every line.
    a = StripeSegment((0, SHAPE[0]), (100.0, 0.0), amplitude=170.0, sigma_px=1.0)
    b = StripeSegment((0, SHAPE[0]), (109.0, 0.0), amplitude=150.0, sigma_px=1.0)
    img, _ = render_stripes(SHAPE, [a, b], noise=1.0, seed=13)
    p = extract_stripe(img, mode="fast", orientation="rows", half_window_px=4)
    assert np.all(np.bincount(p.line, minlength=SHAPE[0]) == 2)


def test_odd_sizes_read_only_and_float_frames_give_the_same_profile():
    img, truth = _single(seed=14)
    ref = extract_stripe(img, mode="precise", orientation="rows")
    ro = img.copy()
    ro.setflags(write=False)
    for other in (ro, img.astype(np.float32), np.asfortranarray(img)):
        p = extract_stripe(other, mode="precise", orientation="rows")
        np.testing.assert_allclose(p.u, ref.u, atol=1e-5)
        np.testing.assert_array_equal(p.flags, ref.flags)
    # Narrower than a window, and a few lines only: still measured (the general path).
    narrow = np.ascontiguousarray(img[:9, 134:146])
    for mode in ("fast", "precise"):
        p = extract_stripe(narrow, mode=mode, orientation="rows", half_window_px=4, noise=1.0)
        err = _errors(p, truth[0][0], truth[0][1] - 134)
        assert len(p) == 9
        assert np.all(np.abs(err) < 0.2)


# --------------------------------------------------------------------------------------------
# The noise and window estimates of the default call, against their plain NumPy definitions.


def test_median_of_eight_bit_values_is_the_lower_middle_one():
    from scanner.stripe.estimates import _median

    rng = np.random.default_rng(15)
    big = rng.integers(0, 12, size=(40, 1023), dtype=np.uint8)  # the histogram path
    for values in (big, big.reshape(-1), big[::3, ::2], big[:3, :5], big.reshape(-1)[:4096]):
        flat = np.sort(values.reshape(-1))
        assert _median(values) == float(flat[(flat.size - 1) // 2])


@pytest.mark.parametrize(("sigma", "last_line"), [(1.0, 240), (1.6, 224), (2.5, 240)])
def test_auto_half_window_is_the_median_width_as_numpy_takes_it(sigma, last_line):
    from scanner.stripe.estimates import auto_half_window
    from scanner.stripe.fast import _measure_many
    from scanner.stripe.profile import _FWHM_PER_SIGMA

    # 15 or 14 sampled lines on the stripe: an odd and an even count of widths.
    seg = StripeSegment((0, last_line), (140.3, 0.21), amplitude=170.0, sigma_px=sigma)
    img, _ = render_stripes(SHAPE, [seg], noise=1.0, seed=16)
    noise = 1.0
    lines = np.arange(0, SHAPE[0], 16)
    m = _measure_many(img, lines, img[::16].argmax(axis=1), 10, np.inf, typical=np.inf)
    widths = m.width[m.contrast > 10.0 * noise]
    assert widths.size in (14, 15)
    want = int(np.clip(np.rint(2.7 * float(np.median(widths)) / _FWHM_PER_SIGMA), 3, 20))
    assert auto_half_window(img, noise) == want


def test_a_faint_narrow_stripe_gets_the_narrowest_window():
    # Frame 22 of benchmarks/bench_stripe_domain.py: a 0.72 px sigma stripe 11 noise sigmas
    # high on a shaded background. Its lines' windowed second moments scatter from 0 to 10 px
    # (the noise's, not the stripe's): the window they gave (7 px) let noise peaks 3-16 px off
    # the stripe become 69 trusted points.
    c = draw_stripe_conditions(np.random.default_rng([0, 22]))
    assert c.sigma_px < 0.75 and 10 < c.snr < 12
    image, lines, pos = render_stripe_conditions(c, seed=22)
    work = np.ascontiguousarray(image.T if c.orientation == "cols" else image)
    flat = flatten_background(work, 255.0)
    assert auto_half_window(flat, estimate_noise(flat)) == 3
    p = extract_stripe(image, orientation=c.orientation)
    truth = np.full(max(c.shape) + 1, np.nan)
    truth[lines] = pos
    err = (p.u if c.orientation == "rows" else p.v) - truth[p.line]
    assert np.count_nonzero((p.flags == 0) & ~(np.abs(err) < 3.0)) == 0
    assert np.isin(lines, p.line[np.abs(err) < 3.0]).mean() > 0.99
