"""Camera intrinsics from target observations.

Two methods:

``"paper"``
    Section III.A of the method: vanishing points p, q of the two diameters from the
    harmonic conjugate of O with respect to the diameter ends, equation (4) per image,
    differences (5) stacked into ``H phi = g`` (6) over n >= 4 images, least squares, then
    alpha, beta from (4). Zero skew, no distortion. Reported in two variants: the diameter
    ends of the largest ring only (the paper), and every ring (a 1-D projective fit along
    each diameter line).
``"default"``
    Starts from the paper estimate (or OpenCV's ``calibrateCamera`` on the exact point
    correspondences), then one robust nonlinear least-squares adjustment of fx, fy, cx, cy,
    k1, k2, p1, p2, k3 and every view's pose, minimising the geometric image distance of
    every ring edge point to the projected circle of its radius and of every diameter-line
    point to the projected line (points of chessboards and circle grids: their reprojection).

The paper's method is in :mod:`calibration.intrinsics_paper`, the adjustment in
:mod:`calibration.intrinsics_adjust`; :func:`calibrate_intrinsics` here runs either.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from calibration.detection.observations import TargetObservation
from calibration.extrinsics import pose_covariance_as_turns
from calibration.intrinsics_adjust import (
    PARAM_NAMES,
    _adjust,
    adjustment_covariances,
    camera_matrix,
)
from calibration.intrinsics_model import (
    DISTORTION_MODELS,
    ModelSelection,
    UncertaintyMap,
    projection_uncertainty,
    select_distortion_model,
)
from calibration.intrinsics_paper import MIN_VIEWS, PaperEstimate, _paper_variants, paper_intrinsics
from scanner.core.conventions import make_transform

log = logging.getLogger(__name__)

__all__ = [
    "PARAM_NAMES",
    "IntrinsicsResult",
    "PaperEstimate",
    "calibrate_intrinsics",
    "paper_intrinsics",
]


@dataclass
class IntrinsicsResult:
    """Calibrated intrinsics and how well they are determined.

    Attributes
    ----------
    K : ndarray, shape (3, 3)
    dist : ndarray, shape (5,)
        OpenCV order ``(k1, k2, p1, p2, k3)``.
    image_size : tuple of int
        ``(width, height)``.
    method : str
        ``"default"`` or ``"paper"`` (the variant used for ``K`` in the latter case).
    view_indices : list of int
        Indices (into the input list) of the views used.
    cam_from_target : list of ndarray, shape (4, 4)
        Pose of each used view, in the order of ``view_indices``.
    pose_covariance : list of ndarray, shape (6, 6)
        Each pose's covariance (small turns of the camera frame rad, translation mm; see
        :func:`calibration.extrinsics.pose_covariance_as_turns`) given the intrinsics, in
        the same order; empty where the method gives none.
    rms_px : float
        RMS of all geometric residuals, pixels.
    per_view_rms_px : ndarray, shape (V,)
    std : dict of str to float
        Standard deviations of ``PARAM_NAMES`` (from J^T J and the residual variance).
    correlation : ndarray, shape (9, 9)
        Correlation matrix of ``PARAM_NAMES``.
    warnings : list of str
    rejected : list of tuple of (int, str)
        Input views not used, with the reason.
    paper : dict of str to PaperEstimate
        ``"diameter_ends"`` (the paper's method) and ``"all_rings"``, when computed.
    n_residuals : int
    distortion_model : str
        The distortion terms fitted (a key of ``DISTORTION_MODELS``, or "given" when the
        caller held terms itself).
    model_selection : ModelSelection or None
        The held-out scores the model was chosen by (``distortion="auto"``).
    uncertainty_map : UncertaintyMap or None
        1-sigma projection uncertainty over the image, from the intrinsics' covariance.
    """

    K: NDArray
    dist: NDArray
    image_size: tuple[int, int]
    method: str
    view_indices: list[int] = field(default_factory=list)
    cam_from_target: list[NDArray] = field(default_factory=list)
    pose_covariance: list[NDArray] = field(default_factory=list)
    rms_px: float = float("nan")
    per_view_rms_px: NDArray = field(default_factory=lambda: np.zeros(0))
    std: dict[str, float] = field(default_factory=dict)
    correlation: NDArray = field(default_factory=lambda: np.eye(len(PARAM_NAMES)))
    warnings: list[str] = field(default_factory=list)
    rejected: list[tuple[int, str]] = field(default_factory=list)
    paper: dict[str, PaperEstimate] = field(default_factory=dict)
    n_residuals: int = 0
    distortion_model: str = "full"
    model_selection: ModelSelection | None = None
    uncertainty_map: UncertaintyMap | None = None

    def quality(self) -> dict[str, object]:
        """JSON-ready figures for the calibration file's ``quality`` object."""
        out: dict[str, object] = {
            "method": self.method,
            "rms_px": self.rms_px,
            "per_view_rms_px": [float(v) for v in self.per_view_rms_px],
            "views_used": list(self.view_indices),
            "std": dict(self.std),
            "correlation": np.nan_to_num(self.correlation).tolist(),
            "param_names": list(PARAM_NAMES),
            "warnings": list(self.warnings),
            "rejected": [{"view": i, "reason": why} for i, why in self.rejected],
            "n_residuals": self.n_residuals,
            "distortion_model": self.distortion_model,
        }
        if self.model_selection is not None:
            out["model_selection"] = self.model_selection.to_json()
        if self.uncertainty_map is not None:
            out["projection_uncertainty_px"] = {
                "max": self.uncertainty_map.max_px,
                "median": self.uncertainty_map.median_px,
            }
        paper = {}
        for name, est in self.paper.items():
            paper[name] = {"ok": est.ok, "reason": est.reason, "K": est.K.tolist()}
        if paper:
            out["paper"] = paper
        return out

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])


def calibrate_intrinsics(
    observations: list[TargetObservation],
    image_size: tuple[int, int],
    method: Literal["default", "paper"] = "default",
    target: object | None = None,
    f_scale_px: float | None = None,
    max_points_per_ring: int = 200,
    fixed: tuple[str, ...] = (),
    distortion: str = "auto",
    check_cancelled: Callable[[], None] | None = None,
    workers: int = 2,
) -> IntrinsicsResult:
    """Calibrate the camera from observations of a planar target.

    Parameters
    ----------
    observations : list of TargetObservation
        One per image; falsy ones are reported in ``rejected`` with their reason.
    image_size : tuple of int
        ``(width, height)``, pixels.
    method : {"default", "paper"}
    target : TargetSpec, optional
        The target spec (not needed: observations carry target coordinates).
    f_scale_px : float, optional
        Residual size, pixels, beyond which the robust (soft L1) loss down-weights a point;
        by default 3 robust standard deviations of a first pass's residuals.
    max_points_per_ring : int
        Ring edge points used per ring and view (evenly subsampled). Neighbouring edge
        points share blur and pixel noise, so points a few pixels apart carry nearly all the
        information: 200 keeps 20 views of 10 rings near 2 s of CPU and the standard
        deviations honest (denser sampling shrinks them without adding information).
    fixed : tuple of str
        Names from ``PARAM_NAMES`` held at their initial value (distortion terms at 0), e.g.
        ``("p1", "p2", "k3")`` for the two-term radial model of Zhang's published result.
    distortion : str
        ``"auto"`` (default): the distortion terms chosen on held-out views
        (:func:`calibration.intrinsics_model.select_distortion_model`) unless ``fixed`` names
        some; or a key of ``DISTORTION_MODELS`` (``"none"``, ``"k1"``, ``"k1k2"``,
        ``"k1k2p1p2"``, ``"full"``).
    check_cancelled : callable, optional
        Called after the first adjustment and each one without outlier views, before each
        fold of the distortion model's choice and before the chosen model's fit: whatever it
        raises stops the calibration and comes out of this function.
    workers : int
        Fits of the distortion model's choice run at a time, on threads.

    Returns
    -------
    IntrinsicsResult

    Raises
    ------
    ValueError
        Fewer than 4 usable views, or views that cannot determine the intrinsics (e.g. the
        paper method on a non-concentric target, or all views parallel), naming what is missing.
    """
    unknown = [n for n in fixed if n not in PARAM_NAMES]
    if unknown:
        raise ValueError(f"fixed: expected names from {PARAM_NAMES}, got {unknown}")
    if method not in ("default", "paper"):
        raise ValueError(f"method: expected 'default' or 'paper', got {method!r}")
    if distortion != "auto" and distortion not in DISTORTION_MODELS:
        raise ValueError(
            f"distortion: expected 'auto' or one of {', '.join(DISTORTION_MODELS)}, "
            f"got {distortion!r}"
        )
    w, h = (int(image_size[0]), int(image_size[1]))
    rejected: list[tuple[int, str]] = []
    used: list[int] = []
    for i, ob in enumerate(observations):
        if not ob:
            rejected.append((i, f"target not found: {ob.reason}"))
        elif tuple(ob.image_size) != (w, h):
            rejected.append((i, f"image size {ob.image_size}, expected {(w, h)}"))
        elif len(ob.points_px) < 4:
            rejected.append((i, f"only {len(ob.points_px)} points, expected >= 4"))
        else:
            used.append(i)
    if len(used) < MIN_VIEWS:
        raise ValueError(
            f"intrinsics: expected >= {MIN_VIEWS} views with the target found, got {len(used)}"
            + (f" (first rejection: view {rejected[0][0]}: {rejected[0][1]})" if rejected else "")
        )
    obs = [observations[i] for i in used]
    concentric = all(ob.kind == "concentric_circles" for ob in obs)
    warnings: list[str] = []

    paper: dict[str, PaperEstimate] = {}
    if concentric:
        paper = _paper_variants(obs)
    if method == "paper":
        if not concentric:
            raise ValueError(
                "intrinsics: method 'paper' needs concentric-circles observations, got "
                + ", ".join(sorted({ob.kind for ob in obs}))
            )
        est = paper["diameter_ends"]
        if not est:
            raise ValueError(f"intrinsics (paper): {est.reason}")
        return _paper_result(est, paper, obs, used, rejected, (w, h))

    # -- initial values
    K0, dist0 = None, np.zeros(5)
    if concentric:
        for variant in ("all_rings", "diameter_ends"):
            est = paper.get(variant)
            if est and _plausible(est.K, (w, h)):
                K0 = est.K.copy()
                break
        if K0 is None:
            warnings.append("paper estimate implausible; initialised with OpenCV calibrateCamera")
    if K0 is None:
        K0, dist0 = _opencv_init(obs, (w, h))
    dist0 = np.array(dist0, dtype=np.float64)
    for n in fixed:
        if PARAM_NAMES.index(n) >= 4:
            dist0[PARAM_NAMES.index(n) - 4] = 0.0
    poses0 = []
    keep = []
    for j, ob in enumerate(obs):
        pose = _initial_pose(ob, K0, dist0)
        if pose is None:
            rejected.append((used[j], "no initial pose (solvePnP failed)"))
        else:
            poses0.append(pose)
            keep.append(j)
    obs = [obs[j] for j in keep]
    used = [used[j] for j in keep]
    if len(obs) < MIN_VIEWS:
        raise ValueError(f"intrinsics: expected >= {MIN_VIEWS} views with a pose, got {len(obs)}")
    poses = np.asarray(poses0)
    # Outlier views are found first, with all distortion terms free where the model is to be
    # chosen: a mislabelled view left in would decide the held-out comparison on its own.
    auto = not fixed and distortion == "auto"
    model = "given" if fixed else distortion
    if not fixed and not auto:
        fixed = DISTORTION_MODELS[distortion]
    for n in fixed:
        if PARAM_NAMES.index(n) >= 4:
            dist0[PARAM_NAMES.index(n) - 4] = 0.0
    check = check_cancelled or (lambda: None)
    x, res, prob, sol = _adjust(obs, K0, dist0, poses, f_scale_px, max_points_per_ring, fixed)
    check()

    # -- outlier views
    for _ in range(2):
        views = prob.residual_views()
        per_view = np.array([np.sqrt(np.mean(res[views == v] ** 2)) for v in range(len(obs))])
        med = float(np.median(per_view))
        bad = np.flatnonzero(per_view > max(4.0 * med, 0.5))
        if len(bad) == 0 or len(obs) - len(bad) < MIN_VIEWS:
            break
        for b in bad:
            rejected.append(
                (used[b], f"outlier view: RMS {per_view[b]:.3f} px vs median {med:.3f} px")
            )
        keep = [j for j in range(len(obs)) if j not in set(bad)]
        obs = [obs[j] for j in keep]
        used = [used[j] for j in keep]
        poses = x[9:].reshape(-1, 6)[keep]
        K1 = camera_matrix(x)
        x, res, prob, sol = _adjust(obs, K1, x[4:9], poses, f_scale_px, max_points_per_ring, fixed)
        check()

    selection = None
    if auto:
        poses = x[9:].reshape(-1, 6)
        selection = select_distortion_model(
            obs, camera_matrix(x), poses, check_cancelled=check_cancelled, workers=workers
        )
        check()
        model = selection.chosen
        fixed = DISTORTION_MODELS[model]
        dist1 = x[4:9].copy()
        for n in fixed:
            if PARAM_NAMES.index(n) >= 4:
                dist1[PARAM_NAMES.index(n) - 4] = 0.0
        x, res, prob, sol = _adjust(
            obs, camera_matrix(x), dist1, poses, f_scale_px, max_points_per_ring, fixed
        )

    views = prob.residual_views()
    per_view = np.array([np.sqrt(np.mean(res[views == v] ** 2)) for v in range(len(obs))])
    K = camera_matrix(x)
    dist = x[4:9].copy()
    poses = x[9:].reshape(-1, 6)
    cam_from_target = [make_transform(Rotation.from_rotvec(p[:3]), p[3:]) for p in poses]

    # -- uncertainty
    std: dict[str, float] = {}
    corr = np.full((9, 9), np.nan)
    uncertainty = None
    pose_cov: list[NDArray] = []
    try:
        c9, given_camera = adjustment_covariances(prob, x, res, fixed)
        pose_cov = [pose_covariance_as_turns(p[:3], c) for p, c in zip(poses, given_camera)]
        sd = np.sqrt(np.maximum(np.diag(c9), 0))
        std = {n: float(v) for n, v in zip(PARAM_NAMES, sd)}
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = c9 / np.outer(sd, sd)
        uncertainty = projection_uncertainty(camera_matrix(x), x[4:9], c9, (w, h))
    except np.linalg.LinAlgError:
        warnings.append("normal matrix singular: parameters not all determined by these views")
    tilts = _view_tilts_deg(poses)
    if float(np.max(tilts)) < 10.0:
        warnings.append(
            f"all views within {np.max(tilts):.1f} deg of fronto-parallel: focal length and "
            "principal point poorly determined (tilt the target 20-45 deg)"
        )
    elif float(np.ptp(tilts)) < 5.0:
        warnings.append(f"tilt range only {np.ptp(tilts):.1f} deg: vary the target's tilt")
    if std and std["fx"] / x[0] > 1e-3:
        warnings.append(f"fx poorly determined: standard deviation {std['fx']:.2f} px")
    if not sol.success:
        warnings.append(f"adjustment did not converge: {sol.message}")
    return IntrinsicsResult(
        K=K,
        dist=dist,
        image_size=(w, h),
        method="default",
        view_indices=used,
        cam_from_target=cam_from_target,
        pose_covariance=pose_cov,
        rms_px=float(np.sqrt(np.mean(res**2))),
        per_view_rms_px=per_view,
        std=std,
        correlation=corr,
        warnings=warnings,
        rejected=sorted(rejected),
        paper=paper,
        n_residuals=len(res),
        distortion_model=model,
        model_selection=selection,
        uncertainty_map=uncertainty,
    )


def _plausible(K: NDArray, size: tuple[int, int]) -> bool:
    w, h = size
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return bool(
        fx > 0.1 * w
        and fy > 0.1 * w
        and 0.8 < fx / fy < 1.25
        and -0.25 * w < cx < 1.25 * w
        and -0.25 * h < cy < 1.25 * h
    )


def _paper_result(
    est: PaperEstimate,
    paper: dict[str, PaperEstimate],
    obs: list[TargetObservation],
    used: list[int],
    rejected: list[tuple[int, str]],
    size: tuple[int, int],
) -> IntrinsicsResult:
    """The paper's K with poses from PnP (no distortion) and their reprojection RMS."""
    poses, per_view, all_res, views = [], [], [], []
    for j, ob in enumerate(obs):
        pose = _initial_pose(ob, est.K, np.zeros(5))
        if pose is None:
            rejected.append((used[j], "no pose (solvePnP failed)"))
            continue
        proj, _ = cv2.projectPoints(ob.points_target, pose[:3], pose[3:], est.K, np.zeros(5))
        r = (proj.reshape(-1, 2) - ob.points_px).ravel()
        per_view.append(float(np.sqrt(np.mean(r**2))))
        all_res.append(r)
        poses.append(make_transform(Rotation.from_rotvec(pose[:3]), pose[3:]))
        views.append(used[j])
    res = np.concatenate(all_res) if all_res else np.zeros(0)
    return IntrinsicsResult(
        K=est.K,
        dist=np.zeros(5),
        image_size=size,
        method="paper",
        view_indices=views,
        cam_from_target=poses,
        rms_px=float(np.sqrt(np.mean(res**2))) if res.size else float("nan"),
        per_view_rms_px=np.asarray(per_view),
        warnings=["paper method: zero skew and no lens distortion assumed"],
        rejected=sorted(rejected),
        paper=paper,
        n_residuals=int(res.size),
        distortion_model="none",
    )


def _initial_pose(ob: TargetObservation, K: NDArray, dist: NDArray) -> NDArray | None:
    obj = ob.points_target.astype(np.float64)
    img = ob.points_px.astype(np.float64)
    if len(obj) < 4:
        return None
    flag = cv2.SOLVEPNP_IPPE if len(obj) >= 4 else cv2.SOLVEPNP_ITERATIVE
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=flag)
    if not ok:
        return None
    ok, rvec, tvec = cv2.solvePnP(
        obj, img, K, dist, rvec, tvec, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE
    )
    if not ok or tvec[2, 0] <= 0:
        return None
    return np.r_[rvec.ravel(), tvec.ravel()]


def _opencv_init(
    obs_list: list[TargetObservation], image_size: tuple[int, int]
) -> tuple[NDArray, NDArray]:
    obj = [ob.points_target.astype(np.float32) for ob in obs_list]
    img = [ob.points_px.astype(np.float32) for ob in obs_list]
    _, K, dist, _, _ = cv2.calibrateCamera(obj, img, image_size, None, None)
    return K, dist.ravel()[:5]


def _view_tilts_deg(poses: NDArray) -> NDArray:
    """Angle between each view's target normal and its line of sight to the target origin.

    A target facing the camera along the line of sight is as uninformative about the focal
    length as a fronto-parallel one, wherever it is in the image.
    """
    R = Rotation.from_rotvec(poses[:, :3]).as_matrix()
    normal = R[:, :, 2]
    sight = poses[:, 3:] / np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
    cosang = np.abs(np.einsum("ij,ij->i", normal, sight))
    return np.degrees(np.arccos(np.clip(cosang, 0, 1)))
