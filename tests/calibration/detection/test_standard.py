import numpy as np
import pytest

from calibration.detection.detect import detect_target
from calibration.intrinsics import calibrate_intrinsics
from scanner.core.conventions import transform_points
from scanner.core.images import load_gray_image
from scanner.core.targets import ChessboardTarget, CircleGridTarget
from tests.calibration.synth_concentric import look_at_pose, render
from tests.conftest import real_data_subdir

K = np.array([[1300.0, 0.0, 405.0], [0.0, 1298.0, 318.0], [0.0, 0.0, 1.0]])
BOARD = ChessboardTarget(inner_corners=(9, 6), square_mm=12.0)


def test_chessboard_corners_are_sub_pixel():
    rng = np.random.default_rng(0)
    T = look_at_pose(500.0, 25.0, 40.0, 0.0) @ np.array(
        [[1, 0, 0, -48.0], [0, 1, 0, -30.0], [0, 0, 1, 0], [0, 0, 0, 1]]
    )
    img = render(BOARD, K, T, (800, 640), rng, supersample=3)
    obs = detect_target(img, BOARD)
    assert obs, obs.reason
    assert obs.kind == "chessboard"
    pc = transform_points(T, obs.points_target)
    want = pc @ K.T
    want = want[:, :2] / want[:, 2:3]
    # OpenCV's order may be any symmetry of the grid: compare the point sets.
    err = np.linalg.norm(obs.points_px[:, None] - want[None], axis=2).min(axis=1)
    assert err.max() < 0.15


def test_missing_chessboard_is_reported():
    img = np.full((480, 640), 200, np.uint8)
    obs = detect_target(img, BOARD)
    assert not obs
    assert "not found" in obs.reason


@pytest.mark.real_data
@pytest.mark.slow
def test_circle_grid_real_data_reproduces_authors_focal_length():
    root = real_data_subdir("zhaocongyang_linelight/calib_picture")
    target = CircleGridTarget(grid=(7, 7), pitch_mm=37.5)
    obs = [detect_target(load_gray_image(p), target) for p in sorted(root.glob("calib*.jpg"))]
    assert sum(map(bool, obs)) >= 10
    res = calibrate_intrinsics(obs, obs[0].image_size)
    assert res.fx == pytest.approx(1144.44, rel=1e-3)


@pytest.mark.real_data
@pytest.mark.slow
def test_kuka_chessboard_real_data_rms_below_a_tenth_of_a_pixel():
    root = real_data_subdir("kuka_1")
    target = ChessboardTarget(inner_corners=(28, 17), square_mm=20.0)
    # Every other image keeps the test short; the first poses are pure translations, so a
    # prefix alone would leave the focal length undetermined.
    paths = sorted(root.glob("*.png"))[::2]
    obs = [detect_target(load_gray_image(p), target) for p in paths]
    assert sum(map(bool, obs)) >= 10
    res = calibrate_intrinsics(obs, obs[0].image_size)
    assert res.rms_px < 0.1
    assert res.fx == pytest.approx(2057.96, rel=5e-3)
