"""The calibration's covariance estimator's building blocks (its whole, on the virtual cell,
is checked against the truth in test_pipeline)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calibration import covariance
from calibration.covariance import intrinsics_covariance_matrix, jackknife_covariance
from calibration.extrinsics import estimate_pose
from calibration.hand_eye import calibrate_hand_eye
from calibration.intrinsics import IntrinsicsResult
from calibration.intrinsics_adjust import PARAM_NAMES
from calibration.light_plane import calibrate_light_plane
from tests.calibration import _synthetic as S
from tests.calibration.test_light_plane import _laser_views
from tests.cancelling import CancelAt, Cancelled


def test_the_jackknife_recovers_the_covariance_of_a_mean():
    # leave-one-group-out means of groups of normal samples: their jackknife covariance is the
    # covariance of the full mean
    rng = np.random.default_rng(0)
    cov_true = np.array([[4.0, 1.2], [1.2, 1.0]])
    n, groups = 2000, 10
    trials = []
    for _ in range(200):
        x = rng.multivariate_normal([0, 0], cov_true, n)
        parts = np.array_split(np.arange(n), groups)
        est = np.array([np.delete(x, g, axis=0).mean(axis=0) for g in parts])
        trials.append(jackknife_covariance(est))
    np.testing.assert_allclose(np.mean(trials, axis=0), cov_true / n, rtol=0.1)


def test_intrinsics_covariance_from_std_and_correlation():
    std = {"fx": 0.5, "fy": 0.4, "cx": 0.2, "cy": 0.3, "k1": 1e-4}
    corr = np.eye(9)
    corr[0, 1] = corr[1, 0] = 0.9
    res = IntrinsicsResult(np.eye(3), np.zeros(5), (640, 480), "default", std=std, correlation=corr)
    c = intrinsics_covariance_matrix(res)
    assert c[0, 1] == pytest.approx(0.9 * 0.5 * 0.4)
    assert c[PARAM_NAMES.index("k3"), PARAM_NAMES.index("k3")] == 0.0  # held fixed
    assert np.all(np.linalg.eigvalsh(c) >= -1e-15)


def _calibration(seed: int) -> tuple:
    """A synthetic cell calibrated: the estimator's inputs with 3 intrinsics directions,
    4 laser frames and 6 posed views (the fewest that give every part of the estimate)."""
    rng = np.random.default_rng(seed)
    views, cam = S.posed_views(6, rng, noise_px=0.1)
    views = [
        replace(v, cam_from_target=estimate_pose(v.points_px, v.points_target, cam).cam_from_target)
        for v in views
    ]
    laser = _laser_views(cam, rng, 4)
    std = {"fx": 0.5, "cx": 0.3, "k1": 1e-4}
    intr = IntrinsicsResult(cam.K, cam.dist, (cam.width, cam.height), "default", std=std)
    intr.correlation = np.eye(9)
    targets = {v.frame_id: (v.points_px, v.points_target) for v in views}
    plane = calibrate_light_plane(laser, cam)
    he = calibrate_hand_eye(views, cam, "default")
    assert plane and he
    return cam, intr, targets, laser, plane, views, he


@pytest.mark.parametrize(
    ("cancel_at", "plane_fits", "hand_eye_fits"),
    [
        # the reference solve, then one of the three intrinsics directions
        (2, 1 + 1, 1 + 1),
        # the reference, the three directions, one of the light plane's four jackknife groups
        (5, 1 + 3 + 1, 1 + 3),
        # ... all four of those, two of the hand-eye's six groups
        (10, 1 + 3 + 4, 1 + 3 + 2),
    ],
)
def test_a_cancelled_uncertainty_stops_within_one_re_solve(
    monkeypatch, cancel_at: int, plane_fits: int, hand_eye_fits: int
):
    inputs = _calibration(seed=0)
    fits = {"plane": 0, "hand_eye": 0}

    def counting(name, func):
        def run(*args, **kwargs):
            fits[name] += 1
            return func(*args, **kwargs)

        return run

    monkeypatch.setattr(
        covariance, "calibrate_light_plane", counting("plane", calibrate_light_plane)
    )
    monkeypatch.setattr(covariance, "calibrate_hand_eye", counting("hand_eye", calibrate_hand_eye))
    check = CancelAt(cancel_at)

    with pytest.raises(Cancelled):
        covariance.estimate_covariance(*inputs, check_cancelled=check)
    assert check.calls == cancel_at
    assert fits == {"plane": plane_fits, "hand_eye": hand_eye_fits}
    # of the whole estimate's 1 + 3 + 4 plane fits and 1 + 3 + 6 hand-eyes
    assert plane_fits + hand_eye_fits < 8 + 10


def test_the_cancellation_check_changes_nothing_in_the_uncertainty():
    inputs = _calibration(seed=0)
    calls = []
    plain = covariance.estimate_covariance(*inputs)
    checked = covariance.estimate_covariance(*inputs, check_cancelled=lambda: calls.append(1))
    assert len(calls) == 3 + 4 + 6  # one per re-solve: directions, plane groups, hand-eye groups
    assert np.array_equal(checked.matrix, plain.matrix)  # to the bit
    assert checked.method == plain.method
    assert "3 directions" in plain.method and "6 groups of views" in plain.method
