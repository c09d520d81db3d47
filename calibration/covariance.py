"""The calibration's joint uncertainty: the covariance the calibration file carries.

Three sources, added:

- **The intrinsics and what follows from them.** The intrinsics' covariance (from their
  adjustment) is taken along its principal directions; along each, the camera is moved by one
  sigma, every view's target pose is re-estimated with it from the same detections, and the
  light plane and hand-eye are solved again. The intrinsics' change and the changes it causes
  downstream form one column of the chain's square root, so their correlations are kept (a
  focal length that is too long gives target poses too far away and a plane that partly
  compensates: what reaches a measurement is the net effect, not both).
- **The light plane's own scatter**: a delete-a-group jackknife over its laser frames (each
  frame's stripe shares that frame's target-pose error, so points of a frame are not
  independent: the frames are).
- **The hand-eye's own scatter**: the same jackknife over the posed views.

The robot's repeatability is the hand-eye adjustment's own estimate. The result is a
:class:`~scanner.formats.calibration_covariance.CalibrationCovariance`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from calibration.extrinsics import estimate_pose
from calibration.hand_eye import calibrate_hand_eye
from calibration.hand_eye_views import HandEyeResult, PosedView
from calibration.intrinsics import IntrinsicsResult
from calibration.intrinsics_adjust import PARAM_NAMES
from calibration.light_plane import LaserView, LightPlaneResult, calibrate_light_plane
from scanner.core.camera import CameraModel
from scanner.formats.calibration_covariance import (
    PARAMETERS,
    CalibrationCovariance,
    camera_correction,
    plane_correction,
)

__all__ = ["estimate_covariance", "intrinsics_covariance_matrix", "jackknife_covariance"]

logger = logging.getLogger(__name__)

#: Groups of the delete-a-group jackknife (at most; fewer when there are fewer frames).
JACKKNIFE_GROUPS = 10


def intrinsics_covariance_matrix(intrinsics: IntrinsicsResult) -> NDArray:
    """``(9, 9)`` covariance of ``PARAM_NAMES`` from the adjustment's std and correlation
    (a parameter held fixed, or without a figure, has zero variance)."""
    sd = np.array([float(intrinsics.std.get(name, 0.0)) for name in PARAM_NAMES])
    sd = np.where(np.isfinite(sd), sd, 0.0)
    corr = np.nan_to_num(np.asarray(intrinsics.correlation, dtype=np.float64))
    corr = 0.5 * (corr + corr.T)
    np.fill_diagonal(corr, 1.0)
    return corr * np.outer(sd, sd)


def jackknife_covariance(estimates: NDArray) -> NDArray:
    """Delete-a-group jackknife covariance ``(P, P)`` from ``(G, P)`` leave-one-group-out
    estimates."""
    g = len(estimates)
    dev = estimates - estimates.mean(axis=0)
    return (g - 1) / g * dev.T @ dev


def _groups(n: int) -> list[NDArray]:
    return [a for a in np.array_split(np.arange(n), min(n, JACKKNIFE_GROUPS)) if a.size]


def _repose(
    camera: CameraModel, targets: dict[int, tuple[NDArray, NDArray]], fallback: dict[int, NDArray]
) -> dict[int, NDArray]:
    """Every view's target pose re-estimated with ``camera`` from the same detections."""
    out = {}
    for fid, (px, pts) in targets.items():
        pose = estimate_pose(px, pts, camera)
        out[fid] = pose.cam_from_target if pose else fallback[fid]
    return out


def estimate_covariance(
    camera: CameraModel,
    intrinsics: IntrinsicsResult,
    targets: dict[int, tuple[NDArray, NDArray]],
    laser_views: Sequence[LaserView],
    plane: LightPlaneResult | None,
    posed_views: Sequence[PosedView],
    hand_eye: HandEyeResult,
    *,
    check_cancelled: Callable[[], None] | None = None,
) -> CalibrationCovariance:
    """The calibration's covariance over the corrections of
    :data:`~scanner.formats.calibration_covariance.PARAMETERS`.

    Parameters
    ----------
    camera : CameraModel
        The calibrated camera.
    intrinsics : IntrinsicsResult
        Its adjustment (std and correlation of ``PARAM_NAMES``).
    targets : dict of int to (ndarray (N, 2), ndarray (N, 3))
        Each view's detected pixels and target points, by frame id (for re-estimating poses).
    laser_views : sequence of LaserView
        The light plane's views (empty for a camera-only calibration).
    plane : LightPlaneResult or None
        The light plane solved from them (``None``: camera-only).
    posed_views : sequence of PosedView
        The hand-eye's views.
    hand_eye : HandEyeResult
        The hand-eye solved from them (its robot repeatability is used).
    check_cancelled : callable, optional
        Called before each re-solve (each intrinsics direction, each jackknife group):
        whatever it raises stops the estimate and comes out of this function (a PLC job's
        cancellation), within one re-solve.

    Returns
    -------
    CalibrationCovariance
    """
    check = check_cancelled or (lambda: None)
    f0 = np.asarray(hand_eye.flange_from_cam, dtype=np.float64)
    p0 = None if plane is None or not plane else plane.plane
    poses0 = {v.frame_id: v.cam_from_target for v in laser_views}
    poses0.update({v.frame_id: v.cam_from_target for v in posed_views})

    def solve(
        cam: CameraModel, lviews: Sequence[LaserView], pviews: Sequence[PosedView]
    ) -> NDArray | None:
        """``(6,)`` or ``(9,)`` deltas of (plane, hand-eye) from the references, or None."""
        out = []
        if p0 is not None:
            pl = calibrate_light_plane(lviews, cam)
            if not pl:
                return None
            out.append(plane_correction(pl.plane.normal, pl.plane.d, p0.normal, p0.d))  # type: ignore[arg-type]
        else:
            out.append(np.zeros(3))
        he = calibrate_hand_eye(pviews, cam, "default")
        if not he:
            return None
        out.append(camera_correction(he.flange_from_cam, f0))  # type: ignore[arg-type]
        return np.concatenate(out)

    def reposed(cam: CameraModel) -> tuple[list[LaserView], list[PosedView]]:
        poses = _repose(cam, targets, poses0)
        lv = [
            replace(v, cam_from_target=poses.get(v.frame_id, v.cam_from_target))
            for v in laser_views
        ]
        pv = [
            replace(v, cam_from_target=poses.get(v.frame_id, v.cam_from_target))
            for v in posed_views
        ]
        return lv, pv

    parts: list[str] = []
    cov = np.zeros((len(PARAMETERS), len(PARAMETERS)))
    # 1. intrinsics, carried through the chain
    # the intrinsics' block alone, through the same square root the readers use
    intrinsics_only = np.zeros((len(PARAMETERS), len(PARAMETERS)))
    intrinsics_only[:9, :9] = intrinsics_covariance_matrix(intrinsics)
    dirs = CalibrationCovariance(intrinsics_only).principal_directions(rel_tol=1e-10)[:, :9]
    if len(dirs):
        base = solve(camera, *reposed(camera))
        columns = []
        for s in dirs:
            check()
            cam = CameraModel(
                camera.width,
                camera.height,
                camera.K + np.array([[s[0], 0, s[2]], [0, s[1], s[3]], [0, 0, 0]]),
                _add_dist(camera.dist, s[4:9]),
            )
            moved = solve(cam, *reposed(cam)) if base is not None else None
            downstream = np.zeros(9) if moved is None else moved - base  # type: ignore[operator]
            columns.append(np.concatenate([s, downstream]))
        chain = np.array(columns)
        cov += chain.T @ chain
        parts.append(f"intrinsics through the chain ({len(dirs)} directions)")

    # 2. the light plane's own scatter, jackknifed over its frames
    if p0 is not None and len(laser_views) >= 3:
        est = []
        for g in _groups(len(laser_views)):
            check()
            keep_views = [lv for i, lv in enumerate(laser_views) if i not in set(g.tolist())]
            pl = calibrate_light_plane(keep_views, camera)
            if pl:
                est.append(plane_correction(pl.plane.normal, pl.plane.d, p0.normal, p0.d))  # type: ignore[arg-type]
        if len(est) >= 3:
            cov[9:12, 9:12] += jackknife_covariance(np.array(est))
            parts.append(f"light plane jackknifed over {len(est)} groups of frames")

    # 3. the hand-eye's own scatter, jackknifed over its views
    if len(posed_views) >= 6:
        est = []
        for g in _groups(len(posed_views)):
            check()
            drop = set(g.tolist())
            he = calibrate_hand_eye(
                [pv for i, pv in enumerate(posed_views) if i not in drop], camera, "default"
            )
            if he:
                est.append(camera_correction(he.flange_from_cam, f0))  # type: ignore[arg-type]
        if len(est) >= 3:
            cov[12:18, 12:18] += jackknife_covariance(np.array(est))
            parts.append(f"hand-eye jackknifed over {len(est)} groups of views")

    robot = hand_eye.robot_repeatability or {}
    return CalibrationCovariance(
        matrix=cov,
        robot_rotation_deg=float(robot.get("rotation_deg", 0.0)),
        robot_translation_mm=float(robot.get("translation_mm", 0.0)),
        method="; ".join(parts) or "none estimated",
    )


def _add_dist(dist: NDArray, delta5: NDArray) -> NDArray:
    out = np.array(dist, dtype=np.float64).reshape(-1)
    if out.size < 5:
        out = np.concatenate([out, np.zeros(5 - out.size)])
    out[:5] += delta5
    return out
