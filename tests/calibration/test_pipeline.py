"""calibrate_session and `scanner calibrate`: virtual cell against its truth, real data sets."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration import intrinsics, pipeline
from calibration.detection.detect import detect_target
from calibration.hand_eye import PosedView, StripePointView, calibrate_hand_eye
from calibration.intrinsics import calibrate_intrinsics
from calibration.opencv_adapter import AX_XB_METHODS
from calibration.pipeline import calibrate_session, stripe_pixel_at, target_extent_mm
from scanner.core.camera import CameraModel
from scanner.core.conventions import angle_between_rotations_deg
from scanner.core.images import load_gray_image
from scanner.core.planes import plane_errors
from scanner.core.targets import ChessboardTarget, CircleGridTarget
from scanner.formats.calibration_covariance import PARAMETERS, camera_correction, plane_correction
from scanner.formats.calibration_file import LightPlane, read_calibration
from scanner.formats.session import Frame, Session, read_session
from scanner.virtual_cell.cell import load_cell
from scanner.virtual_cell.quick import quick_cell
from scanner.virtual_cell.random_cell import randomised_cell
from scanner.virtual_cell.simulate import simulate_cell
from scanner.virtual_cell.truth import read_truth
from tests.calibration import _observations as O
from tests.cancelling import CancelAt, Cancelled
from tests.conftest import REPO_ROOT, real_data_subdir


def test_paper_method_needs_the_concentric_target(tmp_path):
    session = Session(
        tmp_path,
        "calibration",
        640,
        480,
        [Frame(0, tmp_path / "a.png", None)],
        target=ChessboardTarget((9, 6), 20.0),
    )
    with pytest.raises(ValueError, match="concentric-circles"):
        calibrate_session(session, method="paper", progress=False)
    with pytest.raises(ValueError, match="expected one of"):
        calibrate_session(session, method="nope", progress=False)  # type: ignore[arg-type]
    sweep = Session(tmp_path, "sweep", 640, 480, [], target=ChessboardTarget((9, 6), 20.0))
    with pytest.raises(ValueError, match="calibration"):
        calibrate_session(sweep, progress=False)


def test_stripe_pixel_at_projects_onto_the_local_line():
    u = np.linspace(0, 100, 201)
    stripe = np.column_stack([u, 0.5 * u + 10])
    foot, dist = stripe_pixel_at(stripe, np.array([50.0, 37.0]))
    # The line v = 0.5 u + 10 passes (50, 35): the point is 2 px above it, 2 cos(atan .5) away.
    assert dist == pytest.approx(2 * np.cos(np.arctan(0.5)), abs=1e-9)
    assert foot[1] == pytest.approx(0.5 * foot[0] + 10, abs=1e-9)
    assert stripe_pixel_at(stripe, np.array([500.0, 500.0])) is None


@pytest.mark.parametrize("hidden", ["", "B", "A", "B D", "A C", "C +y", "A +x"])
def test_paper_reference_pose_without_the_diameter_ends(hidden):
    # The paper's T_cwO needs the vanishing points of both diameters and a point on +x and +y
    # for their signs. Where an end of the largest ring is out of view (its name and its point
    # gone), every ring's ends give them: the same pose, named as such; with a whole arm
    # hidden (a stripe over it), the other arm gives the sign.
    rng = np.random.default_rng(4)
    cam = CameraModel(*O.SIZE, O.K_TRUE, np.zeros(5))
    ends = {"A": (0, 1), "B": (0, -1), "C": (1, 1), "D": (1, -1)}  # axis, side
    for ct in O.poses(4, rng):
        obs = O.synthetic_observation(ct, O.K_TRUE, np.zeros(5), rng, 0.0)
        t = obs.points_target
        gone = np.zeros(len(t), bool)
        for name in hidden.split():
            if name.startswith("+"):  # the whole arm
                col = "xy".index(name[1])
                gone |= (t[:, 1 - col] == 0) & (t[:, col] > 0)
            else:
                del obs.named_px[name]
                col, side = ends[name]
                gone |= (t[:, 1 - col] == 0) & (t[:, col] == side * O.RADII[-1])
        obs.points_px, obs.points_target = obs.points_px[~gone], t[~gone]
        if hidden:
            obs.vanishing_points = {}
        o_cam = ct[:3, 3]
        n = np.array([0.95, 0.05, 0.3]) / np.linalg.norm([0.95, 0.05, 0.3])
        plane = LightPlane(n, -float(n @ o_cam))
        pose, source = pipeline._paper_reference_pose(obs, cam, obs.named_px["O"], plane)
        assert source == ("all_rings" if hidden else "diameter_ends")
        assert angle_between_rotations_deg(pose, ct) < 1e-4
        assert np.linalg.norm(pose[:3, 3] - o_cam) < 1e-4


def test_the_paper_reference_is_the_papers_own_wherever_a_view_gives_one():
    # A view through O whose vanishing points came from every ring's ends comes first; a
    # later one shows all four ends: that one is the reference, the first loses its pose.
    pose = np.eye(4)
    views = [
        StripePointView(i, name, np.eye(4), np.zeros(3), pose.copy() if name == "O" else None)
        for i, name in enumerate(["O", "A", "O", "C"])
    ]
    assert pipeline._choose_paper_reference(views, ["all_rings", "", "diameter_ends", ""]) == 2
    assert views[0].cam_from_target is None and views[2].cam_from_target is not None
    # Without the paper's own, the first fallback view is the reference.
    views[0].cam_from_target = pose.copy()
    assert pipeline._choose_paper_reference(views[:2], ["all_rings", ""]) == 0
    assert pipeline._choose_paper_reference(views[1:2], [""]) is None


@pytest.mark.slow
def test_paper_method_on_a_randomised_paper_sensor(tmp_path):
    # Sensor 0 of the calibration benchmark's randomised paper cells: no view aimed at O shows
    # both ends of both diameters, which once refused the paper's hand-eye ("no view aimed at
    # O has extrinsics"). Its lens distorts (k1 -0.16) and the paper's method has no model for
    # that, so its errors are large (RESULTS: cx 55 px, hand-eye 1.6 deg and 15 mm); a
    # reference pose a quarter or half turn off would be tens of degrees off.
    cell = randomised_cell(load_cell("paper"), np.random.default_rng(10_000))
    truth = simulate_cell(cell, tmp_path, seed=0, sessions=("calibration",), workers=2)
    res = calibrate_session(read_session(tmp_path / "calibration"), "paper", progress=False)
    c = res.calibration
    assert any("reference view aimed at O (frame 30)" in w for w in c.quality.warnings)
    assert angle_between_rotations_deg(c.flange_from_cam, truth.flange_from_cam) < 5.0
    assert np.linalg.norm(c.flange_from_cam[:3, 3] - truth.flange_from_cam[:3, 3]) < 30.0


def test_target_extent_covers_the_printed_features():
    x0, x1, y0, y1 = target_extent_mm(CircleGridTarget((7, 7), 37.5))
    assert x0 < 0 < 6 * 37.5 < x1 and y0 < 0 < 6 * 37.5 < y1


@pytest.fixture(scope="module")
def modern_cell(tmp_path_factory):
    # Rendering the cell takes minutes: SCANNER_TEST_MODERN_CELL may name a folder that
    # simulate_cell("modern", ..., seed=0) already wrote.
    cached = os.environ.get("SCANNER_TEST_MODERN_CELL")
    if cached and (Path(cached) / "truth.json").is_file():
        return Path(cached), read_truth(Path(cached) / "truth.json")
    out = tmp_path_factory.mktemp("modern")
    truth = simulate_cell("modern", out, seed=0, sessions=("calibration",), workers=2)
    return out, truth


@pytest.mark.slow
def test_virtual_cell_default_calibration_matches_truth(modern_cell):

    out, truth = modern_cell
    res = calibrate_session(read_session(out / "calibration"), progress=False)
    cal = res.calibration
    na, dd = plane_errors(cal.light_plane, truth.light_plane)
    # Issue #4's targets: normal 0.002 deg, d 0.02 mm, hand-eye 0.008 deg and 0.05 mm.
    # Measured on seed 0: 0.0018 deg, -0.0015 mm; 0.0018 deg, 0.011 mm (robot cost: the
    # robot's misses do not follow its pose here). The normal gets 50 % headroom: it rests on
    # the principal point, whose own std is 0.09 px.
    assert na < 0.003 and abs(dd) < 0.02
    assert angle_between_rotations_deg(cal.flange_from_cam, truth.flange_from_cam) < 0.008
    assert np.linalg.norm(cal.flange_from_cam[:3, 3] - truth.flange_from_cam[:3, 3]) < 0.05
    assert "robot errors" in cal.quality.hand_eye_method
    q = cal.quality.record
    for key in (
        "method",
        "verdict",
        "intrinsics",
        "light_plane",
        "hand_eye",
        "rejected",
        "warnings",
    ):
        assert key in q
    json.dumps(cal.to_json())  # the quality record is plain JSON
    # Issue #19: the file carries the calibration's covariance, and the errors lie within it
    # (seed 0: |z| at most 1.3 for the plane and hand-eye terms).
    cov = cal.covariance
    assert cov is not None and "intrinsics through the chain" in cov.method
    err = np.concatenate(
        [
            plane_correction(
                truth.light_plane.normal,
                truth.light_plane.d,
                cal.light_plane.normal,
                cal.light_plane.d,
            ),
            camera_correction(truth.flange_from_cam, cal.flange_from_cam),
        ]
    )
    sd = np.array([cov.std[p] for p in PARAMETERS[9:]])
    assert np.all(np.abs(err) < 4 * sd)
    assert cov.std["plane_d"] < 0.02 and cov.std["cam_tz"] < 0.05
    assert cov.robot_translation_mm == pytest.approx(0.02, rel=0.5)
    # Issue #16: the laser origin from the shadow edges, within 2 mm and within its stated
    # 95 % ellipse (seed 0: 1.1 mm, Mahalanobis 1.4 of 2.45).
    origin = q["laser_origin"]
    assert origin["estimated"] and cal.laser_origin_cam is not None
    err = cal.laser_origin_cam - truth.laser_origin_cam
    assert np.linalg.norm(err) < 2.0
    assert np.sqrt(err @ np.linalg.pinv(np.asarray(origin["covariance_mm2"])) @ err) < 2.45
    # ... and the calibration's covariance carries it for the file (issue #19)
    scale = float(np.abs(origin["covariance_mm2"]).max())
    np.testing.assert_allclose(
        cov.laser_origin_mm2, origin["covariance_mm2"], rtol=1e-12, atol=1e-12 * scale
    )
    assert abs(cal.light_plane.signed_distance(cal.laser_origin_cam[None])[0]) < 1e-6


@pytest.mark.slow
def test_scanner_calibrate_command_writes_file_and_report(modern_cell, tmp_path):
    from scanner.app.cli import main

    out, truth = modern_cell
    calib = tmp_path / "calib.json"
    code = main(
        [
            "calibrate",
            str(out / "calibration"),
            "--out",
            str(calib),
            "--report-dir",
            str(tmp_path / "reports"),
            "--quiet",
        ]
    )
    assert code == 0
    cal = read_calibration(calib)
    assert angle_between_rotations_deg(cal.flange_from_cam, truth.flange_from_cam) < 0.05
    page = (tmp_path / "reports" / "calib.html").read_text()  # named after --out
    assert "Verdict" in page and "data:image/png;base64" in page
    assert "Shadow edges in the light plane" in page and "laser origin (mm" in page


@pytest.mark.slow
@pytest.mark.real_data
def test_kuka_full_chain_beats_opencv_with_the_same_intrinsics():
    root = real_data_subdir("kuka_1")
    poses = np.loadtxt(root / "RobotPosesVec.txt").reshape(-1, 4, 4)
    poses[:, :3, 3] *= 1000.0  # the file is in metres
    target = ChessboardTarget((28, 17), 20.0)
    obs = [detect_target(load_gray_image(root / f"{i:02d}.png"), target) for i in range(1, 31)]
    intr = calibrate_intrinsics(obs, (1928, 1208), "default", target)
    cam = CameraModel(1928, 1208, intr.K, intr.dist)
    views = [PosedView(i, poses[i], o.points_px, o.points_target) for i, o in enumerate(obs) if o]
    ours = calibrate_hand_eye(views, cam)
    assert ours, ours.reason
    best = min((calibrate_hand_eye(views, cam, m) for m in AX_XB_METHODS), key=lambda r: r.rms_px)
    assert ours.rms_px < best.rms_px  # about 2.38 against 2.45 px
    # The board's origin in the base frame scatters less (3-D standard deviation).
    assert np.linalg.norm(ours.target_spread_mm) < np.linalg.norm(best.target_spread_mm)
    assert 255 < ours.flange_from_cam[0, 3] < 263


@pytest.mark.slow
@pytest.mark.real_data
def test_linelight_plane_agrees_with_the_authors(monkeypatch):
    root = real_data_subdir("zhaocongyang_linelight")
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "bench_calibration", REPO_ROOT / "benchmarks" / "bench_calibration.py"
    )
    bench = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "bench_calibration", bench)  # its dataclasses need it
    spec.loader.exec_module(bench)
    bench_linelight = bench.bench_linelight

    fig = bench_linelight(root.parent)
    # Issue #4: normal within 0.5 deg of the authors', their cloud within 0.5 mm of our plane.
    # Measured: 0.22 deg; cloud -0.19 mm mean, 0.42 mm RMS (it scatters 0.235 mm RMS about
    # its own best plane); our stripe points 0.11 mm RMS, every frame's mean within 0.03 mm.
    assert fig["normal_deg"] < 0.35
    assert abs(fig["cloud_mean_mm"]) < 0.3
    assert fig["cloud_rms_mm"] < 0.5
    assert fig["plane_rms_mm"] < 0.15
    assert fig["worst_frame_mean_mm"] < 0.08


@pytest.fixture(scope="module")
def quick_paper_session(tmp_path_factory) -> Session:
    """A small paper cell's calibration session (11 target images, seconds to render)."""
    out = tmp_path_factory.mktemp("quick-paper")
    cell = quick_cell("paper", scale=4, sweep_frames=3)
    simulate_cell(cell, out, seed=1, sessions=("calibration",), workers=1)
    return read_session(out / "calibration")


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2])
def test_a_cancelled_calibration_stops_at_its_next_image(quick_paper_session, monkeypatch, workers):
    """A PLC job's cancellation reaches the detection: checked as the stage starts and after
    each image, it stops there (a pool's images not yet started are dropped)."""
    session = quick_paper_session
    assert sum(f.target_image is not None for f in session.frames) > 10
    detected = []
    real_detect = pipeline._detect_one

    def counting(job):
        detected.append(job)
        return real_detect(job)

    if workers == 1:  # (a pool's processes could not take the stand-in)
        monkeypatch.setattr(pipeline, "_detect_one", counting)
    check = CancelAt(5)  # the stage's start, before the first image, after three

    with pytest.raises(Cancelled):
        calibrate_session(session, progress=False, workers=workers, check_cancelled=check)
    assert check.calls == 5
    if workers == 1:
        assert len(detected) == 3


@pytest.mark.slow
@pytest.mark.parametrize(
    ("module", "name", "stage"),
    [
        (intrinsics, "select_distortion_model", "intrinsics"),
        (pipeline, "estimate_covariance", "uncertainty"),
    ],
)
def test_a_cancelled_calibration_stops_inside_its_long_fits(
    quick_paper_session, monkeypatch, module, name, stage
):
    """The intrinsics' distortion-model choice and the uncertainty's re-solves (tens of
    seconds on a real session) check between their fits: a cancellation there stops the
    calibration at the next one and comes out of it (not taken for a failed estimate)."""
    session = quick_paper_session
    observations = {
        f.id: detect_target(load_gray_image(f.target_image), session.target)
        for f in session.frames
        if f.target_image is not None
    }
    entered = []
    real = getattr(module, name)

    def spy(*args, **kwargs):
        entered.append(name)
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, spy)
    checks_inside = []

    def check() -> None:
        if entered:
            checks_inside.append(1)
            if len(checks_inside) == 2:  # before its second fit
                raise Cancelled

    announced: list[str] = []
    with pytest.raises(Cancelled):
        calibrate_session(
            session,
            progress=False,
            on_stage=announced.append,
            observations=observations,
            check_cancelled=check,
        )
    assert announced[-1] == stage
    assert len(checks_inside) == 2
