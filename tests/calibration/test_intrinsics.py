import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration import intrinsics
from calibration.detection.observations import TargetObservation
from calibration.intrinsics import calibrate_intrinsics, paper_intrinsics
from scanner.formats.reference_data import ZHANG_MSR_IMAGE_SIZE, zhang_msr_corners
from tests.calibration._observations import (
    DIST_TRUE,
    K_TRUE,
    RADII,
    SIZE,
    poses,
    project,
    synthetic_observation,
)
from tests.cancelling import CancelAt, Cancelled


def real_data_dir() -> Path:
    env = os.environ.get("SCANNER_REAL_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real"


def test_paper_method_is_exact_without_noise_and_distortion():
    rng = np.random.default_rng(1)
    obs = [synthetic_observation(T, K_TRUE, np.zeros(5), rng, 0.0) for T in poses(8, rng)]
    res = calibrate_intrinsics(obs, SIZE, method="paper")
    assert res.method == "paper"
    assert res.distortion_model == "none"  # what the report and the file say was fitted
    assert np.allclose(res.K, K_TRUE, rtol=1e-6, atol=1e-3)
    for variant in ("diameter_ends", "all_rings"):
        est = res.paper[variant]
        assert est, est.reason
        assert np.allclose(est.K, K_TRUE, rtol=1e-6, atol=1e-3)


def test_paper_method_needs_four_views_with_finite_vanishing_points():
    vp = (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))  # fronto-parallel: at infinity
    est = paper_intrinsics([vp] * 6)
    assert not est
    assert "expected >= 4" in est.reason


def test_default_recovers_intrinsics_and_distortion():
    rng = np.random.default_rng(2)
    obs = [synthetic_observation(T, K_TRUE, DIST_TRUE, rng, 0.03) for T in poses(20, rng)]
    # Independent noise on every point here: every point carries information, use them all.
    res = calibrate_intrinsics(obs, SIZE, max_points_per_ring=360)
    assert res.method == "default"
    assert abs(res.fx / K_TRUE[0, 0] - 1) < 3e-5
    assert abs(res.fy / K_TRUE[1, 1] - 1) < 3e-5
    assert abs(res.cx - K_TRUE[0, 2]) < 0.1
    assert abs(res.cy - K_TRUE[1, 2]) < 0.1
    assert res.rms_px == pytest.approx(0.03, rel=0.2)
    assert len(res.cam_from_target) == 20
    assert set(res.std) == {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}
    assert res.std["fx"] < 0.2
    assert res.correlation.shape == (9, 9)
    # The distortion model maps every pixel like the truth, within 0.05 px.
    uu, vv = np.meshgrid(np.arange(0, SIZE[0], 32), np.arange(0, SIZE[1], 32))
    uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(float)
    xy = cv2.undistortPointsIter(
        uv.reshape(-1, 1, 2),
        K_TRUE,
        DIST_TRUE,
        None,
        None,
        (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14),
    ).reshape(-1, 2)
    back = project(np.eye(4), np.column_stack([xy, np.ones(len(xy))]), res.K, res.dist)
    # Within 0.1 px (mostly the principal point, sigma ~0.1 px at this noise), shape 0.05 px.
    assert np.max(np.linalg.norm(back - uv, axis=1)) < 0.1


def test_default_rejects_an_outlier_view_with_a_reason():
    rng = np.random.default_rng(3)
    obs = [synthetic_observation(T, K_TRUE, DIST_TRUE, rng, 0.03) for T in poses(8, rng)]
    bad = obs[5]
    for k, ring in enumerate(bad.rings):  # a view whose rings were mislabelled by one
        ring.radius_mm = float(RADII[(k + 1) % len(RADII)])
    res = calibrate_intrinsics(obs, SIZE)
    assert 5 not in res.view_indices
    assert any(i == 5 and "outlier" in why for i, why in res.rejected)
    assert abs(res.fx / K_TRUE[0, 0] - 1) < 2e-4


def test_too_few_views_names_what_is_missing():
    rng = np.random.default_rng(4)
    obs = [synthetic_observation(T, K_TRUE, DIST_TRUE, rng, 0.03) for T in poses(3, rng)]
    obs.append(TargetObservation.failed("no ring pencil found", SIZE, "concentric_circles"))
    with pytest.raises(ValueError, match=r"expected >= 4 views.*no ring pencil found"):
        calibrate_intrinsics(obs, SIZE)


def test_fronto_parallel_views_warn_that_focal_length_is_poorly_determined():
    rng = np.random.default_rng(5)
    obs = [
        synthetic_observation(T, K_TRUE, np.zeros(5), rng, 0.03)
        for T in poses(6, rng, max_tilt_deg=3.0)
    ]
    res = calibrate_intrinsics(obs, SIZE, fixed=("k1", "k2", "p1", "p2", "k3"))
    assert any("fronto-parallel" in w for w in res.warnings)


def test_point_targets_go_through_the_same_adjustment():
    rng = np.random.default_rng(6)
    grid = np.array([(i * 20.0 - 60, j * 20.0 - 40, 0.0) for j in range(5) for i in range(7)])
    obs = []
    for T in poses(10, rng):
        uv = project(T, grid, K_TRUE, DIST_TRUE) + rng.normal(0, 0.05, (len(grid), 2))
        obs.append(TargetObservation(True, "", SIZE, "circle_grid", uv, grid))
    res = calibrate_intrinsics(obs, SIZE)
    assert abs(res.fx / K_TRUE[0, 0] - 1) < 1e-3
    assert abs(res.cx - K_TRUE[0, 2]) < 2.0
    with pytest.raises(ValueError, match="paper"):
        calibrate_intrinsics(obs, SIZE, method="paper")


@pytest.mark.real_data
def test_zhang_published_result_from_given_corners():
    root = real_data_dir() / "zhang_msr"
    if not (root / "Model.txt").is_file():
        pytest.skip(f"real data not found at {root} (set SCANNER_REAL_DATA)")
    model_t, views = zhang_msr_corners(root)
    size = ZHANG_MSR_IMAGE_SIZE
    obs = [TargetObservation(True, "", size, "chessboard", uv, model_t) for uv in views]
    # Zhang's published model: two radial terms (his skew 0.2 is negligible).
    res = calibrate_intrinsics(obs, size, fixed=("p1", "p2", "k3"))
    assert res.fx == pytest.approx(832.5, rel=1e-3)
    assert res.fy == pytest.approx(832.53, rel=1e-3)
    assert res.cx == pytest.approx(303.959, abs=1.0)
    assert res.cy == pytest.approx(206.585, abs=1.0)
    assert res.dist[0] == pytest.approx(-0.228601, abs=0.005)
    assert res.dist[1] == pytest.approx(0.190353, abs=0.02)


@pytest.mark.parametrize(
    ("cancel_at", "choice_begun"),
    [
        (1, False),  # after the first adjustment (no outlier views here): before the choice
        (3, True),  # in the distortion model's choice, before its second fold
        (1 + 3 * 5 + 1, True),  # after its 3 folds of 5 candidates, before the chosen fit
    ],
)
def test_a_cancelled_intrinsics_calibration_stops_before_in_or_after_the_model_choice(
    monkeypatch, cancel_at: int, choice_begun: bool
):
    rng = np.random.default_rng(0)
    obs = [synthetic_observation(T, K_TRUE, np.zeros(5), rng, 0.1) for T in poses(8, rng)]
    check = CancelAt(cancel_at)
    begun = []
    real_choice = intrinsics.select_distortion_model

    def entered(*args, **kwargs):
        begun.append(True)
        return real_choice(*args, **kwargs)

    monkeypatch.setattr(intrinsics, "select_distortion_model", entered)

    with pytest.raises(Cancelled):
        calibrate_intrinsics(obs, SIZE, check_cancelled=check)
    assert check.calls == cancel_at
    assert bool(begun) == choice_begun
