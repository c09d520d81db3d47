"""A quick simulated cell writes sessions that read back, and a truth that matches them."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from scanner.core.conventions import invert_transform
from scanner.core.targets import ChessboardTarget
from scanner.formats.calibration_file import read_calibration
from scanner.formats.session import read_session
from scanner.virtual_cell.quick import quick_cell, quick_simulation
from scanner.virtual_cell.simulate import simulate_cell
from scanner.virtual_cell.truth import read_truth
from tests.cancelling import CancelAt, Cancelled

pytestmark = pytest.mark.slow  # one quick simulation for the module: about 15 s


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper_quick")
    cell = quick_cell("paper", scale=4, sweep_frames=3)
    quick_simulation(out, cell, seed=3)
    return cell, out


def test_sessions_read_back(simulated):
    cell, out = simulated
    calib = read_session(out / "calibration")
    check = read_session(out / "check")
    sweep = read_session(out / "sweep")
    cap = cell.capture
    unposed = cap.hand_held_frames + cap.light_plane_frames
    assert len(calib) == unposed + cap.posed_frames + 3 * cap.aim_frames_each
    assert len(calib.posed_frames) == len(calib) - unposed
    assert all(f.target_image is not None and f.laser_image is not None for f in calib)
    assert len(check) == cap.check_frames and len(check.posed_frames) == cap.check_frames
    assert len(sweep) == 3 and all(f.target_image is None for f in sweep)
    assert calib.target == cell.target_spec()
    assert (calib.width, calib.height) == (cell.camera.width, cell.camera.height)
    image = calib.load_target_image(calib.frames[0])
    assert image.dtype == np.uint8 and image.shape == (cell.camera.height, cell.camera.width)


def test_aim_column_is_a_hint_in_frames_csv(simulated):
    _, out = simulated
    with open(out / "calibration" / "frames.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert {r["aim"] for r in rows} == {"", "O", "A", "C"}
    with open(out / "check" / "frames.csv", newline="") as fh:
        assert {r["aim"] for r in csv.DictReader(fh)} == {"O"}


def test_truth_matches_the_sessions(simulated):
    cell, out = simulated
    truth = read_truth(out)
    assert truth.cell == cell.name and truth.seed == 3
    np.testing.assert_allclose(truth.camera.K, cell.camera.K)
    np.testing.assert_allclose(truth.flange_from_cam, cell.robot.flange_from_cam_matrix())
    calib = read_session(out / "calibration")
    st = truth.sessions["calibration"]
    for frame in calib:
        ft = st.frame(frame.id)
        if frame.has_pose:
            # frames.csv holds the commanded pose; the truth also has the actual one.
            np.testing.assert_allclose(
                frame.base_from_flange, ft.base_from_flange_reported, atol=1e-9
            )
            assert not np.allclose(
                ft.base_from_flange_true, ft.base_from_flange_reported, atol=1e-6
            )
            np.testing.assert_allclose(
                ft.cam_from_target_true,
                invert_transform(ft.base_from_flange_true @ truth.flange_from_cam)
                @ truth.base_from_target,
                atol=1e-9,
            )
        else:
            assert ft.base_from_flange_reported is None and ft.cam_from_target_true is not None
    stripes = truth.sessions["sweep"].stripes
    assert stripes is not None and len(stripes.uv) > 100
    _, ids = stripes.of_frame(0)
    assert "table" in set(ids)
    assert truth.object("sphere_1").params["diameter_mm"] == pytest.approx(25.4)
    assert truth.extra["sphere_pairs"][0]["distance_mm"] == pytest.approx(100.0)
    calib_true = read_calibration(out / "calibration_true.json")
    np.testing.assert_allclose(calib_true.light_plane.normal, cell.laser.normal)


def test_same_seed_same_images(simulated, tmp_path):
    cell, out = simulated
    quick_simulation(tmp_path, cell, seed=3)
    a = read_session(out / "check")
    b = read_session(tmp_path / "check")
    np.testing.assert_array_equal(a.load_laser_image(a.frames[1]), b.load_laser_image(b.frames[1]))


def test_chessboard_override_at_the_same_poses(simulated, tmp_path):
    cell, out = simulated
    quick_simulation(tmp_path, cell, seed=3, target="chessboard")
    session = read_session(tmp_path / "check")
    assert isinstance(session.target, ChessboardTarget)
    a, b = read_truth(out), read_truth(tmp_path)
    fa, fb = a.sessions["check"].frames[0], b.sessions["check"].frames[0]
    np.testing.assert_allclose(fa.base_from_flange_true, fb.base_from_flange_true)
    # The chessboard's frame is shifted so that its pattern is centred where O was.
    shift = np.asarray(b.extra["concentric_from_printed"])
    np.testing.assert_allclose(fb.cam_from_target_true, fa.cam_from_target_true @ shift, atol=1e-9)


@pytest.mark.parametrize("workers", [1, 2])
def test_a_cancelled_simulation_stops_at_its_next_frame(tmp_path, workers):
    """A PLC job's cancellation reaches the rendering: it stops after the frame it was
    called after (a pool's frames not yet started are dropped), and no session is written."""
    check = CancelAt(3)  # before the first frame, after the first, after the second

    cell = quick_cell("paper", scale=4, sweep_frames=200)
    with pytest.raises(Cancelled):
        simulate_cell(cell, tmp_path, sessions=("sweep",), workers=workers, check_cancelled=check)
    assert check.calls == 3
    rendered = list((tmp_path / "sweep" / "images").glob("*.png"))
    # (the frames the pool's processes hold finish: a few of the 200 on a quiet machine, more
    # where one process started late and the other ran ahead)
    assert 2 <= len(rendered) <= (2 if workers == 1 else 199)
    assert not (tmp_path / "sweep" / "session.json").exists()
