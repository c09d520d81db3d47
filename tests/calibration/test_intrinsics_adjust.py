import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.extrinsics import pose_covariance_as_turns
from calibration.intrinsics_adjust import (
    _CIRCLE,
    _POINT,
    _XLINE,
    _YLINE,
    PARAM_NAMES,
    _adjust,
    _Data,
    _Problem,
    _project,
    adjustment_covariances,
)
from tests.calibration._observations import DIST_TRUE, K_TRUE, poses, synthetic_observation

NOISE_PX = 0.3


def _curve_points(
    kind: np.ndarray, radius: np.ndarray, psi: np.ndarray, fixed: np.ndarray
) -> np.ndarray:
    """The observations' target points ``(P, 3)`` in array form: what the kernels are held to."""
    pts = fixed.copy()
    c = kind == _CIRCLE
    pts[c, 0] = radius[c] * np.cos(psi[c])
    pts[c, 1] = radius[c] * np.sin(psi[c])
    xl = kind == _XLINE
    pts[xl, 0] = psi[xl]
    pts[xl, 1] = 0.0
    yl = kind == _YLINE
    pts[yl, 0] = 0.0
    pts[yl, 1] = psi[yl]
    pts[c | xl | yl, 2] = 0.0
    return pts


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


@pytest.mark.slow
def test_with_the_camera_free_the_marginal_and_intrinsics_covariances_match_repeated_noise():
    # With the camera free, the poses also carry the camera's error, which the given-camera
    # covariances leave out by design (it is in the intrinsics' covariance, and what the
    # hand-eye propagates from it). The marginal covariance (the full normal matrix's
    # inverse) holds it.
    rng = np.random.default_rng(19)
    views = poses(3, rng)
    given, marginal, intrinsics = zip(*(_free_camera_chi2(views, rng) for _ in range(40)))
    # 120 pose draws, 6 degrees of freedom (measured 6.03; 5.27-6.36 over seeds 0-3; the
    # three views of one adjustment share its camera's error, so the spread is wider than
    # 120 independent draws' 0.32); 40 intrinsics draws of 9, standard error 0.67 (8.50;
    # 8.39-9.82). The rotation-vector covariance taken for turns gives 206; the coordinates'
    # spreads, which caught that above, are too noisy here (0.72-1.16 over seeds 0-3 and 19).
    assert 4.5 < np.mean(marginal) < 7.5, np.mean(marginal)
    assert 7.0 < np.mean(intrinsics) < 11.0, np.mean(intrinsics)
    # what the given-camera covariance leaves out dominates with three views (mean 3e5)
    assert np.mean(given) > 100 * np.mean(marginal)


def _free_camera_chi2(
    views: list[np.ndarray], rng: np.random.Generator
) -> tuple[float, float, float]:
    """One adjustment with every camera term free: the mean whitened square of the views' pose
    errors under the given-camera and the marginal covariances, and the intrinsics' error's
    whitened square under their stated covariance."""
    start = np.array([np.r_[Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]] for T in views])
    obs = [synthetic_observation(T, K_TRUE, DIST_TRUE, rng, NOISE_PX) for T in views]
    x, res, prob, _ = _adjust(obs, K_TRUE, DIST_TRUE, start, None, 60, ())
    intrinsics_cov, given_camera = adjustment_covariances(prob, x, res, ())
    normal, _ = prob.normal_equations(x, res, np.ones(len(res)))
    full = np.linalg.inv(normal) * float(np.sum(res**2) / (len(res) - x.size))
    assert np.allclose(full[:9, :9], intrinsics_cov)  # the library's marginal, as here
    truth = np.r_[K_TRUE[0, 0], K_TRUE[1, 1], K_TRUE[0, 2], K_TRUE[1, 2], DIST_TRUE]
    given, marginal = [], []
    for v, (T, p) in enumerate(zip(views, x[9:].reshape(-1, 6))):
        turn = (Rotation.from_rotvec(p[:3]) * Rotation.from_matrix(T[:3, :3]).inv()).as_rotvec()
        e = np.r_[turn, p[3:] - T[:3, 3]]
        block = full[9 + 6 * v : 15 + 6 * v, 9 + 6 * v : 15 + 6 * v]
        given.append(e @ np.linalg.solve(pose_covariance_as_turns(p[:3], given_camera[v]), e))
        marginal.append(e @ np.linalg.solve(pose_covariance_as_turns(p[:3], block), e))
    d = x[:9] - truth
    return (
        float(np.mean(given)),
        float(np.mean(marginal)),
        float(d @ np.linalg.solve(intrinsics_cov, d)),
    )


def test_the_compiled_projection_is_the_array_form():
    """Every kind of observation (ring, x and y diameter, fixed point) projects in the
    compiled kernels as :func:`_project` projects it, and the residuals are its distances."""
    rng = np.random.default_rng(5)
    n_views, per_view = 4, 40
    view = np.repeat(np.arange(n_views), per_view)
    kind = rng.integers(0, 4, view.size)
    radius = np.where(kind == 0, rng.uniform(10, 80, view.size), 0.0)
    fixed = np.column_stack([rng.uniform(-60, 60, (view.size, 2)), np.zeros(view.size)])
    psi = rng.uniform(-3, 3, view.size)
    data = _Data(view, kind, radius, rng.uniform(0, 1000, (view.size, 2)), fixed, psi)
    prob = _Problem(data, n_views)
    rotvecs = rng.normal(0, 0.3, (n_views, 3))
    translations = np.column_stack(
        [rng.normal(0, 30, (n_views, 2)), rng.uniform(300, 600, n_views)]
    )
    x = np.r_[K_TRUE[0, 0], K_TRUE[1, 1], K_TRUE[0, 2], K_TRUE[1, 2], DIST_TRUE[:5]]
    x = np.r_[x, np.column_stack([rotvecs, translations]).ravel()]
    x9, R, t = prob.unpack(x)
    pts = _curve_points(kind, radius, psi, fixed)
    expected = _project(x9, R[view], t[view], pts)
    assert np.allclose(prob._proj(x9, R, t, psi), expected, rtol=0, atol=1e-9)
    # The residuals: along the curve's normal for curve points, both pixel errors for points.
    res = prob.residuals(x, update=False)
    diff = data.obs - expected
    ahead = _project(x9, R[view], t[view], _curve_points(kind, radius, psi + prob.step, fixed))
    tangent = ahead - expected
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True).clip(1e-300)
    curve = kind != _POINT
    along = np.einsum("pi,pi->p", diff, normal)[curve]
    assert np.allclose(res[: curve.sum()], along, rtol=0, atol=1e-9)
    assert np.allclose(res[curve.sum() :], diff[~curve].ravel(), rtol=0, atol=1e-9)
    # The residuals' derivatives by the intrinsics: the array form's parts along the normal.
    _, parts = _project(x9, R[view], t[view], pts, parts=True)
    d_intrinsics = prob.jacobian(x)[0]
    along_parts = -np.einsum("pij,pi->pj", parts[curve], normal[curve])
    assert np.allclose(d_intrinsics[: curve.sum()], along_parts, rtol=1e-12, atol=1e-9)
    assert np.allclose(
        d_intrinsics[curve.sum() :], -parts[~curve].reshape(-1, 9), rtol=1e-12, atol=1e-9
    )
