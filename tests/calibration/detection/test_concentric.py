import cv2
import numpy as np
import pytest

from calibration.detection import concentric
from calibration.detection.concentric import detect_concentric
from calibration.detection.concentric_centre import HOUGH_LINES, Z_LINE, _climbed_centre
from calibration.detection.detect import detect_target
from calibration.detection.observations import TargetObservation
from calibration.symmetry import relabel
from scanner.core.conventions import transform_points
from tests.calibration.synth_concentric import demo_target, look_at_pose, render

SIZE = (800, 640)
K = np.array([[1300.0, 0.0, 405.0], [0.0, 1298.0, 318.0], [0.0, 0.0, 1.0]])


def project(T: np.ndarray, pts_t: np.ndarray) -> np.ndarray:
    pc = transform_points(T, pts_t)
    uv = pc @ K.T
    return uv[:, :2] / uv[:, 2:3]


def ring_radial_errors_mm(obs, T) -> np.ndarray:
    """Edge points back-projected onto the target plane: |X| - r, mm."""
    errs = []
    R, t = T[:3, :3], T[:3, 3]
    o = -R.T @ t
    for ring in obs.rings:
        rays = np.column_stack([ring.edge_points_px, np.ones(len(ring.edge_points_px))])
        d = (rays @ np.linalg.inv(K).T) @ R
        s = -o[2] / d[:, 2]
        X = o + s[:, None] * d
        errs.append(np.hypot(X[:, 0], X[:, 1]) - ring.radius_mm)
    return np.concatenate(errs)


def check_labelling(obs, T, tol_px: float) -> None:
    assert obs, obs.reason
    want = project(T, obs.points_target)
    err = np.linalg.norm(obs.points_px - want, axis=1)
    assert err.max() < tol_px, f"worst point {obs.point_names[int(np.argmax(err))]}: {err.max()}"
    target = demo_target()
    for name, p in target.named_points().items():
        if name in obs.named_px:
            assert np.linalg.norm(obs.named_px[name] - project(T, p[None])[0]) < tol_px


@pytest.mark.parametrize(
    ("tilt", "axis", "roll"),
    [(0.0, 0.0, 0.0), (25.0, 30.0, 100.0), (45.0, 200.0, -60.0), (40.0, 95.0, 170.0)],
)
def test_detects_and_labels_at_any_rotation_and_tilt(tilt, axis, roll):
    rng = np.random.default_rng(int(tilt * 10 + roll))
    T = look_at_pose(560.0, tilt, axis, roll)
    img = render(demo_target(), K, T, SIZE, rng, supersample=3)
    obs = detect_target(img, demo_target())
    check_labelling(obs, T, tol_px=0.05)
    assert len(obs.rings) == len(demo_target().ring_diameters_mm)
    err = ring_radial_errors_mm(obs, T)
    assert abs(np.mean(err)) < 0.003
    assert np.std(err) < 0.03  # 0.07 px at 2.3 px/mm: noise 0.01 of white, 8 bit
    assert {a.axis for a in obs.axis_points} == {"x", "y"}


def test_centre_is_pencil_centre_not_ellipse_centre():
    rng = np.random.default_rng(11)
    T = look_at_pose(520.0, 45.0, 0.0, 20.0)
    obs = detect_target(render(demo_target(), K, T, SIZE, rng, supersample=3), demo_target())
    assert obs, obs.reason
    truth = project(T, np.zeros((1, 3)))[0]
    assert np.linalg.norm(obs.center_px - truth) < 0.03
    c = obs.rings[-1].conic
    ellipse_centre = -np.linalg.solve(c[:2, :2], c[:2, 2])
    assert np.linalg.norm(ellipse_centre - truth) > 1.0


def test_vanishing_points_are_images_of_the_axis_directions():
    rng = np.random.default_rng(12)
    T = look_at_pose(560.0, 35.0, 60.0, 30.0)
    obs = detect_target(render(demo_target(), K, T, SIZE, rng, supersample=3), demo_target())
    assert obs, obs.reason
    for key, axis in (("p", 0), ("q", 1)):
        want = K @ T[:3, axis]
        got = obs.vanishing_points[key]
        angle = np.degrees(
            np.arccos(abs(got @ want) / (np.linalg.norm(got) * np.linalg.norm(want)))
        )
        assert angle < 0.01


def test_survives_laser_stripe_clutter_uneven_light_and_noise():
    rng = np.random.default_rng(13)
    T = look_at_pose(560.0, 30.0, 120.0, 45.0)
    img = render(
        demo_target(),
        K,
        T,
        SIZE,
        rng,
        noise=0.03,
        vignetting=0.6,
        blur_px=1.2,
        laser_line=(1.0, 0.35, -480.0),
        clutter=True,
        supersample=3,
    )
    obs = detect_concentric(img, demo_target())
    check_labelling(obs, T, tol_px=0.15)


def test_partly_outside_the_image():
    rng = np.random.default_rng(14)
    # Target centre near the left border: part of the rings leave the image, marker inside.
    T = look_at_pose(560.0, 20.0, 0.0, 0.0, offset=(-120.0, 0.0))
    obs = detect_target(render(demo_target(), K, T, SIZE, rng, supersample=3), demo_target())
    check_labelling(obs, T, tol_px=0.1)
    assert "B" not in obs.named_px  # B is outside


def test_hidden_marker_gives_a_labelling_up_to_symmetry_not_a_guess():
    rng = np.random.default_rng(15)
    T = look_at_pose(560.0, 20.0, 40.0, 10.0)
    img = render(demo_target(), K, T, SIZE, rng, supersample=3)
    m = project(T, np.array([[*demo_target().orientation_marker.center_mm, 0.0]]))[0]
    u0, v0 = int(m[0]), int(m[1])
    img[v0 - 20 : v0 + 21, u0 - 20 : u0 + 21] = np.median(img)  # paper over the disc
    obs = detect_target(img, demo_target())
    assert obs, obs.reason
    assert obs.labelling == "symmetry" and obs.marker_px is None
    # Exactly one quarter turn of the labelling is the truth; the points are right under it.
    fits = []
    for k in range(4):
        turned = relabel(obs, k)
        err = np.linalg.norm(turned.points_px - project(T, turned.points_target), axis=1)
        fits.append(err.max() < 0.15)
    assert sum(fits) == 1


def test_no_target_gives_a_reason():
    rng = np.random.default_rng(16)
    img = (rng.normal(0.7, 0.02, (480, 640)) * 255).astype(np.uint8)
    obs = detect_target(img, demo_target())
    assert not obs
    assert obs.reason
    assert obs.image_size == (640, 480)


def test_of_several_scales_the_refusal_that_got_furthest_is_reported(monkeypatch):
    # each closing kernel fails at another stage, in all eight passes (the second with rays
    # that may start at ring 1, the third with rings that may be fitted together, the fourth
    # and fifth with rays in bundles, the sixth from a centre moved to the most rings, the
    # seventh from the crossings of weaker Hough lines, the last with the crossings named
    # again): the user sees the most telling reason (two closing kernels for a 400 px image)
    stages = iter([(1, "no ring pencil found: 1 rings fitted"), (5, "diameter line not printed"),
                   (3, "too oblique"), (5, "as far, second"), (1, "third"), (2, "third, too"),
                   (4, "fourth"), (5, "fourth, as far"), (1, "fifth"), (5, "fifth, as far"),
                   (2, "sixth"), (5, "sixth, as far"), (1, "seventh"),
                   (5, "seventh, as far"), (3, "eighth"), (5, "eighth, as far"),
                   (1, "last sweep"), (5, "last sweep, as far")]
                  + [(1, "last sweep, later")] * 16)  # fmt: skip
    passes = []

    def fake(img, target, s, kernel, size, state):
        p = state.now
        passes.append(
            (p.ring0_hidden, p.joint, p.bundle_z_line, p.climb, p.wide, p.relabel, p.voted)
        )
        state.progress, reason = next(stages)
        return TargetObservation.failed(reason, size, "concentric_circles")

    monkeypatch.setattr(concentric, "_detect_with_kernel", fake)
    obs = detect_concentric(np.full((400, 400), 0.5), demo_target())
    assert not obs
    assert obs.reason == "diameter line not printed"
    single = [
        (False, False, 0.0, False, False, False, False),
        (True, False, 0.0, False, False, False, False),
        (False, True, 0.0, False, False, False, False),
    ]
    bundles = [
        (False, False, Z_LINE, False, False, False, False),
        (False, False, concentric.BUNDLE_Z_LINE, False, False, False, False),
    ]
    climbed, wide = (
        [(False, False, 0.0, True, False, False, False)],
        [(False, False, 0.0, False, True, False, False)],
    )
    named_again = [(False, False, 0.0, False, False, True, False)]
    # (the last sweep: no pass stopped at two rings, so the bundle-judged centres, then the
    # crossings named again around the other passes' centres, then the edges' voted centres:
    # as they are, their crossings named again, their rays from ring 1 named again)
    last = [
        (False, False, concentric.BUNDLE_Z_LINE, False, False, False, False),
        (True, False, 0.0, False, False, True, False),
        (False, False, 0.0, False, True, True, False),
        (False, False, 0.0, False, False, True, False),  # (around the bundle-judged centres)
        (True, False, 0.0, False, True, True, False),
        (True, False, 0.0, True, False, True, False),
        (False, False, 0.0, False, False, False, True),
        (False, False, 0.0, False, False, True, True),
        (True, False, 0.0, False, False, True, True),
    ]
    regular = single + bundles + climbed + wide + named_again
    assert passes == [p for p in regular + last for _ in range(2)]
    # a reason of a later pass that got further says where it comes from
    firsts = [(1, "first"), (2, "first, too")]
    stages = iter(firsts + [(3, "second"), (6, "marker not found")] + [(1, "later")] * 30)
    obs = detect_concentric(np.full((400, 400), 0.5), demo_target())
    assert obs.reason == "marker not found (rays labelled from ring 1)"
    stages = iter(firsts + [(2, "second"), (1, "second, too"), (4, "too oblique")] + [(1, "")] * 29)
    obs = detect_concentric(np.full((400, 400), 0.5), demo_target())
    assert obs.reason == "too oblique (rings fitted together)"
    stages = iter(firsts + [(1, "later")] * 7 + [(3, "1 rings measured")] + [(1, "")] * 24)
    obs = detect_concentric(np.full((400, 400), 0.5), demo_target())
    assert obs.reason == "1 rings measured (rays in bundles)"
    stages = iter(firsts + [(1, "later")] * 9 + [(4, "2 rings measured")] + [(1, "")] * 22)
    obs = detect_concentric(np.full((400, 400), 0.5), demo_target())
    assert obs.reason == "2 rings measured (centre moved to the most rings)"
    stages = iter(firsts + [(1, "later")] * 11 + [(3, "1 rings measured")] + [(1, "")] * 20)
    obs = detect_concentric(np.full((400, 400), 0.5), demo_target())
    assert obs.reason == "1 rings measured (weaker Hough lines tried)"
    stages = iter(firsts + [(1, "later")] * 13 + [(3, "0 rings measured")] + [(1, "")] * 18)
    obs = detect_concentric(np.full((400, 400), 0.5), demo_target())
    assert obs.reason == "0 rings measured (crossings named again)"


def test_the_last_sweep_repeats_two_ring_passes_and_wants_the_marker(monkeypatch):
    # The third pass (rings fitted together) stops at two rings at the first scale: the last
    # sweep runs it again with the missing rings measured, then the bundle-judged centres and
    # the crossings named again; a detection there without the marker is refused, one with it
    # is returned
    calls = []

    def fake(img, target, s, kernel, size, state, found="symmetry"):
        p = state.now
        calls.append((p.joint, p.bundle_centre, state.recovery.enabled, p.note, kernel))
        state.progress = 1
        if p.joint and not state.recovery.enabled and len(calls) == 5:
            state.recovery.wanted = True
        if state.recovery.enabled and p.bundle_centre and kernel == 5:
            state.progress = 6  # (a detection passed every stage)
            return TargetObservation(ok=True, reason="", image_size=size, labelling=found)
        return TargetObservation.failed("refused", size, "concentric_circles")

    monkeypatch.setattr(concentric, "_detect_with_kernel", fake)
    obs = detect_concentric(np.full((400, 400), 0.5), demo_target())
    assert not obs
    assert "last sweep without its orientation marker" in obs.reason
    assert [c[2] for c in calls] == [False] * 16 + [True] * 19
    assert calls[4][:3] == (True, False, False)  # the third pass's first scale
    assert calls[16] == (True, False, True, "missing rings measured from two", calls[4][4])
    # (the bundle-judged centres, and their crossings named again, refused without the marker)
    assert [c[1] for c in calls[17:]] == [True, True] + [False] * 4 + [True, True] + [False] * 10
    assert calls[17][3] == "centre judged by bundles of rays"
    calls.clear()
    monkeypatch.setattr(concentric, "_detect_with_kernel", lambda *a: fake(*a, found="unique"))
    assert detect_concentric(np.full((400, 400), 0.5), demo_target())
    assert len(calls) == 19


def test_a_centre_off_the_rings_climbs_onto_the_diameter_and_one_in_noise_stays():
    # The sixth pass's candidate: on a steep target no crossing of two Hough lines may be at
    # O. A map in the coarse stage's units (a printed line over Z_LINE), one diameter only.
    rng = np.random.default_rng(23)
    radii = np.array([10.0, 20.0, 30.0, 40.0])
    z = np.zeros((300, 400))
    for r in 2.2 * radii:
        cv2.ellipse(z, (190, 160), (int(r), int(0.45 * r)), 20.0, 0.0, 360.0, 1.0, 2)
    cv2.line(z, (0, 91), (399, 237), 1.0, 2)  # the long diameter, through (190, 160)
    # (never negative: that marks hidden print, where rays stop)
    z = np.maximum(3.0 * cv2.GaussianBlur(z, (0, 0), 1.0) + rng.normal(0.0, 0.15, z.shape), 0)
    axis_angles = [np.radians(a) for a in (20.0, 200.0, 110.0, 290.0)]
    # 8 px off the diameter, as a crossing of it with a clutter line would be
    start = (np.array([187.0, 168.0]), (np.zeros(3), np.zeros(3)), axis_angles)
    c, _, angles = _climbed_centre(z, start, radii, 8.0, False)
    np.testing.assert_array_equal(angles, np.radians([20.0, 200.0, 110.0, 290.0]))
    # Onto the diameter, inside the innermost ring (22 px along it): along the diameter a
    # shift is nearly a projectivity of the radii, and the ring conics' pencil pins O later.
    along = np.array([np.cos(np.radians(20.0)), np.sin(np.radians(20.0))])
    off = c - [190.0, 160.0]
    assert abs(off @ [-along[1], along[0]]) < 2.0 and abs(off @ along) < 11.0, c

    def support(p):
        return concentric._label_rays(z, p, radii, Z_LINE, axis_angles)[1]

    assert support(c) > 1.3 * support(start[0]) > 0
    # noise alone: no crossing in order anywhere near, the candidate stays where it was
    # (among clutter lines it moves; the pencil, the fine stage and the marker refuse it
    # there: test_randomised_detection's target-free views reach this pass)
    noise = np.maximum(rng.normal(0.0, 0.15, z.shape), 0.0)
    c, _, _ = _climbed_centre(noise, start, radii, 8.0, False)
    np.testing.assert_array_equal(c, start[0])


def test_the_first_scales_darkness_floor_holds_at_the_smaller_scales(monkeypatch):
    # A narrow closing follows the noise and leaves most of the paper's darkness at 0: the
    # smaller scales keep the floor the first (widest) one learnt from the paper.
    calls = []
    real = concentric._threshold_map

    def spy(d, bg, tile_px, hidden=None, floor=None, lit=None):
        out = real(d, bg, tile_px, hidden, floor, lit)
        calls.append((floor, out[1]))
        return out

    monkeypatch.setattr(concentric, "_threshold_map", spy)
    rng = np.random.default_rng(2)
    noise = np.clip(rng.normal(150, 3, (480, 640)), 0, 255).astype(np.uint8)
    assert not detect_concentric(noise, demo_target())
    assert len(calls) == 3  # three closing scales (the second pass reuses their maps)
    assert calls[0][0] is None
    assert all(given == calls[0][1] and used == given for given, used in calls[1:])


def test_too_oblique_is_refused():
    rng = np.random.default_rng(17)
    T = look_at_pose(560.0, 75.0, 0.0, 0.0)
    obs = detect_target(render(demo_target(), K, T, SIZE, rng, supersample=3), demo_target())
    assert not obs


def test_passes_labelling_from_ring_0_search_each_scales_centres_once(monkeypatch):
    # The third to sixth passes label the candidates' rays as the first does: they take its
    # chosen centres instead of searching the line crossings again (the sixth climbs from
    # them).
    # The weaker lines' pass searches only the crossings the others did not try (a line after
    # the first HOUGH_LINES in each pair).
    calls = []
    real = concentric._best_centre

    def spy(z_rays, lines, radii, size, ring0_hidden, first_new=0, *bundles):
        (bundled if bundles else calls).append((ring0_hidden, first_new, len(lines)))
        return real(z_rays, lines, radii, size, ring0_hidden, first_new, *bundles)

    bundled = []

    monkeypatch.setattr(concentric, "_best_centre", spy)
    rng = np.random.default_rng(17)
    T = look_at_pose(560.0, 75.0, 0.0, 0.0)
    assert not detect_target(render(demo_target(), K, T, SIZE, rng, supersample=3), demo_target())
    first = [c for c in calls if c[1] == 0]
    assert all(n <= HOUGH_LINES for _, _, n in first)
    from_ring_1 = sum(r for r, _, _ in first)
    assert from_ring_1 > 0  # the second pass searched every scale with lines again
    assert len(first) - from_ring_1 == from_ring_1
    wide = [(r, f, n) for r, f, n in calls if f]
    assert wide and all(f == HOUGH_LINES and n > f for r, f, n in wide)
    # (from ring 0 in the seventh pass, from ring 1 in the last sweep: once a scale each)
    assert 2 * sum(r for r, _, _ in wide) == len(wide)
    # the crossings judged by bundles of rays (the last regular pass where it has no centre,
    # the last sweep): searched once a scale, from ring 0, over the first lines
    assert 0 < len(bundled) <= len(first) - from_ring_1
    assert all(not r and f == 0 for r, f, _ in bundled)


@pytest.mark.slow
def test_virtual_cell_views_detected_labelled_and_calibrated():
    from calibration.intrinsics import calibrate_intrinsics
    from scanner.virtual_cell import load_cell, render_target_image
    from scanner.virtual_cell.poses import hand_held_view

    cell = load_cell("modern")
    cam, spec = cell.camera_model(), cell.target_spec()
    rng = np.random.default_rng(21)
    obs, truths = [], []
    for i in range(8):
        T = hand_held_view(cell, rng)
        img = render_target_image(cell, T, np.random.default_rng(100 + i))
        ob = detect_target(img, spec)
        if ob:
            # Labelling: A, C where the true camera sees them (within the distortion-limited
            # accuracy of the crossings: line and conic fits of distorted curves, worst in the
            # views that reach the image's corners; a wrong label is off by tens of pixels).
            for name in ("A", "C"):
                if name in ob.named_px:
                    p = spec.named_points()[name]
                    want = cam.project(transform_points(T, p[None]))[0]
                    assert np.linalg.norm(ob.named_px[name] - want) < 1.0
        obs.append(ob)
        truths.append(T)
    assert sum(map(bool, obs)) >= 6, [o.reason for o in obs if not o]
    res = calibrate_intrinsics(obs, (cam.width, cam.height))
    assert abs(res.fx / cam.K[0, 0] - 1) < 2e-4
    assert abs(res.fy / cam.K[1, 1] - 1) < 2e-4
