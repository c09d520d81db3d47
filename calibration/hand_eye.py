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

The parts: :mod:`calibration.hand_eye_views` (posed views, the result, the checks and the
closed forms), :mod:`calibration.hand_eye_adjust` (the two adjustments and the robot test)
and :mod:`calibration.hand_eye_paper`; :func:`calibrate_hand_eye` here runs the default and
closed-form methods.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calibration.extrinsics import project_target
from calibration.hand_eye_adjust import (
    ROBOT_TEST_ALPHA,
    _adjust,
    _adjust_robot_space,
    _chain_residuals,
    _held_out_rms,
    _rms,
    robot_errors_depend_on_pose,
)
from calibration.hand_eye_paper import StripePointView, paper_hand_eye
from calibration.hand_eye_views import (
    CLOSED_FORM_METHODS,
    HandEyeResult,
    PosedView,
    _per_view_poses,
    average_transforms,
    check_robot_motion,
    closed_form_hand_eye,
    fix_label_flips,
    pose_convention_warnings,
)
from scanner.core.camera import CameraModel
from scanner.core.conventions import angle_between_rotations_deg, invert_transform

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
