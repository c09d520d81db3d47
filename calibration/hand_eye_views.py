"""Hand-eye inputs and result: posed views, their checks, label flips and the closed forms.

A :class:`PosedView` is one robot pose with the fixed target's features seen from it;
:class:`HandEyeResult` is what every hand-eye method returns. Before any solve, the flange
poses are checked for enough rotation about enough axes (:func:`check_robot_motion`) and for
unit or convention mistakes (:func:`pose_convention_warnings`), and grids numbered from the
opposite corner are relabelled (:func:`fix_label_flips`). :func:`closed_form_hand_eye` runs
one of OpenCV's AX=XB or AX=ZB solvers (through :mod:`calibration.opencv_adapter`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from calibration.extrinsics import estimate_pose
from calibration.opencv_adapter import (
    AX_XB_METHODS,
    AX_ZB_METHODS,
    hand_eye_ax_xb,
    robot_world_hand_eye_ax_zb,
)
from scanner.core.camera import CameraModel
from scanner.core.conventions import invert_transform, make_transform

__all__ = [
    "CLOSED_FORM_METHODS",
    "MIN_AXIS_SPREAD_DEG",
    "MIN_ROTATION_DEG",
    "HandEyeResult",
    "PosedView",
    "average_transforms",
    "check_robot_motion",
    "closed_form_hand_eye",
    "fix_label_flips",
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
    pose_covariance : ndarray, shape (6, 6) or None
        Covariance of ``cam_from_target`` from the adjustment that gave it: small turns of
        the camera frame (rad, see :func:`calibration.extrinsics.pose_covariance_as_turns`)
        and translation (mm). None: from the PnP residuals of ``points_px``, which must
        then be the detected features, not ones projected from the pose.
    """

    frame_id: int
    base_from_flange: NDArray
    points_px: NDArray
    points_target: NDArray
    cam_from_target: NDArray | None = None
    pose_covariance: NDArray | None = None


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
        axis) and, where some view's pose covariance came from its PnP residuals,
        ``image_px`` (feature noise, per coordinate); empty otherwise.
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
