"""Hand-eye adjustments: ``flange_from_cam`` X and ``base_from_target`` Z from a start.

Two costs (see :mod:`calibration.hand_eye` for when each is used): the robot's misses
(:func:`_adjust_robot_space`, every robot pose missed by an unknown flange motion held to
the robot's repeatability) and every feature's image residual through the whole chain
(:func:`_adjust`, optionally with the intrinsics). Each returns a ``_Fit``, from which
:func:`_held_out_rms` predicts every view left out, and :func:`robot_errors_depend_on_pose`
tests whether the robot's misses follow its pose (absolute-accuracy errors, not
repeatability).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration.extrinsics import pose_covariance_as_turns, project_target
from calibration.hand_eye_views import PosedView
from scanner.core.camera import CameraModel
from scanner.core.conventions import invert_transform, make_transform

__all__ = ["MIN_VIEWS_FOR_ROBOT_TEST", "ROBOT_TEST_ALPHA", "robot_errors_depend_on_pose"]

logger = logging.getLogger(__name__)


def _chain_residuals(
    views: Sequence[PosedView],
    camera: CameraModel,
    flange_from_cam: NDArray,
    base_from_target: NDArray,
) -> list[NDArray]:
    out = []
    for v in views:
        cam_from_target = invert_transform(v.base_from_flange @ flange_from_cam) @ base_from_target
        out.append(v.points_px - project_target(camera, cam_from_target, v.points_target))
    return out


def _rms(res: Sequence[NDArray]) -> float:
    allr = np.concatenate([r.reshape(-1, 2) for r in res])
    return float(np.sqrt(np.mean(np.sum(allr**2, axis=1))))


def _camera_params(camera: CameraModel) -> NDArray:
    dist = np.zeros(5)
    dist[: min(5, camera.dist.size)] = camera.dist[:5]
    return np.concatenate([[camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]], dist])


def _camera_from_params(camera: CameraModel, p: NDArray) -> CameraModel:
    K = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
    return CameraModel(camera.width, camera.height, K, p[4:9].copy())


def _perturbed(x0: NDArray, z0: NDArray, p: NDArray) -> tuple[NDArray, NDArray]:
    """X and Z moved by the 12-vector ``p``: ``X = X0 (exp(p[0:3]), p[3:6])`` in the camera
    frame, ``Z = (exp(p[6:9]), p[9:12]) Z0`` in the base frame (every adjustment's unknowns)."""
    x = x0 @ make_transform(Rotation.from_rotvec(p[0:3]), p[3:6])
    z = make_transform(Rotation.from_rotvec(p[6:9]), p[9:12]) @ z0
    return x, z


def _forward_jacobian(fun: Callable[[NDArray], NDArray], p: NDArray, step: float) -> NDArray:
    """Forward-difference Jacobian of ``fun`` (returning a flat vector) at ``p``."""
    f0 = fun(p)
    jac = np.empty((f0.size, p.size))
    for k in range(p.size):
        d = np.zeros(p.size)
        d[k] = step
        jac[:, k] = (fun(p + d) - f0) / step
    return jac


def _pose_covariance(view: PosedView, camera: CameraModel) -> tuple[NDArray, float, int]:
    """The view's own pose uncertainty from PnP: ``(6, 6)`` covariance of ``cam_from_target``
    (camera-frame turns, translation) per unit image variance, and its residual sum of squares
    with its dof."""
    ct = view.cam_from_target
    rvec = Rotation.from_matrix(ct[:3, :3]).as_rotvec()  # type: ignore[index]
    obj = np.ascontiguousarray(view.points_target.reshape(-1, 1, 3))
    proj, jac = cv2.projectPoints(obj, rvec, ct[:3, 3], camera.K, camera.dist)  # type: ignore[index]
    j = jac[:, :6]
    r = proj.reshape(-1, 2) - view.points_px
    cov = pose_covariance_as_turns(rvec, np.linalg.pinv(j.T @ j))
    return cov, float(np.sum(r**2)), max(1, 2 * len(view.points_px) - 6)


def _robot_misses(
    x: NDArray, z: NDArray, flange_from_base: NDArray, target_from_cam: NDArray
) -> NDArray:
    """``(n, 6)`` flange motion by which each robot pose missed (rotation vector rad, mm).

    The camera stood at ``B_i E_i X`` when it saw the target at ``C_i``, so
    ``E_i = inv(B_i) Z inv(C_i) inv(X)``.
    """
    e = flange_from_base @ z @ target_from_cam @ invert_transform(x)
    return np.column_stack([Rotation.from_matrix(e[:, :3, :3]).as_rotvec(), e[:, :3, 3]])


@dataclass
class _Fit:
    """One adjustment's answer, with what the leave-one-view-out check needs to redo it."""

    flange_from_cam: NDArray
    base_from_target: NDArray
    std: NDArray  # (6,): rotation deg about the camera axes, translation mm
    residuals: list[NDArray]  # chain image residuals per view
    #: Per-view residuals of the cost this fit minimised, as a function of (X, Z): the
    #: leave-one-view-out check linearises it.
    cost_residuals: Callable[[NDArray, NDArray], list[NDArray]]
    camera: CameraModel
    repeatability: dict[str, float] = field(default_factory=dict)


def _adjust_robot_space(
    views: Sequence[PosedView],
    camera: CameraModel,
    x0: NDArray,
    z0: NDArray,
    iterations: int = 10,
) -> _Fit:
    """Adjustment with each robot pose's own error: the ``"robot"`` cost of
    :mod:`calibration.hand_eye`.

    Every view's target pose from its image, ``C_i``, is far more precise than the robot's
    pose (a whole target's features pin it), so the unknown miss of each robot pose follows
    from X and Z in closed form, ``E_i = inv(B_i) Z inv(C_i) inv(X)``. The cost is the sum of
    ``E_i``'s whitened squares, its covariance the robot's repeatability (rotation
    ``sigma_r``, translation ``sigma_t``, per axis in the flange frame) plus ``C_i``'s own
    uncertainty carried into ``E_i`` (the view's ``pose_covariance`` where its adjustment gave
    one, else PnP's on its features). Without it the variance components take up ``C_i``'s
    errors as the robot's. ``sigma_r`` and ``sigma_t`` are variance components
    re-estimated from the misses until they settle: the data say how good the robot is.
    Twelve unknowns and six residuals per view: a fraction of a second.
    """
    n = len(views)
    flange_from_base = np.stack([invert_transform(v.base_from_flange) for v in views])
    cam_from_target = np.stack([v.cam_from_target for v in views])  # type: ignore[misc]
    target_from_cam = np.stack([invert_transform(c) for c in cam_from_target])
    # C_i's covariance: the adjustment's that gave it, else PnP's scaled by the image noise
    # of the views without one.
    pnp = {i: _pose_covariance(v, camera) for i, v in enumerate(views) if v.pose_covariance is None}
    var_px = float("nan")
    if pnp:
        sums = sum(s for _, s, _ in pnp.values())
        var_px = max(sums / sum(d for _, _, d in pnp.values()), 1e-6)  # per coordinate, px^2
    pose_cov = np.stack(
        [
            pnp[i][0] * var_px if i in pnp else np.asarray(v.pose_covariance, dtype=np.float64)
            for i, v in enumerate(views)
        ]
    )

    def unpack(p: NDArray) -> tuple[NDArray, NDArray]:
        return _perturbed(x0, z0, p)

    def pose_to_miss(x: NDArray, z: NDArray) -> NDArray:
        """``(n, 6, 6)`` derivative of each miss by its view's pose (camera-frame turn,
        translation)."""
        base = _robot_misses(x, z, flange_from_base, target_from_cam)
        g = np.zeros((n, 6, 6))
        rotations = Rotation.from_matrix(cam_from_target[:, :3, :3])
        step = 1e-6
        for k in range(6):
            d = np.zeros(6)
            d[k] = step
            turned = (Rotation.from_rotvec(d[:3]) * rotations).as_matrix()
            moved = np.stack(
                [
                    invert_transform(make_transform(r, c[:3, 3] + d[3:]))
                    for r, c in zip(turned, cam_from_target)
                ]
            )
            g[:, :, k] = (_robot_misses(x, z, flange_from_base, moved) - base) / step
        return g

    sig = np.array([np.radians(0.01), 0.05])  # rad, mm: starting guesses
    floor = np.array([np.radians(1e-5), 1e-5])
    p = np.zeros(12)
    whiten = np.tile(np.eye(6), (n, 1, 1))
    jac = np.zeros((6 * n, 12))
    for _ in range(max(1, iterations)):
        g = pose_to_miss(*unpack(p))
        from_image = np.einsum("nij,njk,nlk->nil", g, pose_cov, g)
        cov = from_image + np.diag(np.repeat(sig**2, 3))[None]
        whiten = np.linalg.inv(np.linalg.cholesky(cov))

        def fun(q: NDArray, w: NDArray = whiten) -> NDArray:
            return np.einsum(
                "nij,nj->ni", w, _robot_misses(*unpack(q), flange_from_base, target_from_cam)
            ).ravel()

        sol = least_squares(fun, p, x_scale="jac", loss="soft_l1", f_scale=3.0)
        p, jac = sol.x, sol.jac

        # Variance components (Helmert / Foerstner): theta_k = v' W Q_k W v / tr(R Q_k), with
        # R = W - W A N^-1 A' W the redundancy matrix, so the share of the misses that X
        # and Z absorb, and the share the views' own pose noise explains, are not counted.
        def misses(q: NDArray) -> NDArray:
            return _robot_misses(*unpack(q), flange_from_base, target_from_cam).ravel()

        e = misses(p)
        a = _forward_jacobian(misses, p, 1e-7)
        w = np.zeros((6 * n, 6 * n))
        for i, wi in enumerate(whiten):
            w[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] = wi.T @ wi
        wa = w @ a
        redundancy = w - wa @ np.linalg.pinv(a.T @ wa) @ wa.T
        we = w @ e
        new = sig.copy()
        for k in range(2):
            q = np.zeros(6 * n)
            q.reshape(n, 6)[:, 3 * k : 3 * k + 3] = 1.0  # this component's rows
            trace = float(np.sum(np.diag(redundancy) * q))
            if trace > 1e-9:
                new[k] = np.sqrt(max(float(np.sum(we**2 * q)) / trace * sig[k] ** 2, floor[k] ** 2))
        settled = bool(np.all(np.abs(new / sig - 1) < 0.01))
        sig = new
        if settled:
            break
    x, z = unpack(p)
    std = np.full(6, np.nan)
    try:
        sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(jac.T @ jac))[:6], 0, None))
        std = np.concatenate([np.degrees(sd[:3]), sd[3:6]])
    except np.linalg.LinAlgError:
        logger.debug("hand-eye covariance singular")
    final_whiten = whiten

    def cost_residuals(xx: NDArray, zz: NDArray) -> list[NDArray]:
        e = _robot_misses(xx, zz, flange_from_base, target_from_cam)
        return list(np.einsum("nij,nj->ni", final_whiten, e))

    repeatability = {
        "rotation_deg": float(np.degrees(sig[0])),
        "translation_mm": float(sig[1]),
    }
    if pnp:
        repeatability["image_px"] = float(np.sqrt(var_px))
    return _Fit(
        x, z, std, _chain_residuals(views, camera, x, z), cost_residuals, camera, repeatability
    )


def _held_out_rms(
    views: Sequence[PosedView], camera: CameraModel, fit: _Fit, step: float = 1e-6
) -> float:
    """Chain reprojection RMS of each view predicted by the fit without it (px).

    Leaving view k out is one Gauss-Newton step of the fit's own cost from its solution
    (the gradient without view k's terms), linearised once: cheap, and exact enough for the
    small moves one view causes. The held-out view is then projected exactly through the
    robot's reported pose: what calibrating on the other views predicts for a new pose.
    """
    x, z = fit.flange_from_cam, fit.base_from_target
    sizes = [np.size(r) for r in fit.cost_residuals(x, z)]

    def at(p: NDArray) -> NDArray:
        return np.concatenate([np.ravel(r) for r in fit.cost_residuals(*_perturbed(x, z, p))])

    r = at(np.zeros(12))
    jac = _forward_jacobian(at, np.zeros(12), step)
    normal = jac.T @ jac
    grad = jac.T @ r
    squares, count = 0.0, 0
    bounds = np.concatenate([[0], np.cumsum(sizes)])
    for k, v in enumerate(views):
        jk, rk = jac[bounds[k] : bounds[k + 1]], r[bounds[k] : bounds[k + 1]]
        try:
            dp = -np.linalg.solve(normal - jk.T @ jk, grad - jk.T @ rk)
        except np.linalg.LinAlgError:
            return float("inf")
        res = _chain_residuals([v], fit.camera, *_perturbed(x, z, dp))[0].reshape(-1, 2)
        squares += float(np.sum(res**2))
        count += len(res)
    return float(np.sqrt(squares / max(count, 1)))


#: Minimum posed views for the test of the robot-error model (7 regressors and some dof).
MIN_VIEWS_FOR_ROBOT_TEST = 14
#: Significance below which the robot's misses count as depending on its pose.
ROBOT_TEST_ALPHA = 1e-3


def robot_errors_depend_on_pose(views: Sequence[PosedView], fit: _Fit) -> float:
    """p-value that the robot's misses are independent of its pose (repeatability only).

    The robot cost models each pose's miss ``E_i`` as repeatability: zero-mean noise that
    does not depend on where the robot is. Misses from absolute-accuracy errors (kinematic
    parameters, elasticity) are smooth functions of the pose instead. Each of the six miss
    components, in the flange frame and turned into the base frame, is regressed on the
    flange position and rotation (about their mean) and F-tested against a constant; the
    smallest p-value, Bonferroni-corrected over the twelve.
    On the real kuka_1 robot the misses depend on the pose (F up to 18, p ~ 5e-14); on the
    virtual cells they do not (p > 0.1).

    Returns
    -------
    float
        NaN with fewer than :data:`MIN_VIEWS_FOR_ROBOT_TEST` views.
    """
    from scipy.stats import f as f_distribution

    n = len(views)
    if n < MIN_VIEWS_FOR_ROBOT_TEST:
        return float("nan")
    base_from_flange = np.stack([v.base_from_flange for v in views])
    flange_from_base = np.stack([invert_transform(b) for b in base_from_flange])
    target_from_cam = np.stack([invert_transform(v.cam_from_target) for v in views])  # type: ignore[arg-type]
    misses = _robot_misses(
        fit.flange_from_cam, fit.base_from_target, flange_from_base, target_from_cam
    )
    # In the flange frame (errors of the wrist) and turned into the base frame (errors of
    # the arm's geometry, such as a wrong link length, point the same way in the base).
    rot = base_from_flange[:, :3, :3]
    in_base = np.column_stack(
        [np.einsum("nij,nj->ni", rot, misses[:, :3]), np.einsum("nij,nj->ni", rot, misses[:, 3:])]
    )
    rotations = Rotation.from_matrix(rot)
    about_mean = (rotations.mean().inv() * rotations).as_rotvec()
    position = base_from_flange[:, :3, 3] - base_from_flange[:, :3, 3].mean(axis=0)
    design = np.column_stack([np.ones(n), position, about_mean])
    k = design.shape[1]
    p_values = []
    for y in np.column_stack([misses, in_base]).T:
        coef, *_ = np.linalg.lstsq(design, y, rcond=None)
        rss_model = float(np.sum((y - design @ coef) ** 2))
        rss_const = float(np.sum((y - y.mean()) ** 2))
        if rss_model <= 0:
            p_values.append(0.0)
            continue
        f_stat = ((rss_const - rss_model) / (k - 1)) / (rss_model / (n - k))
        p_values.append(float(f_distribution.sf(f_stat, k - 1, n - k)))
    return min(1.0, len(p_values) * min(p_values))


def _adjust(
    views: Sequence[PosedView],
    camera: CameraModel,
    x0: NDArray,
    z0: NDArray,
    refine_intrinsics: bool,
) -> _Fit:
    """Joint adjustment of X and Z (and the intrinsics) on every feature's image residual."""
    cam_p0 = _camera_params(camera)
    n_cam = 9 if refine_intrinsics else 0
    obj = [np.ascontiguousarray(v.points_target.reshape(-1, 1, 3)) for v in views]
    uv = [v.points_px for v in views]
    flange_from_base = [invert_transform(v.base_from_flange) for v in views]

    def unpack(p: NDArray) -> tuple[NDArray, NDArray, CameraModel]:
        x, z = _perturbed(x0, z0, p)
        cam = _camera_from_params(camera, p[12:]) if n_cam else camera
        return x, z, cam

    def fun(p: NDArray) -> NDArray:
        x, z, cam = unpack(p)
        cam_from_flange = invert_transform(x)
        out = []
        for o, u, fb in zip(obj, uv, flange_from_base):
            ct = cam_from_flange @ fb @ z
            rvec = Rotation.from_matrix(ct[:3, :3]).as_rotvec()
            proj, _ = cv2.projectPoints(o, rvec, ct[:3, 3], cam.K, cam.dist)
            out.append((proj.reshape(-1, 2) - u).ravel())
        return np.concatenate(out)

    p0 = np.zeros(12 + n_cam)
    if n_cam:
        p0[12:] = cam_p0
    r0 = np.abs(fun(p0))
    # Robust scale: a few times the typical residual, never below a quarter pixel.
    f_scale = max(0.25, 3.0 * 1.4826 * float(np.median(r0)))
    sol = least_squares(fun, p0, loss="soft_l1", f_scale=f_scale, x_scale="jac", max_nfev=200)
    x, z, cam = unpack(sol.x)
    dof = max(1, sol.fun.size - sol.x.size)
    sigma2 = float(np.sum(sol.fun**2) / dof)
    std = np.full(6, np.nan)
    try:
        cov = np.linalg.pinv(sol.jac.T @ sol.jac) * sigma2
        s = np.sqrt(np.clip(np.diag(cov)[:6], 0, None))
        std = np.concatenate([np.degrees(s[:3]), s[3:6]])
    except np.linalg.LinAlgError:
        logger.debug("hand-eye covariance singular")
    res = _chain_residuals(views, cam, x, z)

    def cost_residuals(xx: NDArray, zz: NDArray) -> list[NDArray]:
        return _chain_residuals(views, cam, xx, zz)

    return _Fit(x, z, std, res, cost_residuals, cam)
