"""Camera extrinsics: the target's pose in the camera frame, ``cam_from_target``.

Two ways:

* default (:func:`estimate_pose`): every detected target feature (``points_px`` against
  ``points_target``) through ``cv2.solvePnP`` (IPPE for the planar target), refined by
  ``scipy.optimize.least_squares`` on the distorted image residuals of the calibrated camera;
* the paper's (Section III.C, :func:`paper_pose`): rotation from the vanishing points p and q
  of the two diameters (the Rodrigues construction, the four sign cases of its Fig. 6, SVD
  orthonormalisation) and translation from the stripe point on O intersected with the light
  plane.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from scanner.core.camera import CameraModel, intersect_rays_with_plane
from scanner.core.conventions import check_points, make_transform, orthonormalize
from scanner.core.outcome import Outcome
from scanner.formats.calibration_file import LightPlane

__all__ = [
    "PoseResult",
    "estimate_pose",
    "paper_pose",
    "paper_rotation_from_vanishing_points",
    "pose_covariance_as_turns",
    "project_target",
    "rodrigues_align",
]

logger = logging.getLogger(__name__)


@dataclass
class PoseResult(Outcome):
    """``cam_from_target`` of one view, or a failed estimate (falsy) with its ``reason``.

    Attributes
    ----------
    cam_from_target : ndarray, shape (4, 4) or None
    rms_px : float
        Reprojection RMS over the view's features.
    residuals_px : ndarray, shape (N, 2)
        Observed minus projected pixels.
    std_rotation_deg, std_translation_mm : ndarray, shape (3,)
        One-sigma uncertainty of the pose (rotation vector components, translation), from the
        Gauss-Newton covariance scaled by the residual variance.
    """

    cam_from_target: NDArray | None = None
    rms_px: float = float("nan")
    residuals_px: NDArray = field(default_factory=lambda: np.zeros((0, 2)))
    std_rotation_deg: NDArray = field(default_factory=lambda: np.full(3, np.nan))
    std_translation_mm: NDArray = field(default_factory=lambda: np.full(3, np.nan))


def project_target(
    camera: CameraModel, cam_from_target: NDArray, points_target: NDArray
) -> NDArray:
    """Project ``(N, 3)`` target points through ``cam_from_target`` to ``(N, 2)`` pixels."""
    rvec = Rotation.from_matrix(cam_from_target[:3, :3]).as_rotvec()
    uv, _ = cv2.projectPoints(
        np.ascontiguousarray(points_target, dtype=np.float64).reshape(-1, 1, 3),
        rvec,
        cam_from_target[:3, 3].astype(np.float64),
        camera.K,
        camera.dist,
    )
    return uv.reshape(-1, 2)


def pose_covariance_as_turns(rotvec: ArrayLike, covariance: ArrayLike) -> NDArray:
    """A pose's covariance moved from rotation-vector coordinates to small turns of the
    camera frame.

    Parameters
    ----------
    rotvec : array_like, shape (3,)
        The pose's rotation vector (radians), the point the covariance was computed at.
    covariance : array_like, shape (6, 6)
        Covariance of (rotation vector, translation mm).

    Returns
    -------
    ndarray, shape (6, 6)
        Covariance of (``w`` rad, translation mm), where the pose's rotation is
        ``exp(w) R``: the same whichever of a rotation's equivalent vectors gave it, and
        unchanged when the target frame is turned about its origin.
    """
    r = np.asarray(rotvec, dtype=np.float64).reshape(3)
    cov = np.asarray(covariance, dtype=np.float64)
    if cov.shape != (6, 6):
        raise ValueError(f"covariance: expected shape (6, 6), got {cov.shape}")
    base = Rotation.from_rotvec(r).inv()
    step = 1e-7
    jac = np.eye(6)
    for k in range(3):
        d = np.zeros(3)
        d[k] = step
        jac[:3, k] = (Rotation.from_rotvec(r + d) * base).as_rotvec() / step
    return jac @ cov @ jac.T


def estimate_pose(
    points_px: ArrayLike,
    points_target: ArrayLike,
    camera: CameraModel,
    refine: bool = True,
) -> PoseResult:
    """Pose of the target from exact 2-D/3-D correspondences, with the calibrated camera.

    Parameters
    ----------
    points_px : array_like, shape (N, 2)
        Detected (distorted) pixels.
    points_target : array_like, shape (N, 3)
        The same features in the target frame, mm.
    camera : CameraModel
    refine : bool
        Refine the PnP solution with ``least_squares`` (and report its uncertainty).

    Returns
    -------
    PoseResult
        Falsy with a reason when there are fewer than 4 features or PnP fails.
    """
    uv = check_points(points_px, min_count=0, name="points_px", dim=2)
    xyz = check_points(points_target, min_count=0, name="points_target")
    if len(uv) != len(xyz):
        raise ValueError(f"expected as many pixels as target points, got {len(uv)} and {len(xyz)}")
    if len(uv) < 4:
        return PoseResult(False, f"expected >= 4 features for a pose, got {len(uv)}")
    planar = bool(np.ptp(xyz[:, 2]) < 1e-9)
    obj = np.ascontiguousarray(xyz.reshape(-1, 1, 3))
    img = np.ascontiguousarray(uv.reshape(-1, 1, 2))
    try:
        flag = cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_ITERATIVE
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist, flags=flag)
        if ok:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.K, camera.dist, rvec, tvec)
    except cv2.error as exc:
        return PoseResult(False, f"solvePnP failed: {exc.err}")
    if not ok or not np.all(np.isfinite(tvec)):
        return PoseResult(False, "solvePnP found no pose")
    if float(tvec[2, 0]) <= 0:
        return PoseResult(False, "solvePnP put the target behind the camera")
    x0 = np.concatenate([rvec.reshape(3), tvec.reshape(3)])

    def residuals(x: NDArray) -> NDArray:
        proj, _ = cv2.projectPoints(obj, x[:3], x[3:], camera.K, camera.dist)
        return (proj.reshape(-1, 2) - uv).ravel()

    std_r = np.full(3, np.nan)
    std_t = np.full(3, np.nan)
    x = x0
    if refine:
        sol = least_squares(residuals, x0, method="lm", x_scale="jac")
        x = sol.x
        dof = max(1, 2 * len(uv) - 6)
        sigma2 = float(np.sum(sol.fun**2) / dof)
        try:
            cov = np.linalg.inv(sol.jac.T @ sol.jac) * sigma2
            std = np.sqrt(np.clip(np.diag(cov), 0, None))
            std_r, std_t = np.degrees(std[:3]), std[3:]
        except np.linalg.LinAlgError:
            logger.debug("pose covariance singular")
    res = -residuals(x).reshape(-1, 2)
    pose = make_transform(Rotation.from_rotvec(x[:3]), x[3:])
    return PoseResult(
        True,
        cam_from_target=pose,
        rms_px=float(np.sqrt(np.mean(np.sum(res**2, axis=1)))),
        residuals_px=res,
        std_rotation_deg=std_r,
        std_translation_mm=std_t,
    )


def rodrigues_align(n: ArrayLike) -> NDArray:
    """The paper's Rodrigues matrix: the rotation about ``delta = n x z_c`` by the angle eta
    between ``n`` and ``z_c``, ``cos(eta) I + (1 - cos(eta)) delta delta^T + sin(eta) [delta]_x``.

    It maps ``n`` onto ``z_c = (0, 0, 1)``.
    """
    n = np.asarray(n, dtype=np.float64).reshape(3)
    n = n / np.linalg.norm(n)
    z = np.array([0.0, 0.0, 1.0])
    eta = float(np.arccos(np.clip(n @ z, -1.0, 1.0)))
    axis = np.cross(n, z)
    norm = float(np.linalg.norm(axis))
    if norm < 1e-12:
        return np.eye(3) if n[2] > 0 else np.diag([1.0, -1.0, -1.0])
    delta = axis / norm
    skew = np.array([[0, -delta[2], delta[1]], [delta[2], 0, -delta[0]], [-delta[1], delta[0], 0]])
    return np.cos(eta) * np.eye(3) + (1 - np.cos(eta)) * np.outer(delta, delta) + np.sin(eta) * skew


def _direction(camera: CameraModel, vp: ArrayLike) -> NDArray:
    """Camera-frame direction of a vanishing point given as pixel (2,) or homogeneous (3,)."""
    v = np.asarray(vp, dtype=np.float64).reshape(-1)
    if v.shape == (2,):
        # A finite vanishing point: undistort it like any pixel.
        return camera.rays(v.reshape(1, 2))[0]
    if v.shape == (3,):
        if abs(v[2]) > 1e-9 * max(1.0, float(np.abs(v[:2]).max())):
            return camera.rays((v[:2] / v[2]).reshape(1, 2))[0]
        return np.linalg.solve(camera.K, v)  # at infinity: distortion does not apply
    raise ValueError(f"vanishing point: expected 2 or 3 values, got {v.shape}")


def _side(camera: CameraModel, toward_px: ArrayLike, origin_px: ArrayLike, d: NDArray) -> float:
    """+1 when the target point seen at ``toward_px`` lies along +d from the one at ``origin_px``.

    A point O + s d projects onto a ray ``r ~ lambda r_o + s d`` (lambda > 0), so the sign of
    s is the sign of ``(r x r_o) . (d x r_o)``.
    """
    r = camera.rays(np.asarray(toward_px, dtype=np.float64).reshape(1, 2))[0]
    r_o = camera.rays(np.asarray(origin_px, dtype=np.float64).reshape(1, 2))[0]
    s = float(np.cross(r, r_o) @ np.cross(d, r_o))
    return 1.0 if s >= 0 else -1.0


def paper_rotation_from_vanishing_points(
    camera: CameraModel,
    p: ArrayLike,
    q: ArrayLike,
    o_px: ArrayLike,
    a_px: ArrayLike,
    c_px: ArrayLike,
) -> NDArray:
    """``R_cw`` (target axes in the camera frame) from the vanishing points (paper III.C).

    Parameters
    ----------
    camera : CameraModel
    p, q : array_like, shape (2,) or (3,)
        Vanishing points of the diameters AB (target x) and CD (target y): pixels, or
        homogeneous pixels when (nearly) at infinity.
    o_px, a_px, c_px : array_like, shape (2,)
        Image points of O, A and C; they settle the four sign cases of the paper's Fig. 6
        (whether p lies towards a or away from it, and q towards c or away).

    Returns
    -------
    ndarray, shape (3, 3)
        ``R_cw``, a proper rotation (SVD-orthonormalised).

    Notes
    -----
    The paper's Rodrigues matrix aligns the plane normal ``n = p_c x q_c`` with ``z_c`` and so
    fixes only the target's normal; the in-plane axes then come from ``p_c`` and ``q_c``.
    Here the transition frame {w'} has rows ``x' = p_c``, ``y' = q_c``, ``z' = n`` (unit), the
    sign cases flip them as in Fig. 6 (``[r1, -r2, -r3]``, ``[-r1, r2, -r3]``, ``[-r1, -r2, r3]``)
    and the SVD gives the nearest rotation, whose transpose is ``R_cw``. The Rodrigues matrix
    checks the normal: its third row equals ``z'``.
    """
    pc = _direction(camera, p)
    qc = _direction(camera, q)
    x = pc / np.linalg.norm(pc)
    y = qc / np.linalg.norm(qc)
    n = np.cross(x, y)
    if np.linalg.norm(n) < 1e-9:
        raise ValueError("vanishing points: expected two distinct directions, got parallel ones")
    n /= np.linalg.norm(n)
    # Sign cases of Fig. 6: does p lie in the direction of o->a, q in the direction of o->c?
    sx = _side(camera, a_px, o_px, x)
    sy = _side(camera, c_px, o_px, y)
    r1, r2, r3 = x, y, n
    rows = np.vstack([sx * r1, sy * r2, sx * sy * r3])  # R_w'c: camera -> transition frame
    r_wc = orthonormalize(rows)
    # The Rodrigues matrix carries n onto z_c; its third row is n (consistency, logged).
    align = rodrigues_align(sx * sy * n)
    logger.debug("Rodrigues check |row3 - z'| = %.2e", np.linalg.norm(align[2] - r_wc[2]))
    return r_wc.T


def paper_pose(
    camera: CameraModel,
    p: ArrayLike,
    q: ArrayLike,
    o_px: ArrayLike,
    a_px: ArrayLike,
    c_px: ArrayLike,
    stripe_o_px: ArrayLike,
    light_plane: LightPlane,
) -> PoseResult:
    """The paper's extrinsics (III.C): rotation from p and q, translation from the stripe on O.

    Parameters
    ----------
    stripe_o_px : array_like, shape (2,)
        Pixel of the stripe where it crosses the target centre O (eq. 10: its ray meets the
        light plane at O, so ``t_cw`` is that point).
    light_plane : LightPlane
        Calibrated light plane, camera frame.

    Returns
    -------
    PoseResult
        ``cam_from_target``; falsy when the ray misses the plane.
    """
    try:
        r_cw = paper_rotation_from_vanishing_points(camera, p, q, o_px, a_px, c_px)
    except ValueError as exc:
        return PoseResult(False, str(exc))
    ray = camera.rays(np.asarray(stripe_o_px, dtype=np.float64).reshape(1, 2))
    o_cam = intersect_rays_with_plane(ray, light_plane.normal, light_plane.d)[0]
    if not np.all(np.isfinite(o_cam)):
        return PoseResult(False, "the ray through the stripe point on O misses the light plane")
    return PoseResult(True, cam_from_target=make_transform(r_cw, o_cam))
