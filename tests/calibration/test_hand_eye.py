"""Hand-eye: simulate posed views with a known flange_from_cam, solve, compare."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.extrinsics import project_target
from calibration.hand_eye import (
    PosedView,
    StripePointView,
    calibrate_hand_eye,
    check_robot_motion,
    paper_hand_eye,
)
from scanner.core.camera import CameraModel
from scanner.core.conventions import (
    RotationConvention,
    angle_between_rotations_deg,
    invert_transform,
    make_transform,
    transform_points,
)
from scanner.formats.session import Frame, read_session, write_session
from tests.calibration import _synthetic as S


def _errors(x: np.ndarray) -> tuple[float, float]:
    return (
        angle_between_rotations_deg(x, S.FLANGE_FROM_CAM),
        float(np.linalg.norm(x[:3, 3] - S.FLANGE_FROM_CAM[:3, 3])),
    )


def test_default_recovers_truth_and_beats_every_closed_form():
    rng = np.random.default_rng(0)
    views, cam = S.posed_views(12, rng, noise_px=0.1)
    # Image noise only: the image-residual cost is the maximum-likelihood one here.
    res = calibrate_hand_eye(views, cam, cost="image")
    assert res, res.reason
    dr, dt = _errors(res.flange_from_cam)
    # 0.1 px noise on 81 points x 12 views: a few thousandths of a degree, hundredths of a mm.
    assert dr < 0.02
    assert dt < 0.15
    assert abs(res.rms_px - 0.1 * np.sqrt(2)) < 0.02
    assert res.rms_px <= min(res.candidates.values()) + 1e-9
    # The reported uncertainty is honest: the error is within a few sigma.
    assert dt < 5 * np.linalg.norm(res.std_translation_mm)
    assert np.all(res.target_spread_mm < 0.2)
    assert len(res.per_pose) == 12
    for method in res.candidates:
        closed = calibrate_hand_eye(views, cam, method)
        assert closed.rms_px >= res.rms_px
    # The robot-space cost on the same data lands on the same solution within its noise
    # (a little less efficient here: it finds a small repeatability in the pose noise).
    robot = calibrate_hand_eye(views, cam, cost="robot")
    assert _errors(robot.flange_from_cam)[0] < 2 * np.linalg.norm(robot.std_rotation_deg)
    assert _errors(robot.flange_from_cam)[1] < 0.15


def _with_robot_error(
    views: list[PosedView], rng: np.random.Generator, sigma_deg: float, sigma_mm: float
) -> list[PosedView]:
    """The same images, but reported robot poses off by a repeatability error (flange frame):
    the robot actually stood at the rendered pose and reports ``actual @ inv(error)``."""
    out = []
    for v in views:
        err = make_transform(
            Rotation.from_rotvec(np.radians(sigma_deg) * rng.standard_normal(3)),
            sigma_mm * rng.standard_normal(3),
        )
        out.append(PosedView(v.frame_id, v.base_from_flange @ err, v.points_px, v.points_target))
    return out


def test_auto_cost_uses_the_robot_cost_for_repeatability_and_the_image_cost_for_pose_errors():
    rng = np.random.default_rng(7)
    views, cam = S.posed_views(20, rng, noise_px=0.03)
    random_miss = _with_robot_error(views, rng, 0.005, 0.02)
    auto = calibrate_hand_eye(random_miss, cam)  # "auto" is the default
    assert auto.robot_test_p > 0.01
    assert "robot errors" in auto.method
    alone = calibrate_hand_eye(random_miss, cam, cost="robot")
    assert np.allclose(auto.flange_from_cam, alone.flange_from_cam, atol=1e-9)
    # A robot whose misses follow its pose (as absolute-accuracy errors do): up to ~0.05 deg
    # and 0.3 mm, growing with the flange's distance from the middle of the poses.
    positions = np.stack([v.base_from_flange[:3, 3] for v in views])
    scaled = []
    for v, position in zip(views, positions):
        u = (position - positions.mean(axis=0)) / 200.0
        miss = make_transform(
            Rotation.from_rotvec(np.radians(0.05) * np.array([u[1], -u[0], 0.0])),
            0.3 * np.array([u[0], u[1], 0.0]),
        )
        scaled.append(
            PosedView(v.frame_id, v.base_from_flange @ miss, v.points_px, v.points_target)
        )
    auto = calibrate_hand_eye(scaled, cam)
    assert auto.robot_test_p < 1e-3
    assert "image residuals" in auto.method
    assert any("absolute-accuracy" in w for w in auto.warnings)
    alone = calibrate_hand_eye(scaled, cam, cost="image")
    assert np.allclose(auto.flange_from_cam, alone.flange_from_cam, atol=1e-9)
    # What the image cost is for then: the whole chain reprojects better, the target scatters less.
    robot = calibrate_hand_eye(scaled, cam, cost="robot")
    assert auto.rms_px < robot.rms_px
    assert np.linalg.norm(auto.target_spread_mm) < np.linalg.norm(robot.target_spread_mm)
    quality = auto.quality()
    assert quality["robot_test_p"] == auto.robot_test_p and quality["held_out_rms_px"] > 0
    with pytest.raises(ValueError, match="cost"):
        calibrate_hand_eye(views, cam, cost="pose")


def test_held_out_rms_matches_refitting_without_each_view():
    # The linearised leave-one-view-out RMS against honest refits on the other views (they
    # also re-estimate the repeatability, which the linearisation holds: within 10 %).
    rng = np.random.default_rng(11)
    views, cam = S.posed_views(8, rng, noise_px=0.05)
    views = _with_robot_error(views, rng, 0.01, 0.05)
    for cost in ("robot", "image"):
        full = calibrate_hand_eye(views, cam, cost=cost)
        squares, count = 0.0, 0
        for k, v in enumerate(views):
            rest = calibrate_hand_eye(views[:k] + views[k + 1 :], cam, cost=cost)
            cam_from_target = (
                invert_transform(v.base_from_flange @ rest.flange_from_cam) @ rest.base_from_target
            )
            uv = cam.project(transform_points(cam_from_target, v.points_target))
            squares += float(np.sum((uv - v.points_px) ** 2))
            count += len(uv)
        refit = np.sqrt(squares / count)
        assert abs(full.held_out_rms_px - refit) < 0.1 * refit, cost
        assert full.held_out_rms_px > full.rms_px


def test_robot_cost_beats_image_cost_when_the_robot_repeatability_dominates():
    errors = {"robot": [], "image": [], "tsai": []}
    repeat = []
    for seed in range(4):
        rng = np.random.default_rng(100 + seed)
        views, cam = S.posed_views(20, rng, noise_px=0.03)
        views = _with_robot_error(views, rng, 0.005, 0.02)
        for key, kwargs in (
            ("robot", {"cost": "robot"}),
            ("image", {"cost": "image"}),
            ("tsai", {"method": "tsai"}),
        ):
            res = calibrate_hand_eye(views, cam, **kwargs)
            assert res, res.reason
            errors[key].append(_errors(res.flange_from_cam))
        repeat.append(calibrate_hand_eye(views, cam, cost="robot").robot_repeatability)
    rms = {k: np.sqrt(np.mean(np.square(v), axis=0)) for k, v in errors.items()}
    # Rotation (deg) and translation (mm): the robot-space adjustment is the best of the three.
    assert rms["robot"][0] <= min(rms["image"][0], rms["tsai"][0])
    # Translation: well ahead of the image cost, level with Tsai (whose translation step is
    # a linear least squares that is nearly optimal here): within 10 % of it over 4 seeds.
    assert rms["robot"][1] <= min(0.5 * rms["image"][1], 1.1 * rms["tsai"][1])
    # 20 views, 0.005 deg and 0.02 mm per axis of repeatability: about 0.006 deg, 0.03 mm.
    assert rms["robot"][0] < 0.01 and rms["robot"][1] < 0.05
    # The repeatability it estimates is the one simulated (per axis, one sigma).
    rot = np.mean([r["rotation_deg"] for r in repeat])
    trans = np.mean([r["translation_mm"] for r in repeat])
    assert 0.0035 < rot < 0.0065 and 0.014 < trans < 0.026


def test_robot_repeatability_leaves_the_views_own_pose_noise_out():
    # Target poses from an adjustment (as the concentric target's are: the intrinsics'
    # adjustment over every ring edge), with their features projected from that pose, so PnP
    # sees no residual. The pose covariance the view carries goes into the misses; without it
    # the pose noise (about 0.003 deg, 0.015-0.03 mm: 0.03 mm per axis at the flange) would
    # be taken for the robot's 0.02 mm.
    # Correlated, unequal turns: the misses see them only through the right convention.
    a = np.array([[1.2, 0.0, 0.0], [0.6, 0.5, 0.0], [-0.3, 0.4, 0.8]]) * np.radians(0.003)
    cov = np.zeros((6, 6))
    cov[:3, :3] = a @ a.T
    cov[3:, 3:] = np.diag([0.015**2, 0.015**2, 0.03**2])
    given, ignored = [], []
    for seed in range(4):
        rng = np.random.default_rng(300 + seed)
        views, cam = S.posed_views(30, rng, noise_px=0.0)
        reported = _with_robot_error(views, rng, 0.005, 0.02)
        with_cov, without = [], []
        for v, r in zip(views, reported):
            ct = invert_transform(v.base_from_flange @ S.FLANGE_FROM_CAM) @ S.BASE_FROM_TARGET
            d = rng.multivariate_normal(np.zeros(6), cov)
            noisy = make_transform(
                Rotation.from_rotvec(d[:3]) * Rotation.from_matrix(ct[:3, :3]), ct[:3, 3] + d[3:]
            )
            px = project_target(cam, noisy, v.points_target)
            with_cov.append(
                PosedView(v.frame_id, r.base_from_flange, px, v.points_target, noisy, cov)
            )
            without.append(PosedView(v.frame_id, r.base_from_flange, px, v.points_target, noisy))
        given.append(calibrate_hand_eye(with_cov, cam, cost="robot").robot_repeatability)
        ignored.append(calibrate_hand_eye(without, cam, cost="robot").robot_repeatability)
    trans = np.mean([r["translation_mm"] for r in given])
    rot = np.mean([r["rotation_deg"] for r in given])
    # One 30-view estimate spreads by about 17 % (0.0035 mm); over seeds 300-323 the mean is
    # 0.0202 +- 0.0007 mm and 0.00505 +- 0.00009 deg, so unbiased; these four give 0.0222.
    # Turns applied on the wrong side give 0.028 mm at these four seeds.
    assert 0.017 < trans < 0.024 and 0.0042 < rot < 0.0058
    assert "image_px" not in given[0]  # no PnP residual was used
    assert np.mean([r["translation_mm"] for r in ignored]) > 1.3 * trans


def test_a_principal_point_error_turns_the_hand_eye_and_its_std_says_by_how_much():
    rng = np.random.default_rng(5)
    views, cam = S.posed_views(15, rng, noise_px=0.03)
    shifted_k = cam.K.copy()
    shifted_k[0, 2] -= 0.3
    shifted_k[1, 2] += 0.5
    shifted = CameraModel(cam.width, cam.height, shifted_k, cam.dist)
    right = calibrate_hand_eye(views, cam)
    wrong = calibrate_hand_eye(views, shifted)
    turn_deg = np.degrees(
        Rotation.from_matrix(
            right.flange_from_cam[:3, :3].T @ wrong.flange_from_cam[:3, :3]
        ).as_rotvec()
    )
    # About the camera's x axis by dcy / fy, about its y axis by dcx / fx (the PnP hands
    # about a tenth of the turn to a sideways shift, measured 0.87-0.90 of it here).
    expected_deg = np.degrees([0.5 / cam.K[1, 1], 0.3 / cam.K[0, 0]])
    assert np.all(np.abs(turn_deg[:2]) > 0.7 * expected_deg)
    assert np.all(np.abs(turn_deg[:2]) < 1.1 * expected_deg)
    assert abs(turn_deg[2]) < 0.1 * expected_deg.min()
    # The intrinsics' own cx / cy uncertainty enters the rotation's standard deviation.
    told = calibrate_hand_eye(views, cam, principal_point_std_px=(0.2, 0.3))
    added_deg = np.sqrt(told.std_rotation_deg**2 - right.std_rotation_deg**2)
    np.testing.assert_allclose(added_deg[:2], np.degrees([0.3, 0.2]) / cam.K[0, 0], rtol=1e-6)
    assert added_deg[2] == 0.0
    np.testing.assert_array_equal(told.std_translation_mm, right.std_translation_mm)


def test_refining_intrinsics_keeps_the_solution():
    rng = np.random.default_rng(1)
    views, cam = S.posed_views(15, rng, noise_px=0.1)
    res = calibrate_hand_eye(views, cam, refine_intrinsics=True)
    assert res, res.reason
    dr, dt = _errors(res.flange_from_cam)
    assert dr < 0.05 and dt < 0.5
    assert abs(res.camera.K[0, 0] - cam.K[0, 0]) < 5.0


def test_copes_with_leading_pure_translations():
    rng = np.random.default_rng(2)
    views, cam = S.posed_views(8, rng, noise_px=0.05)
    # Three extra stops: the first pose translated only (rotation unchanged).
    pts = views[0].points_target
    extra = []
    for k, shift in enumerate(([20.0, 0, 0], [0, 25.0, 0], [0, 0, -30.0])):
        bf = views[0].base_from_flange.copy()
        bf[:3, 3] += shift
        ct = invert_transform(bf @ S.FLANGE_FROM_CAM) @ S.BASE_FROM_TARGET
        from calibration.extrinsics import project_target

        uv = project_target(cam, ct, pts) + rng.normal(0, 0.05, (len(pts), 2))
        extra.append(PosedView(100 + k, bf, uv, pts))
    res = calibrate_hand_eye(extra + views, cam)
    assert res, res.reason
    dr, dt = _errors(res.flange_from_cam)
    assert dr < 0.02 and dt < 0.1


def test_refuses_too_few_views_and_degenerate_motion():
    rng = np.random.default_rng(3)
    views, cam = S.posed_views(6, rng)
    res = calibrate_hand_eye(views[:2], cam)
    assert not res and "at least 3" in res.reason
    # Pure translations: no rotation at all.
    bf = np.stack([make_transform(np.eye(3), [i * 10.0, i * 3.0, 0]) for i in range(5)])
    assert "rotations of at least" in check_robot_motion(bf)
    # Rotations all about one axis.
    bf = np.stack(
        [
            make_transform(Rotation.from_euler("z", 10 * i, degrees=True), [i, 0, 0])
            for i in range(5)
        ]
    )
    assert "same axis" in check_robot_motion(bf)
    assert check_robot_motion(np.stack([v.base_from_flange for v in views])) is None


def test_warns_about_metres_and_inverted_poses():
    rng = np.random.default_rng(4)
    views, cam = S.posed_views(10, rng, noise_px=0.05)
    inverted = [
        PosedView(v.frame_id, invert_transform(v.base_from_flange), v.points_px, v.points_target)
        for v in views
    ]
    res = calibrate_hand_eye(inverted, cam, "park")
    assert any("inverted" in w for w in res.warnings)
    # Same motion in metres: every translation tiny.
    s_views = []
    for v in views:
        bf = v.base_from_flange.copy()
        bf[:3, 3] *= 1e-3
        s_views.append(PosedView(v.frame_id, bf, v.points_px, v.points_target))
    res = calibrate_hand_eye(s_views, cam, "park")
    assert any("metres" in w for w in res.warnings)


@pytest.mark.parametrize("convention", list(RotationConvention))
def test_every_rotation_convention_gives_the_same_result(tmp_path, convention):
    rng = np.random.default_rng(5)
    views, cam = S.posed_views(8, rng, noise_px=0.05)
    img = tmp_path / "x.png"
    img.write_bytes(b"")
    frames = [Frame(v.frame_id, None, img, v.base_from_flange) for v in views]
    write_session(tmp_path, "sweep", 1280, 1024, frames, convention)
    back = read_session(tmp_path, check_images=False)
    rt = [
        PosedView(v.frame_id, f.base_from_flange, v.points_px, v.points_target)
        for v, f in zip(views, back.frames)
    ]
    ref = calibrate_hand_eye(views, cam)
    res = calibrate_hand_eye(rt, cam)
    assert angle_between_rotations_deg(res.flange_from_cam, ref.flange_from_cam) < 1e-4
    assert np.allclose(res.flange_from_cam[:3, 3], ref.flange_from_cam[:3, 3], atol=1e-3)


def _paper_views(rng: np.random.Generator, noise_mm: float) -> list[StripePointView]:
    r = 80.0
    named = {"O": np.zeros(3), "A": np.array([r, 0, 0]), "C": np.array([0, r, 0])}
    views = []
    k = 0
    for name, p_t in named.items():
        p_base = transform_points(S.BASE_FROM_TARGET, p_t.reshape(1, 3))[0]
        for _ in range(4):
            ct = S.look_at_target(rng)
            bf = S.BASE_FROM_TARGET @ invert_transform(ct) @ invert_transform(S.FLANGE_FROM_CAM)
            p_cam = transform_points(
                invert_transform(bf @ S.FLANGE_FROM_CAM), p_base.reshape(1, 3)
            )[0]
            views.append(
                StripePointView(
                    k, name, bf, p_cam + rng.normal(0, noise_mm, 3), ct if name == "O" else None
                )
            )
            k += 1
    return views


def test_paper_hand_eye_is_exact_without_noise_and_close_with_it():
    rng = np.random.default_rng(6)
    res = paper_hand_eye(_paper_views(rng, 0.0), 80.0)
    assert res, res.reason
    dr, dt = _errors(res.flange_from_cam)
    assert dr < 1e-6 and dt < 1e-6
    assert angle_between_rotations_deg(res.base_from_target, S.BASE_FROM_TARGET) < 1e-6
    res = paper_hand_eye(_paper_views(rng, 0.02), 80.0)
    assert res
    dr, dt = _errors(res.flange_from_cam)
    assert dr < 0.2 and dt < 1.0


def test_paper_hand_eye_needs_views_on_o_a_and_c():
    rng = np.random.default_rng(7)
    views = [v for v in _paper_views(rng, 0.0) if v.name != "C"]
    res = paper_hand_eye(views, 80.0)
    assert not res and "on C" in res.reason


def test_grid_numbered_from_the_opposite_corner_is_relabelled():
    rng = np.random.default_rng(8)
    cam = S.camera()
    views, cam = S.posed_views(10, rng, noise_px=0.05, cam=cam)
    # A 9x9 grid centred on the origin: reversing the order turns it by 180 degrees.
    flipped_ids = {2, 5}
    mixed = [
        PosedView(v.frame_id, v.base_from_flange, v.points_px[::-1].copy(), v.points_target)
        if v.frame_id in flipped_ids
        else v
        for v in views
    ]
    res = calibrate_hand_eye(mixed, cam)
    assert res, res.reason
    assert any("relabelled" in w and "2" in w and "5" in w for w in res.warnings)
    dr, dt = _errors(res.flange_from_cam)
    assert dr < 0.02 and dt < 0.1


def test_paper_hand_eye_with_stripe_points_in_the_light_plane():
    # As in use: every stripe point lies in the light plane (camera frame), which leaves the
    # plain linear solve for R and t rank-deficient.
    rng = np.random.default_rng(9)
    n = np.array([0.9, 0.0, 0.3]) / np.linalg.norm([0.9, 0.0, 0.3])
    d = -float(n @ [0.0, 0.0, 350.0])
    e1 = np.cross(n, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    views = []
    for k, p_t in enumerate(([0.0, 0, 0], [80.0, 0, 0], [0.0, 80, 0])):
        p_base = transform_points(S.BASE_FROM_TARGET, np.array([p_t]))[0]
        for j in range(4):
            p_cam = -d * n + rng.uniform(-40, 40) * e1 + rng.uniform(-40, 40) * e2
            rot = Rotation.from_rotvec(rng.normal(0, 0.3, 3)) * Rotation.from_euler(
                "x", 180, degrees=True
            )
            base_from_cam = make_transform(rot, p_base - rot.apply(p_cam))
            bf = base_from_cam @ invert_transform(S.FLANGE_FROM_CAM)
            ct = invert_transform(base_from_cam) @ S.BASE_FROM_TARGET
            views.append(StripePointView(4 * k + j, "OAC"[k], bf, p_cam, ct))
    res = paper_hand_eye(views, 80.0)
    assert res, res.reason
    dr, dt = _errors(res.flange_from_cam)
    assert dr < 1e-6 and dt < 1e-5
