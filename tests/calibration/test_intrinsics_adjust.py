import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.extrinsics import pose_covariance_as_turns
from calibration.intrinsics_adjust import PARAM_NAMES, _adjust, adjustment_covariances
from tests.calibration._observations import DIST_TRUE, K_TRUE, poses, synthetic_observation

NOISE_PX = 0.3


def _pose_errors(views: list[np.ndarray], fixed: tuple[str, ...], rng: np.random.Generator):
    """One adjustment of noisy concentric views from the true start: each view's pose error
    as (turn rad, translation mm) of the camera frame, and its stated covariance."""
    start = np.array([np.r_[Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]] for T in views])
    obs = [synthetic_observation(T, K_TRUE, DIST_TRUE, rng, NOISE_PX) for T in views]
    x, res, prob, _ = _adjust(obs, K_TRUE, DIST_TRUE, start, None, 60, fixed)
    _, given_camera = adjustment_covariances(prob, x, res, fixed)
    out = []
    for T, p, cov in zip(views, x[9:].reshape(-1, 6), given_camera):
        turn = (Rotation.from_rotvec(p[:3]) * Rotation.from_matrix(T[:3, :3]).inv()).as_rotvec()
        out.append((np.r_[turn, p[3:] - T[:3, 3]], pose_covariance_as_turns(p[:3], cov)))
    return out


@pytest.mark.slow
def test_pose_covariance_given_the_camera_matches_repeated_noise():
    # The hand-eye's robot cost takes each view's pose noise from these covariances; here the
    # same views are adjusted again and again with new edge noise, the camera held at the
    # truth, and every pose error is whitened by the covariance the adjustment stated.
    rng = np.random.default_rng(19)
    views = poses(3, rng)
    draws = [e for _ in range(40) for e in _pose_errors(views, PARAM_NAMES, rng)]
    chi2 = np.array([e @ np.linalg.solve(c, e) for e, c in draws])
    # 120 draws of a chi-square with 6 degrees of freedom: mean 6, its standard error 0.32
    # (measured 6.37; 5.84-6.53 over seeds 0-9)
    assert 5.0 < chi2.mean() < 7.0, chi2.mean()
    # each coordinate on its own too: the spread against the stated sigma. This is what
    # catches the rotation-vector covariance taken for turns (one coordinate's spread off by
    # 0.43-0.61 over seeds 0-9; the chi-square mean alone passes at half of them)
    z = np.array([e / np.sqrt(np.diag(c)) for e, c in draws])
    assert np.all(np.abs(z.std(axis=0) - 1) < 0.25), z.std(axis=0)

    # With the camera free, the poses also carry the camera's error, which these
    # covariances leave out by design (it is the intrinsics' covariance): whitened by them,
    # the errors come out far larger (a mean of some 1e5 with three views): documentation of
    # what the covariance leaves out more than a check.
    free = [e for _ in range(40) for e in _pose_errors(views, (), rng)]
    assert np.mean([e @ np.linalg.solve(c, e) for e, c in free]) > 8.0
