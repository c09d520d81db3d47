"""Laser light plane in the camera frame (``normal . p_cam + d = 0``).

Two ways:

* default (:func:`calibrate_light_plane`): in every laser frame whose target pose is known
  (``cam_from_target`` from the target image of the same row), the stripe's sub-pixel centre
  points are undistorted into rays and met with the target plane; one robust fit (RANSAC,
  then total least squares) over every frame's points; frames that disagree are rejected with
  a reason;
* the paper's (Section III.B, after its Ref. [13], :func:`paper_light_plane`): with the stripe
  along the known diameter A-O-B, the angles alpha1, alpha2 between the rays to a, o and b give
  A, O and B in the camera frame (eqs. 7-8); at least two target positions; the plane by the
  least squares of eq. (9).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanner.core.camera import CameraModel, intersect_rays_with_plane
from scanner.core.conventions import check_points, transform_points
from scanner.core.outcome import Outcome
from scanner.formats.calibration_file import LightPlane

__all__ = [
    "LaserView",
    "LightPlaneResult",
    "PaperPlaneView",
    "PlaneFit",
    "calibrate_light_plane",
    "fit_plane",
    "fit_plane_robust",
    "paper_diameter_points",
    "paper_light_plane",
    "stripe_points_on_target",
]

logger = logging.getLogger(__name__)


@dataclass
class PlaneFit(Outcome):
    """A plane ``normal . p + d = 0`` fitted to points, or a failed fit (falsy) with ``reason``.

    Attributes
    ----------
    normal : ndarray, shape (3,)
        Unit normal, oriented so that ``d <= 0`` (the camera centre on the negative side).
    d : float
    rms_mm, max_abs_mm : float
        Orthogonal residuals of the inliers.
    inliers : ndarray of bool, shape (N,)
    std_normal_deg, std_d_mm : float
        One-sigma uncertainty from the residual variance and the points' spread.
    """

    normal: NDArray = field(default_factory=lambda: np.full(3, np.nan))
    d: float = float("nan")
    rms_mm: float = float("nan")
    max_abs_mm: float = float("nan")
    inliers: NDArray = field(default_factory=lambda: np.zeros(0, bool))
    std_normal_deg: float = float("nan")
    std_d_mm: float = float("nan")


def _tls(points: NDArray) -> tuple[NDArray, float, NDArray]:
    """Total least squares plane; returns normal, d and singular values."""
    c = points.mean(axis=0)
    _, s, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2]
    d = -float(n @ c)
    if d > 0:
        n, d = -n, -d
    return n, d, s


def fit_plane(points: ArrayLike) -> PlaneFit:
    """Fit a plane by orthogonal (total) least squares.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points in any frame, mm. N >= 3, not collinear.

    Returns
    -------
    PlaneFit
        Unit normal and offset, residual RMS and maximum, uncertainties; a failed fit (falsy)
        when the points are (nearly) collinear.
    """
    p = check_points(points, min_count=3)
    n, d, s = _tls(p)
    if s[1] < 1e-9 * max(1.0, s[0]):
        return PlaneFit(False, "points are collinear: a plane is not determined")
    r = p @ n + d
    dof = max(1, len(p) - 3)
    sigma = float(np.sqrt(np.sum(r**2) / dof))
    # Gauss-Newton covariance of (two normal tilts, d): residual r = (n + a e1 + b e2) . p + d.
    e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    jac = np.column_stack([p @ e1, p @ e2, np.ones(len(p))])
    try:
        cov = np.linalg.inv(jac.T @ jac) * sigma**2
        std_n = float(np.degrees(np.sqrt(max(0.0, cov[0, 0] + cov[1, 1]))))
        std_d = float(np.sqrt(max(0.0, cov[2, 2])))
    except np.linalg.LinAlgError:
        std_n = std_d = float("nan")
    return PlaneFit(
        True,
        normal=n,
        d=d,
        rms_mm=float(np.sqrt(np.mean(r**2))),
        max_abs_mm=float(np.abs(r).max()),
        inliers=np.ones(len(p), bool),
        std_normal_deg=std_n,
        std_d_mm=std_d,
    )


def fit_plane_robust(
    points: ArrayLike,
    threshold_mm: float = 0.2,
    iterations: int = 300,
    seed: int = 0,
    groups: ArrayLike | None = None,
) -> PlaneFit:
    """RANSAC over minimal triples, then total least squares on the inliers.

    Parameters
    ----------
    points : array_like, shape (N, 3)
    threshold_mm : float
        Inlier distance for the consensus.
    iterations : int
    seed : int
        RANSAC is seeded: the same points give the same plane.
    groups : array_like of int, shape (N,), optional
        Which frame each point comes from. Then every hypothesis takes its three points from
        at least two frames (one frame's stripe is a line: any plane through it fits it) and
        the consensus counts every frame equally (inliers weighted by 1 / frame size).

    Returns
    -------
    PlaneFit
        ``inliers`` marks the points kept; falsy when fewer than 3 points agree.
    """
    p = check_points(points, min_count=3)
    rng = np.random.default_rng(seed)
    best = np.ones(len(p), bool)
    best_count = -1.0
    weight = np.ones(len(p))
    labels = None
    if groups is not None:
        labels = np.asarray(groups).reshape(-1)
        if labels.shape != (len(p),):
            raise ValueError(f"groups: expected shape ({len(p)},), got {labels.shape}")
        uniq, inverse, counts = np.unique(labels, return_inverse=True, return_counts=True)
        weight = 1.0 / counts[inverse]
        if len(uniq) < 2:
            labels = None
    if len(p) > 3:
        for _ in range(iterations):
            idx = rng.choice(len(p), 3, replace=False)
            if labels is not None and labels[idx[0]] == labels[idx[1]] == labels[idx[2]]:
                others = np.flatnonzero(labels != labels[idx[0]])
                idx[2] = others[rng.integers(len(others))]
            a, b, c = p[idx]
            n = np.cross(b - a, c - a)
            norm = np.linalg.norm(n)
            if norm < 1e-9:
                continue
            n /= norm
            inl = np.abs((p - a) @ n) < threshold_mm
            count = float(weight[inl].sum())
            if count > best_count:
                best, best_count = inl, count
    for _ in range(3):  # TLS on the consensus, re-select inliers at the same threshold
        if best.sum() < 3:
            return PlaneFit(False, f"only {int(best.sum())} points agree on a plane")
        fit = fit_plane(p[best])
        if not fit:
            return fit
        new = np.abs(p @ fit.normal + fit.d) < max(threshold_mm, 3.0 * fit.rms_mm)
        if np.array_equal(new, best):
            break
        best = new
    fit = fit_plane(p[best])
    fit.inliers = best
    return fit


def stripe_points_on_target(
    stripe_px: ArrayLike, camera: CameraModel, cam_from_target: NDArray
) -> NDArray:
    """Stripe pixels met with the target plane: ``(N, 3)`` camera-frame points, mm.

    Rays through the (distorted) pixels come from the camera model; the target plane is its
    z = 0 face. Rows whose ray misses the plane are NaN.
    """
    uv = check_points(stripe_px, min_count=0, name="stripe_px", dim=2)
    n = cam_from_target[:3, 2]
    d = -float(n @ cam_from_target[:3, 3])
    return intersect_rays_with_plane(camera.rays(uv), n, d)


def _stripe_line_inliers(
    points_cam: NDArray, cam_from_target: NDArray, threshold_mm: float
) -> NDArray:
    """The points on the frame's dominant straight line (in the target plane), RANSAC + TLS."""
    pt = transform_points(np.linalg.inv(cam_from_target), points_cam)[:, :2]
    rng = np.random.default_rng(0)
    # 100 lines through pairs of points, all judged at once: the first with the most inliers.
    pairs = np.array([rng.choice(len(pt), 2, replace=False) for _ in range(100)])
    d = pt[pairs[:, 1]] - pt[pairs[:, 0]]
    norm = np.hypot(d[:, 0], d[:, 1])
    usable = norm >= 1e-6
    normal = np.column_stack([-d[:, 1], d[:, 0]]) / np.where(usable, norm, 1.0)[:, None]
    offset = pt[None, :, :] - pt[pairs[:, 0]][:, None, :]  # (100, N, 2)
    inliers = np.abs(offset @ normal[:, :, None])[:, :, 0] < threshold_mm
    counts = np.where(usable, inliers.sum(axis=1), 0)
    best = inliers[int(np.argmax(counts))] if counts.max() > 0 else np.zeros(len(pt), bool)
    for _ in range(3):
        if best.sum() < 2:
            break
        c = pt[best].mean(axis=0)
        _, _, vt = np.linalg.svd(pt[best] - c)
        r = np.abs((pt - c) @ vt[1])
        rms = float(np.sqrt(np.mean(r[best] ** 2)))
        best = r < min(threshold_mm, max(4.0 * rms, 0.05))
    return points_cam[best]


@dataclass
class LaserView:
    """One laser frame with a known target pose.

    Attributes
    ----------
    frame_id : int
    stripe_px : ndarray, shape (N, 2)
        Sub-pixel stripe centre points (u, v).
    cam_from_target : ndarray, shape (4, 4)
        From the target image of the same row.
    target_extent_mm : tuple or None
        ``(xmin, xmax, ymin, ymax)`` of the printed target in its frame: stripe points that
        fall outside it (the stripe on the background) are dropped.
    """

    frame_id: int
    stripe_px: NDArray
    cam_from_target: NDArray
    target_extent_mm: tuple[float, float, float, float] | None = None


@dataclass
class LightPlaneResult(Outcome):
    """The calibrated plane with its quality record, or a failure (falsy) with ``reason``."""

    plane: LightPlane | None = None
    method: str = "default"
    rms_mm: float = float("nan")
    max_abs_mm: float = float("nan")
    std_normal_deg: float = float("nan")
    std_d_mm: float = float("nan")
    n_points: int = 0
    per_frame: list[dict[str, Any]] = field(default_factory=list)
    rejected: list[dict[str, Any]] = field(default_factory=list)
    points_cam: NDArray = field(default_factory=lambda: np.zeros((0, 3)))

    #: The fields :meth:`quality` reports, in order.
    _QUALITY_FIELDS: ClassVar[tuple[str, ...]] = (
        "method",
        "rms_mm",
        "max_abs_mm",
        "std_normal_deg",
        "std_d_mm",
        "n_points",
        "per_frame",
        "rejected",
    )

    def quality(self) -> dict[str, Any]:
        """The calibration file's ``quality`` record of the light plane."""
        return {name: getattr(self, name) for name in self._QUALITY_FIELDS}


def calibrate_light_plane(
    views: Sequence[LaserView],
    camera: CameraModel,
    min_frames: int = 2,
    ransac_threshold_mm: float = 1.0,
    reject_factor: float = 4.0,
    offset_factor: float = 5.0,
    min_offset_mm: float = 0.02,
    max_points_per_frame: int = 400,
    line_threshold_mm: float = 0.5,
) -> LightPlaneResult:
    """Fit the light plane to the stripe points of every laser frame with a known target pose.

    Parameters
    ----------
    views : sequence of LaserView
    camera : CameraModel
    min_frames : int
        Target positions needed (two non-parallel stripes determine the plane).
    ransac_threshold_mm : float
    reject_factor : float
        A frame whose points' RMS distance to the common plane exceeds this many times the
        median frame's (and 0.05 mm) is rejected and the plane refitted without it.
    offset_factor, min_offset_mm : float
        With 4 frames or more, a frame whose points lie off the common plane on average by
        more than ``offset_factor`` robust standard deviations of the frames' mean offsets
        (and ``min_offset_mm``) is rejected too: its target pose is off.
    max_points_per_frame : int
        Stripe points are thinned evenly to this many per frame (equal weight per frame).
    line_threshold_mm : float
        On the target plane one frame's stripe is a straight line: points farther than this
        from the frame's dominant line (RANSAC) are other peaks (print, reflections) and are
        dropped before the plane fit.

    Returns
    -------
    LightPlaneResult
        Plane, residual RMS (mm) overall and per frame, rejected frames with reasons; falsy
        when fewer than ``min_frames`` frames remain or the points do not span a plane.
    """
    per_frame_pts: dict[int, NDArray] = {}
    rejected: list[dict[str, Any]] = []
    for v in views:
        pts = stripe_points_on_target(v.stripe_px, camera, v.cam_from_target)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if v.target_extent_mm is not None and len(pts):
            pt = transform_points(np.linalg.inv(v.cam_from_target), pts)
            x0, x1, y0, y1 = v.target_extent_mm
            keep = (pt[:, 0] >= x0) & (pt[:, 0] <= x1) & (pt[:, 1] >= y0) & (pt[:, 1] <= y1)
            pts = pts[keep]
        if len(pts) >= 10:
            pts = _stripe_line_inliers(pts, v.cam_from_target, line_threshold_mm)
        if len(pts) < 10:
            rejected.append(
                {
                    "frame_id": int(v.frame_id),
                    "reason": f"only {len(pts)} stripe points on the target",
                }
            )
            continue
        if len(pts) > max_points_per_frame:
            pts = pts[np.linspace(0, len(pts) - 1, max_points_per_frame).round().astype(int)]
        per_frame_pts[int(v.frame_id)] = pts

    def fit(ids: list[int]) -> PlaneFit:
        return fit_plane_robust(
            np.vstack([per_frame_pts[i] for i in ids]),
            threshold_mm=ransac_threshold_mm,
            groups=np.concatenate([np.full(len(per_frame_pts[i]), i) for i in ids]),
        )

    ids = list(per_frame_pts)
    if len(ids) < min_frames:
        return LightPlaneResult(
            False,
            f"light plane needs stripes on the target in >= {min_frames} frames, got {len(ids)}",
            rejected=rejected,
        )
    plane_fit = fit(ids)
    for _ in range(5):
        if not plane_fit:
            break
        residual = {i: per_frame_pts[i] @ plane_fit.normal + plane_fit.d for i in ids}
        frame_rms = {i: float(np.sqrt(np.mean(r**2))) for i, r in residual.items()}
        med = float(np.median(list(frame_rms.values())))
        limit = max(reject_factor * med, 0.05)
        # A frame whose target pose is off, or whose stripe runs along printed ink (which
        # darkens one side of it and shifts its centre), lifts all its points together: its
        # mean offset stands out from the other frames' long before its RMS does (400 points
        # average the stripe noise down; on the paper cell a stripe along the rings' tangents
        # sat 0.22 mm off against a spread of 0.01 mm, its target pose being right).
        frame_mean = {i: float(np.mean(r)) for i, r in residual.items()}
        means = np.array(list(frame_mean.values()))
        centre = float(np.median(means))
        spread = 1.4826 * float(np.median(np.abs(means - centre)))
        offset_limit = max(offset_factor * spread, min_offset_mm)
        why = {}
        for i in ids:
            if frame_rms[i] > limit:
                why[i] = (
                    f"stripe points {frame_rms[i]:.3f} mm RMS off the common plane (limit {limit:.3f} mm)"
                )
            elif len(ids) >= 4 and abs(frame_mean[i] - centre) > offset_limit:
                why[i] = (
                    f"stripe points {frame_mean[i] - centre:+.3f} mm off the common plane on "
                    f"average (limit {offset_limit:.3f} mm): its target pose, or its stripe (printed ink along it), is off"
                )
        bad = list(why)
        if not bad or len(ids) - len(bad) < min_frames:
            break
        for i in bad:
            rejected.append({"frame_id": i, "reason": why[i]})
        ids = [i for i in ids if i not in bad]
        plane_fit = fit(ids)
    if not plane_fit:
        return LightPlaneResult(False, f"light plane: {plane_fit.reason}", rejected=rejected)
    # The stripes must not all be parallel: check the in-plane spread of the points.
    all_pts = np.vstack([per_frame_pts[i] for i in ids])
    _, s, _ = np.linalg.svd(all_pts - all_pts.mean(axis=0), full_matrices=False)
    if s[1] < 1e-3 * s[0]:
        return LightPlaneResult(
            False,
            "light plane: the stripe points are collinear (move the target between frames)",
            rejected=rejected,
        )
    per_frame = []
    for i in ids:
        r = per_frame_pts[i] @ plane_fit.normal + plane_fit.d
        per_frame.append(
            {
                "frame_id": i,
                "n_points": len(r),
                "rms_mm": float(np.sqrt(np.mean(r**2))),
                "mean_mm": float(np.mean(r)),
                "max_abs_mm": float(np.abs(r).max()),
            }
        )
    return LightPlaneResult(
        True,
        plane=LightPlane(plane_fit.normal, plane_fit.d),
        method="default",
        rms_mm=plane_fit.rms_mm,
        max_abs_mm=plane_fit.max_abs_mm,
        std_normal_deg=plane_fit.std_normal_deg,
        std_d_mm=plane_fit.std_d_mm,
        n_points=int(plane_fit.inliers.sum()),
        per_frame=per_frame,
        rejected=rejected,
        points_cam=all_pts,
    )


@dataclass
class PaperPlaneView:
    """Image points a, o, b of the diameter A-O-B lying in the light plane (one target position)."""

    frame_id: int
    a_px: NDArray
    o_px: NDArray
    b_px: NDArray


def paper_diameter_points(
    camera: CameraModel, a_px: ArrayLike, o_px: ArrayLike, b_px: ArrayLike, radius_mm: float
) -> NDArray:
    """A, O, B in the camera frame from their image points (paper eqs. 7-8).

    In the plane through the optical centre and A-O-B, with x along the ray to O: A lies at
    angle alpha1 on one side, B at alpha2 on the other, O halfway, |AB| = 2R. Then (eq. 7)::

        x_B = sqrt((2 R tan a1)^2 / ((2 tan a1 tan a2)^2 + (tan a1 - tan a2)^2))
        y_B = -x_B tan a2,  x_A = x_B tan a2 / tan a1,  y_A = x_B tan a2
        x_O = x_B (tan a1 + tan a2) / (2 tan a1),  y_O = 0

    (``y_A = -y_B``: A and B sit symmetrically about the x axis through O.) The distances
    ``D = sqrt(x^2 + y^2)`` scale the unit-focal rays (eq. 8). The rays come from the camera
    model, so lens distortion is removed first.

    Returns
    -------
    ndarray, shape (3, 3)
        Rows A, O, B, camera frame, mm.
    """
    uv = np.vstack([np.reshape(a_px, 2), np.reshape(o_px, 2), np.reshape(b_px, 2)]).astype(float)
    rays = camera.rays(uv)
    unit = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    alpha1 = float(np.arccos(np.clip(unit[0] @ unit[1], -1, 1)))
    alpha2 = float(np.arccos(np.clip(unit[2] @ unit[1], -1, 1)))
    t1, t2 = np.tan(alpha1), np.tan(alpha2)
    if t1 < 1e-9 or t2 < 1e-9:
        raise ValueError("paper light plane: a, o, b must be distinct image points")
    x_b = np.sqrt((2 * radius_mm * t1) ** 2 / ((2 * t1 * t2) ** 2 + (t1 - t2) ** 2))
    y_b = -x_b * t2
    x_a = t2 / t1 * x_b
    y_a = x_b * t2
    x_o = (t1 + t2) / (2 * t1) * x_b
    dist = np.array([np.hypot(x_a, y_a), x_o, np.hypot(x_b, y_b)])
    # Eq. (8): X_c = D * (normalised ray) / |ray|, i.e. the unit ray scaled by the distance.
    return unit * dist[:, None]


def paper_light_plane(
    views: Sequence[PaperPlaneView], camera: CameraModel, radius_mm: float, d_scale: float = 1000.0
) -> LightPlaneResult:
    """The paper's light plane (III.B): eqs. (7)-(8) per position, least squares (9).

    Parameters
    ----------
    views : sequence of PaperPlaneView
        At least two target positions with A-O-B in the light plane.
    camera : CameraModel
    radius_mm : float
        R = |AB| / 2, half the largest ring diameter.
    d_scale : float
        The fixed non-zero d of eq. (9) (the paper: "any real number except zero").

    Returns
    -------
    LightPlaneResult
        ``per_frame`` lists each position's A, O, B and their distances to the fitted plane.
    """
    if len(views) < 2:
        return LightPlaneResult(
            False,
            f"paper light plane: expected >= 2 target positions, got {len(views)}",
            method="paper",
        )
    pts, ids = [], []
    for v in views:
        pts.append(paper_diameter_points(camera, v.a_px, v.o_px, v.b_px, radius_mm))
        ids += [v.frame_id] * 3
    L = np.vstack(pts)
    # Eq. (9): a x + b y + c z + d = 0 with d fixed: L psi = -d.
    psi = np.linalg.lstsq(L, -d_scale * np.ones(len(L)), rcond=None)[0]
    plane = LightPlane(-psi, -d_scale) if d_scale > 0 else LightPlane(psi, d_scale)
    fit = fit_plane(L)  # for the uncertainty figures only
    r = plane.signed_distance(L)
    per_frame = []
    for k, v in enumerate(views):
        rr = r[3 * k : 3 * k + 3]
        per_frame.append(
            {
                "frame_id": int(v.frame_id),
                "A_cam_mm": L[3 * k].tolist(),
                "O_cam_mm": L[3 * k + 1].tolist(),
                "B_cam_mm": L[3 * k + 2].tolist(),
                "rms_mm": float(np.sqrt(np.mean(rr**2))),
            }
        )
    return LightPlaneResult(
        True,
        plane=plane,
        method="paper",
        rms_mm=float(np.sqrt(np.mean(r**2))),
        max_abs_mm=float(np.abs(r).max()),
        std_normal_deg=fit.std_normal_deg if fit else float("nan"),
        std_d_mm=fit.std_d_mm if fit else float("nan"),
        n_points=len(L),
        per_frame=per_frame,
        points_cam=L,
    )
