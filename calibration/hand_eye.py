"""Hand-eye calibration: ``flange_from_cam`` (the paper's T_ec) and the fixed target's pose.

With the target fixed in the base frame, every posed view i closes the chain::

    base_from_target = base_from_flange[i] @ flange_from_cam @ cam_from_target[i]

Methods
-------
``default``
    Initialise from the best closed form (OpenCV's five AX=XB solvers and two AX=ZB solvers,
    through :mod:`calibration.opencv_adapter`), then one joint nonlinear adjustment of
    ``flange_from_cam`` and ``base_from_target`` (robust loss). Its cost (``cost``):

    ``"auto"`` (default)
        The robot cost, unless the data refute its model: when the robot's misses depend on
        its pose (:func:`robot_errors_depend_on_pose`), they are absolute-accuracy errors,
        not repeatability, and the image cost is used, with a warning. On the virtual cells
        (plain repeatability) the robot cost gives 0.002 deg / 0.01 mm against 0.045 deg /
        0.24 mm for the image cost (modern cell, hand-held views reaching the corners); on
        the real kuka_1 robot (misses of ~0.5 mm that follow the pose, p ~ 5e-14) the image
        cost reprojects the chain better (2.38 px against 2.72 px). Which cost predicts
        held-out views better does not tell them apart: on simulated repeatability the image
        cost sometimes predicts better with a hand-eye 0.2 deg off.
    ``"robot"``
        Every robot pose missed by an unknown flange motion ``E_i``, held to the robot's
        repeatability; each view's own target pose (all its features) fixes ``E_i`` given X
        and Z, so the cost is the sum of the whitened misses. The rotation and translation
        repeatability are variance components estimated from the data (reported in
        ``robot_repeatability``). With a well-calibrated camera the robot's repeatability
        dominates (0.005 deg of flange rotation moves the target ~0.2 px at 350 mm, ten times
        the image noise of the pose); the image cost then trades a rotation of X against a
        translation (the target's image barely tells them apart) and lets the robot's error
        leak into both.
    ``"image"``
        The image residuals of every target feature in every posed view; the intrinsics can
        be refined too (``refine_intrinsics``, which selects this cost).
``tsai``, ``park``, ``horaud``, ``andreff``, ``daniilidis``, ``shah``, ``li``
    The OpenCV baselines alone.
``paper``
    Section III.D: stripe on O, A and C; their base-frame positions from eqs. (12)-(13);
    ``base_from_target`` built from O, A, C; ``T_ec = T_o6O^-1 T_ow T_wcO``
    (:func:`paper_hand_eye`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration.extrinsics import estimate_pose, project_target
from calibration.opencv_adapter import (
    AX_XB_METHODS,
    AX_ZB_METHODS,
    hand_eye_ax_xb,
    robot_world_hand_eye_ax_zb,
)
from scanner.core.camera import CameraModel
from scanner.core.conventions import (
    angle_between_rotations_deg,
    invert_transform,
    make_transform,
    orthonormalize,
    transform_points,
)

__all__ = [
    "CLOSED_FORM_METHODS",
    "HandEyeResult",
    "PosedView",
    "StripePointView",
    "average_transforms",
    "calibrate_hand_eye",
    "check_robot_motion",
    "closed_form_hand_eye",
    "fix_label_flips",
    "paper_hand_eye",
    "pose_convention_warnings",
]

logger = logging.getLogger(__name__)

CLOSED_FORM_METHODS = (*AX_XB_METHODS, *AX_ZB_METHODS)

#: Refuse when no two poses differ by more than this rotation.
MIN_ROTATION_DEG = 2.0
#: Refuse when every relative rotation axis lies within this angle of one line.
MIN_AXIS_SPREAD_DEG = 3.0


@dataclass
class PosedView:
    """One posed view of the fixed target.

    Attributes
    ----------
    frame_id : int
    base_from_flange : ndarray, shape (4, 4)
    points_px : ndarray, shape (N, 2)
        Detected features, distorted pixels.
    points_target : ndarray, shape (N, 3)
        The same features in the target frame, mm.
    cam_from_target : ndarray, shape (4, 4) or None
        The view's own pose estimate (computed by PnP when None).
    """

    frame_id: int
    base_from_flange: NDArray
    points_px: NDArray
    points_target: NDArray
    cam_from_target: NDArray | None = None


@dataclass
class HandEyeResult:
    """A hand-eye solution, or a failed one (falsy) whose ``reason`` says why.

    Attributes
    ----------
    flange_from_cam, base_from_target : ndarray, shape (4, 4) or None
    method : str
    rms_px : float
        Reprojection RMS of every feature through the whole chain (robot pose, hand-eye,
        target in base, intrinsics).
    per_pose : list of dict
        ``frame_id``, ``rms_px``, ``target_dt_mm``, ``target_dr_deg`` (how far the view's own
        target pose, carried into the base, lies from ``base_from_target``).
    std_rotation_deg, std_translation_mm : ndarray, shape (3,)
        One-sigma uncertainty of ``flange_from_cam`` (rotation about the camera axes,
        translation), NaN for closed forms. The rotation's includes the principal point's
        share when its uncertainty was given.
    target_spread_mm : ndarray, shape (3,)
        Standard deviation (x, y, z) of the target origin in the base frame across views.
    camera : CameraModel or None
        The camera after the adjustment (changed only when intrinsics were refined).
    warnings : list of str
    candidates : dict
        Closed-form candidates tried: name -> chain reprojection RMS, px.
    robot_repeatability : dict
        Estimated by the ``"robot"`` adjustment (also when ``"auto"`` then used the image
        cost): ``rotation_deg`` and ``translation_mm`` (the robot's misses, one sigma per
        axis) and ``image_px`` (feature noise, per coordinate); empty otherwise.
    """

    ok: bool
    reason: str = ""
    flange_from_cam: NDArray | None = None
    base_from_target: NDArray | None = None
    method: str = ""
    rms_px: float = float("nan")
    per_pose: list[dict[str, Any]] = field(default_factory=list)
    std_rotation_deg: NDArray = field(default_factory=lambda: np.full(3, np.nan))
    std_translation_mm: NDArray = field(default_factory=lambda: np.full(3, np.nan))
    target_spread_mm: NDArray = field(default_factory=lambda: np.full(3, np.nan))
    camera: CameraModel | None = None
    warnings: list[str] = field(default_factory=list)
    candidates: dict[str, float] = field(default_factory=dict)
    robot_repeatability: dict[str, float] = field(default_factory=dict)
    held_out_rms_px: float = float("nan")
    robot_test_p: float = float("nan")

    def __bool__(self) -> bool:
        return self.ok

    def quality(self) -> dict[str, Any]:
        """JSON-ready summary for the calibration file's ``quality``."""
        return {
            "method": self.method,
            "rms_px": self.rms_px,
            "std_rotation_deg": self.std_rotation_deg.tolist(),
            "std_translation_mm": self.std_translation_mm.tolist(),
            "target_spread_mm": self.target_spread_mm.tolist(),
            "base_from_target": None
            if self.base_from_target is None
            else self.base_from_target.tolist(),
            "per_pose": self.per_pose,
            "candidates_rms_px": self.candidates,
            "robot_repeatability": dict(self.robot_repeatability),
            "held_out_rms_px": self.held_out_rms_px,
            "robot_test_p": self.robot_test_p,
            "warnings": list(self.warnings),
        }


def average_transforms(transforms: Sequence[NDArray] | NDArray) -> NDArray:
    """Mean rigid transform: chordal mean rotation and mean translation, ``(4, 4)``."""
    arr = np.asarray(transforms, dtype=np.float64)
    rot = Rotation.from_matrix(arr[:, :3, :3]).mean()
    return make_transform(rot, arr[:, :3, 3].mean(axis=0))


def check_robot_motion(base_from_flange: NDArray) -> str | None:
    """Why a set of flange poses cannot determine a hand-eye transform, or None.

    Parameters
    ----------
    base_from_flange : ndarray, shape (N, 4, 4)

    Returns
    -------
    str or None
        A reason: fewer than 3 poses, too little rotation, or all relative rotations about
        parallel axes (the translation along that axis is then unobservable).
    """
    n = len(base_from_flange)
    if n < 3:
        return f"hand-eye needs at least 3 posed views, got {n}"
    rots = Rotation.from_matrix(base_from_flange[:, :3, :3])
    axes = []
    max_angle = 0.0
    for i in range(n):
        rel = (rots[i].inv() * rots[i + 1 :]).as_rotvec() if i + 1 < n else np.zeros((0, 3))
        ang = np.linalg.norm(rel, axis=1)
        if len(ang):
            max_angle = max(max_angle, float(np.degrees(ang.max())))
        for v, a in zip(rel, ang):
            if np.degrees(a) > 1.0:
                axes.append(v / a)
    if max_angle < MIN_ROTATION_DEG:
        return (
            f"degenerate robot motion: expected rotations of at least {MIN_ROTATION_DEG} deg "
            f"between poses, got at most {max_angle:.2f} deg"
        )
    ax = np.asarray(axes)
    # Sign-free principal direction of the axes; spread = largest angle off it.
    _, _, vt = np.linalg.svd(ax)
    cosines = np.abs(ax @ vt[0])
    spread = float(np.degrees(np.arccos(np.clip(cosines.min(), -1, 1))))
    if spread < MIN_AXIS_SPREAD_DEG:
        return (
            "degenerate robot motion: every rotation between poses is about (nearly) the same "
            f"axis (within {spread:.2f} deg); rotate about at least two different axes"
        )
    return None


def _ax_xb_residual_mm(base_from_flange: NDArray, cam_from_target: NDArray, x: NDArray) -> float:
    """RMS of the translation part of ``A X - X B`` over consecutive pose pairs, mm."""
    res = []
    for i in range(len(base_from_flange) - 1):
        a = invert_transform(base_from_flange[i + 1]) @ base_from_flange[i]
        b = cam_from_target[i + 1] @ invert_transform(cam_from_target[i])
        res.append(((a @ x) - (x @ b))[:3, 3])
    return float(np.sqrt(np.mean(np.square(res))))


def pose_convention_warnings(base_from_flange: NDArray, cam_from_target: NDArray) -> list[str]:
    """Warnings for robot poses that look like a unit or convention mistake.

    Metres given as millimetres (every position under 5), or the inverse transform given
    (``flange_from_base``): AX=XB is solved with the poses as given and inverted, and the
    inverted ones fitting far better is reported.
    """
    warnings = []
    pos = base_from_flange[:, :3, 3]
    if np.all(np.abs(pos) < 5.0):
        warnings.append(
            "robot positions are all under 5 in size: they look like metres, expected mm"
        )
    try:
        x_given = hand_eye_ax_xb(base_from_flange, cam_from_target, "park")
        inv = np.stack([invert_transform(t) for t in base_from_flange])
        x_inv = hand_eye_ax_xb(inv, cam_from_target, "park")
        r_given = _ax_xb_residual_mm(base_from_flange, cam_from_target, x_given)
        r_inv = _ax_xb_residual_mm(inv, cam_from_target, x_inv)
        if r_inv < 0.2 * r_given and r_given > 1.0:
            warnings.append(
                f"robot poses fit AX=XB far better inverted ({r_inv:.2f} mm vs {r_given:.2f} mm): "
                "they look like flange_from_base, expected base_from_flange"
            )
    except ValueError as exc:
        logger.debug("convention check skipped: %s", exc)
    return warnings


def closed_form_hand_eye(
    base_from_flange: NDArray, cam_from_target: NDArray, method: str
) -> tuple[NDArray, NDArray]:
    """``(flange_from_cam, base_from_target)`` from one OpenCV closed form.

    For the AX=XB solvers ``base_from_target`` is the mean of the per-view chains.
    """
    if method in AX_ZB_METHODS:
        return robot_world_hand_eye_ax_zb(base_from_flange, cam_from_target, method)
    x = hand_eye_ax_xb(base_from_flange, cam_from_target, method)
    chains = base_from_flange @ x @ cam_from_target
    return x, average_transforms(chains)


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
    """The view's own pose uncertainty: ``(6, 6)`` covariance of ``cam_from_target``'s (rvec,
    tvec) per unit image variance, and its PnP residual sum of squares with its dof."""
    ct = view.cam_from_target
    rvec = Rotation.from_matrix(ct[:3, :3]).as_rotvec()  # type: ignore[index]
    obj = np.ascontiguousarray(view.points_target.reshape(-1, 1, 3))
    proj, jac = cv2.projectPoints(obj, rvec, ct[:3, 3], camera.K, camera.dist)  # type: ignore[index]
    j = jac[:, :6]
    r = proj.reshape(-1, 2) - view.points_px
    return np.linalg.pinv(j.T @ j), float(np.sum(r**2)), max(1, 2 * len(view.points_px) - 6)


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
    """Adjustment with each robot pose's own error; see the module's ``"robot"`` cost.

    Every view's target pose from its image, ``C_i``, is far more precise than the robot's
    pose (a whole target's features pin it), so the unknown miss of each robot pose follows
    from X and Z in closed form, ``E_i = inv(B_i) Z inv(C_i) inv(X)``. The cost is the sum of
    ``E_i``'s whitened squares, its covariance the robot's repeatability (rotation
    ``sigma_r``, translation ``sigma_t``, per axis in the flange frame) plus ``C_i``'s own
    uncertainty carried into ``E_i``. ``sigma_r`` and ``sigma_t`` are variance components
    re-estimated from the misses until they settle: the data say how good the robot is.
    Twelve unknowns and six residuals per view: a fraction of a second.
    """
    n = len(views)
    flange_from_base = np.stack([invert_transform(v.base_from_flange) for v in views])
    cam_from_target = np.stack([v.cam_from_target for v in views])  # type: ignore[misc]
    target_from_cam = np.stack([invert_transform(c) for c in cam_from_target])
    covs, sums, dofs = zip(*[_pose_covariance(v, camera) for v in views])
    pose_cov = np.stack(covs)
    var_px = max(sum(sums) / sum(dofs), 1e-6)  # image noise per coordinate, px^2

    def unpack(p: NDArray) -> tuple[NDArray, NDArray]:
        return _perturbed(x0, z0, p)

    def pose_to_miss(x: NDArray, z: NDArray) -> NDArray:
        """``(n, 6, 6)`` derivative of each miss by its view's (rvec, tvec)."""
        base = _robot_misses(x, z, flange_from_base, target_from_cam)
        g = np.zeros((n, 6, 6))
        rvecs = Rotation.from_matrix(cam_from_target[:, :3, :3]).as_rotvec()
        step = 1e-6
        for k in range(6):
            d = np.zeros(6)
            d[k] = step
            moved = np.stack(
                [
                    invert_transform(
                        make_transform(Rotation.from_rotvec(r + d[:3]), c[:3, 3] + d[3:])
                    )
                    for r, c in zip(rvecs, cam_from_target)
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
        from_image = var_px * np.einsum("nij,njk,nlk->nil", g, pose_cov, g)
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
        "image_px": float(np.sqrt(var_px)),
    }
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


def _grid_flip_order(points_target: NDArray) -> NDArray | None:
    """Index order that relabels a point grid rotated by 180 degrees in its plane, or None.

    A chessboard or circle grid detector may number the same board from the opposite corner
    in some images. Reversing a row-major grid's order is exactly that rotation; it applies
    when the reversed points are the points turned by 180 degrees about their centre.
    """
    n = len(points_target)
    if n < 4:
        return None
    c = points_target.mean(axis=0)
    order = np.arange(n)[::-1]
    turned = 2 * c - points_target
    turned[:, 2] = points_target[:, 2]
    if np.allclose(points_target[order], turned, atol=1e-6):
        return order
    return None


def _rotation_angle(t: NDArray) -> float:
    return float(Rotation.from_matrix(t[:3, :3]).magnitude())


def fix_label_flips(
    views: Sequence[PosedView], camera: CameraModel
) -> tuple[list[PosedView], list[int]]:
    """Relabel views whose grid detection came back turned by 180 degrees.

    With the target fixed, the rotation angle of the robot motion between two views equals
    that of the camera motion (``A X = X B`` keeps the angle). A view numbered from the
    opposite corner breaks that equality against the others; relabelling it restores it.

    Returns
    -------
    views : list of PosedView
        With ``points_px`` reordered (and ``cam_from_target`` recomputed) where flipped.
    flipped : list of int
        Frame ids that were relabelled.
    """
    if len(views) < 3 or any(v.cam_from_target is None for v in views):
        return list(views), []
    order = _grid_flip_order(views[0].points_target)
    if order is None or any(len(v.points_target) != len(order) for v in views):
        return list(views), []
    flip = make_transform(Rotation.from_euler("z", 180, degrees=True), np.zeros(3))
    # Turning the labels by 180 degrees about the grid centre c: cam_from_target' =
    # cam_from_target @ T(c) @ Rz(180) @ T(-c).
    c = views[0].points_target.mean(axis=0)
    about_c = make_transform(np.eye(3), c) @ flip @ make_transform(np.eye(3), -c)
    n = len(views)
    cts = [v.cam_from_target for v in views]
    alt = [ct @ about_c for ct in cts]  # type: ignore[operator]
    fl = [v.base_from_flange for v in views]

    def mismatch(i: int, ci: NDArray, j: int, cj: NDArray) -> float:
        a = _rotation_angle(invert_transform(fl[j]) @ fl[i])
        b = _rotation_angle(cj @ invert_transform(ci))
        return abs(a - b)

    # Choose each view's labelling to agree with the majority of the others (two passes).
    state = [False] * n
    for _ in range(2):
        for j in range(n):
            cost = [0.0, 0.0]
            for k in range(n):
                if k == j:
                    continue
                ck = alt[k] if state[k] else cts[k]
                cost[0] += min(mismatch(k, ck, j, cts[j]), 0.5)
                cost[1] += min(mismatch(k, ck, j, alt[j]), 0.5)
            state[j] = cost[1] < cost[0]
    if sum(state) > n / 2:  # keep the majority's numbering
        state = [not s for s in state]
    out, flipped = [], []
    for v, s in zip(views, state):
        if s:
            px = v.points_px[order]
            pose = estimate_pose(px, v.points_target, camera)
            out.append(
                PosedView(v.frame_id, v.base_from_flange, px, v.points_target, pose.cam_from_target)
            )
            flipped.append(int(v.frame_id))
        else:
            out.append(v)
    return out, flipped


def _per_view_poses(
    views: Sequence[PosedView], camera: CameraModel
) -> tuple[list[PosedView], list[str]]:
    kept, rejected = [], []
    for v in views:
        if v.cam_from_target is None:
            pose = estimate_pose(v.points_px, v.points_target, camera)
            if not pose:
                rejected.append(f"frame {v.frame_id}: {pose.reason}")
                continue
            v = PosedView(
                v.frame_id, v.base_from_flange, v.points_px, v.points_target, pose.cam_from_target
            )
        kept.append(v)
    return kept, rejected


def _summaries(
    views: Sequence[PosedView],
    residuals: Sequence[NDArray],
    x: NDArray,
    z: NDArray,
    camera: CameraModel,
) -> tuple[list[dict[str, Any]], NDArray, list[str]]:
    per_pose = []
    origins = []
    warnings = []
    for v, r in zip(views, residuals):
        implied = v.base_from_flange @ x @ v.cam_from_target
        origins.append(implied[:3, 3])
        ct = invert_transform(v.base_from_flange @ x) @ z
        uv = project_target(camera, ct, v.points_target)
        inside = camera.in_image(uv)
        if not np.all(inside):
            warnings.append(
                f"frame {v.frame_id}: {int((~inside).sum())} target features project outside the image"
            )
        per_pose.append(
            {
                "frame_id": int(v.frame_id),
                "rms_px": float(np.sqrt(np.mean(np.sum(r**2, axis=1)))),
                "max_px": float(np.sqrt(np.sum(r**2, axis=1)).max()),
                "target_dt_mm": float(np.linalg.norm(implied[:3, 3] - z[:3, 3])),
                "target_dr_deg": angle_between_rotations_deg(implied, z),
            }
        )
    spread = np.std(np.asarray(origins), axis=0, ddof=1) if len(origins) > 1 else np.zeros(3)
    return per_pose, spread, warnings


def calibrate_hand_eye(
    views: Sequence[PosedView],
    camera: CameraModel,
    method: str = "default",
    refine_intrinsics: bool = False,
    cost: str = "auto",
    principal_point_std_px: tuple[float, float] | None = None,
) -> HandEyeResult:
    """Solve ``flange_from_cam`` and ``base_from_target`` from posed views of the fixed target.

    Parameters
    ----------
    views : sequence of PosedView
        At least 3, with enough rotation about at least two axes.
    camera : CameraModel
        Calibrated intrinsics.
    method : str
        ``"default"`` (closed-form start, then a joint adjustment, see ``cost``) or one of
        :data:`CLOSED_FORM_METHODS` alone.
    refine_intrinsics : bool
        Let the adjustment refine fx, fy, cx, cy and five distortion terms too (needs
        ``cost="image"``; given alone it selects it).
    cost : {"auto", "robot", "image"}
        What the default adjustment minimises (see the module docstring). ``"auto"``: the
        robot cost unless the robot's misses follow its pose.
    principal_point_std_px : (float, float), optional
        The intrinsics' own standard deviations of (cx, cy). A principal-point error turns
        the camera frame, about its y and x axes by ``dcx / fx`` and ``dcy / fy``, and the
        hand-eye rotation with it, a turn no robot motion can reveal (``C_i -> G C_i`` and
        ``X -> X G^-1`` explain the same data; the translation stays). It is added to the
        rotation's standard deviation; on the paper cell it is the larger share.

    Returns
    -------
    HandEyeResult
        Falsy with a reason for too few views, degenerate motion, or solver failure.
    """
    if method != "default" and method not in CLOSED_FORM_METHODS:
        raise ValueError(
            f"method: expected 'default' or one of {', '.join(CLOSED_FORM_METHODS)}, got {method!r}"
        )
    if cost not in ("auto", "robot", "image"):
        raise ValueError(f"cost: expected 'auto', 'robot' or 'image', got {cost!r}")
    if refine_intrinsics:
        cost = "image"  # only image residuals can tell the intrinsics anything
    views, rejected = _per_view_poses(views, camera)
    warnings = list(rejected)
    views, flipped = fix_label_flips(views, camera)
    if flipped:
        warnings.append(f"grid numbered from the opposite corner, relabelled: frames {flipped}")
    if len(views) < 3:
        return HandEyeResult(
            False,
            f"hand-eye needs at least 3 posed views with the target found, got {len(views)}",
            method=method,
            warnings=warnings,
        )
    bf = np.stack([v.base_from_flange for v in views])
    ct = np.stack([v.cam_from_target for v in views])  # type: ignore[misc]
    reason = check_robot_motion(bf)
    if reason:
        return HandEyeResult(False, reason, method=method, warnings=warnings)
    warnings += pose_convention_warnings(bf, ct)

    names = CLOSED_FORM_METHODS if method == "default" else (method,)
    candidates: dict[str, float] = {}
    solutions: dict[str, tuple[NDArray, NDArray]] = {}
    for name in names:
        try:
            x, z = closed_form_hand_eye(bf, ct, name)
        except ValueError as exc:
            warnings.append(f"{name}: {exc}")
            continue
        candidates[name] = _rms(_chain_residuals(views, camera, x, z))
        solutions[name] = (x, z)
    if not solutions:
        return HandEyeResult(
            False, "every closed-form hand-eye solver failed", method=method, warnings=warnings
        )
    best = min(candidates, key=lambda k: candidates[k])
    x, z = solutions[best]
    std_r = np.full(3, np.nan)
    std_t = np.full(3, np.nan)
    cam = camera
    repeatability: dict[str, float] = {}
    robot_test_p = float("nan")
    held_out = float("nan")
    if method == "default":
        chosen = cost
        if cost in ("auto", "robot"):
            fit = _adjust_robot_space(views, camera, x, z)
            repeatability = fit.repeatability
            robot_test_p = robot_errors_depend_on_pose(views, fit)
            if cost == "auto" and robot_test_p < ROBOT_TEST_ALPHA:
                # The robot cost's model (misses independent of the pose) is refuted.
                chosen = "image"
                warnings.append(
                    "the robot's reported poses miss by amounts that depend on the pose "
                    f"(p = {robot_test_p:.2g}; about {repeatability['translation_mm']:.3f} mm and "
                    f"{repeatability['rotation_deg']:.4f} deg per axis): absolute-accuracy errors, "
                    "not repeatability, so the image cost is used; a kinematic calibration of "
                    "the robot would improve scanning accuracy"
                )
            elif cost == "auto":
                chosen = "robot"
        if chosen == "image":
            fit = _adjust(views, camera, x, z, refine_intrinsics)
        held_out = _held_out_rms(views, camera, fit)
        x, z, cam, res = fit.flange_from_cam, fit.base_from_target, fit.camera, fit.residuals
        std_r, std_t = fit.std[:3], fit.std[3:]
        if principal_point_std_px is not None and not refine_intrinsics:
            scx, scy = principal_point_std_px
            gauge = np.degrees([scy / cam.K[1, 1], scx / cam.K[0, 0], 0.0])
            std_r = np.sqrt(std_r**2 + gauge**2)
        label = {
            "robot": "joint adjustment, robot errors",
            "image": "joint adjustment, image residuals",
        }[chosen] + f" (start: {best}"
        if np.isfinite(robot_test_p):
            label += f"; robot misses independent of the pose: p = {robot_test_p:.2g}"
        label += ")"
    else:
        res = _chain_residuals(views, camera, x, z)
        label = method
    per_pose, spread, view_warn = _summaries(views, res, x, z, cam)
    return HandEyeResult(
        True,
        flange_from_cam=x,
        base_from_target=z,
        method=label,
        rms_px=_rms(res),
        per_pose=per_pose,
        std_rotation_deg=std_r,
        std_translation_mm=std_t,
        target_spread_mm=spread,
        camera=cam,
        warnings=warnings + view_warn,
        candidates=candidates,
        robot_repeatability=repeatability,
        held_out_rms_px=held_out,
        robot_test_p=robot_test_p,
    )


@dataclass
class StripePointView:
    """A posed view in which the stripe crosses one of the named target points.

    Attributes
    ----------
    frame_id : int
    name : str
        ``"O"``, ``"A"`` or ``"C"``.
    base_from_flange : ndarray, shape (4, 4)
    point_cam : ndarray, shape (3,)
        The named point in the camera frame: its stripe pixel's ray met with the light plane.
    cam_from_target : ndarray, shape (4, 4) or None
        The view's extrinsics (needed for the reference view aimed at O).
    """

    frame_id: int
    name: str
    base_from_flange: NDArray
    point_cam: NDArray
    cam_from_target: NDArray | None = None


def _linear_hand_eye_from_points(groups: dict[str, list[StripePointView]]) -> NDArray:
    """Closed form for X from fixed points seen at several poses.

    ``F_j X p_j = F_0 X p_0`` for every view j of the same point. Every ``p`` lies in the light
    plane ``n . p + d = 0``, so write ``p = -d n + alpha e1 + beta e2``; then
    ``X p = alpha (R e1) + beta (R e2) + (t - d R n)`` is linear in the nine unknowns
    ``a = R e1``, ``b = R e2``, ``s = t - d R n`` (the 12 entries of R and t are not all
    observable from coplanar points: a linear solve for them has a 3-D null space). R follows
    from ``[a, b, a x b]`` by SVD orthonormalisation, then the translation is re-solved.
    """
    all_p = np.array([v.point_cam for g in groups.values() for v in g])
    centre = all_p.mean(axis=0)
    _, sv, vt = np.linalg.svd(all_p - centre)
    if sv[1] < 1e-6 * max(sv[0], 1e-12):
        raise ValueError("paper hand-eye: the stripe points are collinear")
    e1, e2 = vt[0], vt[1]
    n = np.cross(e1, e2)  # right-handed basis: R n = R e1 x R e2
    if sv[2] > 1e-2 * sv[0]:
        return _linear_hand_eye_general(groups)
    rows, rhs = [], []
    for views in groups.values():
        ref = views[0]
        r_0, t_0 = ref.base_from_flange[:3, :3], ref.base_from_flange[:3, 3]
        a0, b0 = float(e1 @ ref.point_cam), float(e2 @ ref.point_cam)
        for v in views[1:]:
            r_j, t_j = v.base_from_flange[:3, :3], v.base_from_flange[:3, 3]
            aj, bj = float(e1 @ v.point_cam), float(e2 @ v.point_cam)
            rows.append(np.hstack([aj * r_j - a0 * r_0, bj * r_j - b0 * r_0, r_j - r_0]))
            rhs.append(t_0 - t_j)
    a = np.vstack(rows)
    b = np.concatenate(rhs)
    if np.linalg.matrix_rank(a, tol=1e-9 * np.abs(a).max()) < 9:
        raise ValueError("paper hand-eye: the views aimed at O, A and C do not determine T_ec")
    sol = np.linalg.lstsq(a, b, rcond=None)[0]
    ra, rb = sol[:3], sol[3:6]
    rn = np.cross(ra, rb)
    rn /= np.linalg.norm(rn)
    rot = orthonormalize(np.column_stack([ra, rb, rn]) @ np.vstack([e1, e2, n]))
    return _resolve_translation(groups, rot)


def _linear_hand_eye_general(groups: dict[str, list[StripePointView]]) -> NDArray:
    """The same constraints for points in general position: linear in vec(R) and t."""
    rows, rhs = [], []
    for views in groups.values():
        ref = views[0]
        r_0, t_0 = ref.base_from_flange[:3, :3], ref.base_from_flange[:3, 3]
        for v in views[1:]:
            r_j, t_j = v.base_from_flange[:3, :3], v.base_from_flange[:3, 3]
            m = r_j @ np.kron(np.eye(3), v.point_cam) - r_0 @ np.kron(np.eye(3), ref.point_cam)
            rows.append(np.hstack([m, r_j - r_0]))
            rhs.append(t_0 - t_j)
    a = np.vstack(rows)
    if np.linalg.matrix_rank(a, tol=1e-9 * np.abs(a).max()) < 12:
        raise ValueError("paper hand-eye: the views aimed at O, A and C do not determine T_ec")
    sol = np.linalg.lstsq(a, np.concatenate(rhs), rcond=None)[0]
    return _resolve_translation(groups, orthonormalize(sol[:9].reshape(3, 3)))


def _resolve_translation(groups: dict[str, list[StripePointView]], rot: NDArray) -> NDArray:
    """Least-squares translation of X with its rotation fixed."""
    # Re-solve the translation with the rotation fixed.
    rows_t, rhs_t = [], []
    for views in groups.values():
        ref = views[0]
        for v in views[1:]:
            r_j, t_j = v.base_from_flange[:3, :3], v.base_from_flange[:3, 3]
            r_0, t_0 = ref.base_from_flange[:3, :3], ref.base_from_flange[:3, 3]
            rows_t.append(r_j - r_0)
            rhs_t.append(t_0 - t_j - r_j @ rot @ v.point_cam + r_0 @ rot @ ref.point_cam)
    t = np.linalg.lstsq(np.vstack(rows_t), np.concatenate(rhs_t), rcond=None)[0]
    return make_transform(rot, t)


def _point_in_base_eq13(views: list[StripePointView], x: NDArray) -> NDArray:
    """Eqs. (12)-(13): the named point in the base frame, least squares over its views.

    Eq. (12) carries each view's stripe point ``i_c^j`` into the base through
    ``T_o6^j T_o6,0^-1 T_oi' T_wci0`` and ``T_oi' T_wci0 = T_o6,0 T_ec``, so every view gives
    ``i_o = T_o6^j T_ec i_c^j``; eq. (13) solves the stacked system by least squares, whose
    solution is the mean of those chains.
    """
    chains = [transform_points(v.base_from_flange @ x, v.point_cam.reshape(1, 3))[0] for v in views]
    return np.mean(chains, axis=0)


def paper_hand_eye(views: Sequence[StripePointView], radius_mm: float) -> HandEyeResult:
    """The paper's hand-eye (Section III.D) from views with the stripe on O, A and C.

    Parameters
    ----------
    views : sequence of StripePointView
        At least two views per point O, A and C; the first view aimed at O must carry its
        ``cam_from_target`` (the paper's T_cwO, e.g. from :func:`calibration.extrinsics.paper_pose`).
    radius_mm : float
        R = |OA| = |OC|, to report how far the recovered points are from the target's geometry.

    Returns
    -------
    HandEyeResult
        ``flange_from_cam = T_o6O^-1 T_ow T_wcO`` and ``base_from_target = T_ow`` built from
        O, A and C in the base frame; falsy with a reason when a point has too few views.

    Notes
    -----
    Eq. (13) as printed needs ``T_wci0``, which contains the unknown rotation of ``T_ec``.
    The rotation and translation of ``T_ec`` are first taken from the same fixed-point
    constraints ``T_o6^j T_ec i_c^j = T_o6^0 T_ec i_c^0`` (linear in the entries of ``R_ec``,
    SVD-orthonormalised), then O, A and C follow from eqs. (12)-(13) by least squares.
    """
    groups: dict[str, list[StripePointView]] = {"O": [], "A": [], "C": []}
    for v in views:
        if v.name not in groups:
            raise ValueError(f"view {v.frame_id}: expected name O, A or C, got {v.name!r}")
        groups[v.name].append(v)
    for name, g in groups.items():
        if len(g) < 2:
            return HandEyeResult(
                False,
                f"paper hand-eye: expected >= 2 views with the stripe on {name}, got {len(g)}",
                method="paper",
            )
    ref_o = next((v for v in groups["O"] if v.cam_from_target is not None), None)
    if ref_o is None:
        return HandEyeResult(
            False, "paper hand-eye: no view aimed at O has extrinsics", method="paper"
        )
    groups["O"].remove(ref_o)
    groups["O"].insert(0, ref_o)
    bf = np.stack([v.base_from_flange for v in views])
    reason = check_robot_motion(bf)
    if reason:
        return HandEyeResult(False, reason, method="paper")
    try:
        x_lin = _linear_hand_eye_from_points(groups)
    except ValueError as exc:
        return HandEyeResult(False, str(exc), method="paper")
    pts = {name: _point_in_base_eq13(g, x_lin) for name, g in groups.items()}
    o, a, c = pts["O"], pts["A"], pts["C"]
    x_axis = (a - o) / np.linalg.norm(a - o)
    y_axis = c - o
    z_axis = np.cross(x_axis, y_axis)
    z_axis /= np.linalg.norm(z_axis)
    y_axis = np.cross(z_axis, x_axis)
    base_from_target = make_transform(orthonormalize(np.column_stack([x_axis, y_axis, z_axis])), o)
    target_from_cam_o = invert_transform(ref_o.cam_from_target)  # type: ignore[arg-type]
    x = invert_transform(ref_o.base_from_flange) @ base_from_target @ target_from_cam_o
    per_pose = []
    for name, g in groups.items():
        for v in g:
            p_base = transform_points(v.base_from_flange @ x, v.point_cam.reshape(1, 3))[0]
            per_pose.append(
                {
                    "frame_id": int(v.frame_id),
                    "point": name,
                    "point_base_mm": p_base.tolist(),
                    "scatter_mm": float(np.linalg.norm(p_base - pts[name])),
                }
            )
    warnings = []
    for name, p in (("A", a), ("C", c)):
        err = abs(float(np.linalg.norm(p - o)) - radius_mm)
        if err > 1.0:
            warnings.append(f"|O{name}| differs from R = {radius_mm:.3f} mm by {err:.2f} mm")
    spread = np.std([q["point_base_mm"] for q in per_pose if q["point"] == "O"], axis=0, ddof=1)
    return HandEyeResult(
        True,
        flange_from_cam=x,
        base_from_target=base_from_target,
        method="paper",
        per_pose=per_pose,
        target_spread_mm=spread,
        warnings=warnings,
    )
