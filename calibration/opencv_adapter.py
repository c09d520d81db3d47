"""The one adapter between our ``a_from_b`` transforms and OpenCV's hand-eye names.

OpenCV names a transform after the motion of a frame (``R_gripper2base`` maps gripper
coordinates into the base frame). Translated once, here:

==========================  ===================
OpenCV                      this code base
==========================  ===================
``gripper2base``            ``base_from_flange``
``target2cam``              ``cam_from_target``
``cam2gripper``             ``flange_from_cam``
``base2gripper``            ``flange_from_base``
``world2cam``               ``cam_from_target`` (the world is the fixed target)
``base2world``              ``target_from_base``
``gripper2cam``             ``cam_from_flange``
==========================  ===================

Nothing outside this module uses OpenCV's names.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanner.core.conventions import invert_transform, make_transform, orthonormalize

__all__ = [
    "AX_XB_METHODS",
    "AX_ZB_METHODS",
    "hand_eye_ax_xb",
    "robot_world_hand_eye_ax_zb",
]

logger = logging.getLogger(__name__)

#: The five AX=XB solvers of ``cv2.calibrateHandEye``.
AX_XB_METHODS: dict[str, int] = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}

#: The two AX=ZB solvers of ``cv2.calibrateRobotWorldHandEye``.
AX_ZB_METHODS: dict[str, int] = {
    "shah": cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH,
    "li": cv2.CALIB_ROBOT_WORLD_HAND_EYE_LI,
}


def _split(transforms: NDArray) -> tuple[list[NDArray], list[NDArray]]:
    rot = [np.ascontiguousarray(t[:3, :3], dtype=np.float64) for t in transforms]
    trans = [np.ascontiguousarray(t[:3, 3].reshape(3, 1), dtype=np.float64) for t in transforms]
    return rot, trans


def _stack(transforms: Sequence[ArrayLike] | NDArray, name: str) -> NDArray:
    arr = np.asarray(transforms, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected shape (N, 4, 4), got {arr.shape}")
    return arr


def _checked_poses(
    base_from_flange: Sequence[ArrayLike] | NDArray,
    cam_from_target: Sequence[ArrayLike] | NDArray,
    method: str,
    methods: Mapping[str, int],
) -> tuple[NDArray, NDArray]:
    """The robot and camera poses as ``(N, 4, 4)`` stacks, checked for one of ``methods``.

    Raises
    ------
    ValueError
        Unknown method, poses of the wrong shape, mismatched counts or fewer than 3 poses.
    """
    if method not in methods:
        raise ValueError(f"method: expected one of {', '.join(methods)}, got {method!r}")
    bf = _stack(base_from_flange, "base_from_flange")
    ct = _stack(cam_from_target, "cam_from_target")
    if len(bf) != len(ct) or len(bf) < 3:
        raise ValueError(
            f"expected the same number (>= 3) of robot and camera poses, got {len(bf)} and {len(ct)}"
        )
    return bf, ct


def _as_transform(rot: NDArray, trans: NDArray) -> NDArray:
    return make_transform(orthonormalize(np.asarray(rot)), np.asarray(trans).reshape(3))


def hand_eye_ax_xb(
    base_from_flange: Sequence[ArrayLike] | NDArray,
    cam_from_target: Sequence[ArrayLike] | NDArray,
    method: str = "park",
) -> NDArray:
    """Solve ``flange_from_cam`` with one of OpenCV's AX=XB solvers.

    Parameters
    ----------
    base_from_flange : array_like, shape (N, 4, 4)
        Robot flange poses, mm.
    cam_from_target : array_like, shape (N, 4, 4)
        Target pose seen by the camera in the same N stops (target fixed in the base).
    method : str
        One of :data:`AX_XB_METHODS`.

    Returns
    -------
    ndarray, shape (4, 4)
        ``flange_from_cam``.

    Raises
    ------
    ValueError
        Unknown method, mismatched counts, fewer than 3 poses, or OpenCV failing.
    """
    bf, ct = _checked_poses(base_from_flange, cam_from_target, method, AX_XB_METHODS)
    r_g2b, t_g2b = _split(bf)
    r_t2c, t_t2c = _split(ct)
    try:
        r_c2g, t_c2g = cv2.calibrateHandEye(
            r_g2b, t_g2b, r_t2c, t_t2c, method=AX_XB_METHODS[method]
        )
    except cv2.error as exc:
        raise ValueError(f"OpenCV hand-eye ({method}) failed: {exc.err}") from None
    out = _as_transform(r_c2g, t_c2g)
    if not np.all(np.isfinite(out)):
        raise ValueError(f"OpenCV hand-eye ({method}) returned non-finite values")
    return out


def robot_world_hand_eye_ax_zb(
    base_from_flange: Sequence[ArrayLike] | NDArray,
    cam_from_target: Sequence[ArrayLike] | NDArray,
    method: str = "shah",
) -> tuple[NDArray, NDArray]:
    """Solve ``flange_from_cam`` and ``base_from_target`` with OpenCV's AX=ZB solvers.

    Parameters
    ----------
    base_from_flange, cam_from_target : array_like, shape (N, 4, 4)
        As :func:`hand_eye_ax_xb`.
    method : str
        ``"shah"`` or ``"li"``.

    Returns
    -------
    flange_from_cam, base_from_target : ndarray, shape (4, 4) each
    """
    bf, ct = _checked_poses(base_from_flange, cam_from_target, method, AX_ZB_METHODS)
    flange_from_base = np.stack([invert_transform(t) for t in bf])
    r_w2c, t_w2c = _split(ct)
    r_b2g, t_b2g = _split(flange_from_base)
    try:
        r_b2w, t_b2w, r_g2c, t_g2c = cv2.calibrateRobotWorldHandEye(
            r_w2c, t_w2c, r_b2g, t_b2g, method=AX_ZB_METHODS[method]
        )
    except cv2.error as exc:
        raise ValueError(f"OpenCV robot-world hand-eye ({method}) failed: {exc.err}") from None
    target_from_base = _as_transform(r_b2w, t_b2w)
    cam_from_flange = _as_transform(r_g2c, t_g2c)
    return invert_transform(cam_from_flange), invert_transform(target_from_base)
