"""Which lens-distortion terms the data can pin, chosen on held-out views; and how well the
chosen camera model projects, over the whole image.

Five distortion terms fitted to a lens without distortion, or to eight views that leave the
image corners empty, bend the model where no view looked: the fit is better on the views it
was fitted to and worse everywhere else. So the terms are chosen as mrcal teaches, by the data:
each candidate model (no distortion, k1, k1 k2, k1 k2 p1 p2, all five) is fitted to the views
of all folds but one and scored on the views held out (their poses fitted with the
intrinsics held): that finds the terms a lens needs where the views looked (bias). Where they
did not look, the held-out views cannot tell; there the model's own projection uncertainty,
from the folds' fits, says how far extra terms let it wander (variance). Of the models whose
held-out error is not worse than the best by more than one standard error of the paired
per-view difference, those whose projection uncertainty is within 5 % of the smallest are
pinned as well as any, and of those the one with the most terms wins (terms that cost no
variance may still remove a bias the held-out views cannot see: decentring against the
principal point).

:func:`projection_uncertainty` then maps the 1-sigma uncertainty of the projection of a
camera-frame point over the image from the intrinsics' covariance: where it is large, more
views are needed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration.detection.observations import TargetObservation
from calibration.intrinsics_adjust import (
    PARAM_NAMES,
    _adjust,
    _project,
    camera_matrix,
    intrinsics_covariance,
)
from scanner.core.parallel import thread_map

__all__ = [
    "DISTORTION_MODELS",
    "ModelScore",
    "ModelSelection",
    "UncertaintyMap",
    "projection_uncertainty",
    "select_distortion_model",
]

#: Candidate distortion models, simplest first: the terms each holds at zero.
DISTORTION_MODELS: dict[str, tuple[str, ...]] = {
    "none": ("k1", "k2", "p1", "p2", "k3"),
    "k1": ("k2", "p1", "p2", "k3"),
    "k1k2": ("p1", "p2", "k3"),
    "k1k2p1p2": ("k3",),
    "full": (),
}

#: Fewest views a fold's fit is made from (the intrinsics' own minimum).
_MIN_TRAIN = 4


@dataclass(frozen=True)
class ModelScore:
    """One candidate's held-out error.

    Attributes
    ----------
    name : str
        A key of :data:`DISTORTION_MODELS`.
    held_out_rms_px : float
        RMS over every held-out view's residuals, pixels.
    uncertainty_rms_px : float
        RMS over the image of the projection's 1-sigma uncertainty of the folds' fits.
    per_view_px : ndarray, shape (V,)
        Each view's RMS when it was held out.
    fit_rms_px : float
        Mean RMS of the folds' fits on their own views (lower than held-out when overfitted).
    """

    name: str
    held_out_rms_px: float
    uncertainty_rms_px: float
    per_view_px: NDArray
    fit_rms_px: float


@dataclass(frozen=True)
class ModelSelection:
    """The distortion model chosen and the scores it was chosen from."""

    chosen: str
    scores: tuple[ModelScore, ...]
    folds: int
    reason: str

    @property
    def fixed(self) -> tuple[str, ...]:
        """The terms the chosen model holds at zero."""
        return DISTORTION_MODELS[self.chosen]

    def to_json(self) -> dict[str, object]:
        return {
            "chosen": self.chosen,
            "reason": self.reason,
            "folds": self.folds,
            "held_out_rms_px": {s.name: s.held_out_rms_px for s in self.scores},
            "uncertainty_rms_px": {s.name: s.uncertainty_rms_px for s in self.scores},
            "fit_rms_px": {s.name: s.fit_rms_px for s in self.scores},
        }


def _folds(n_views: int, folds: int) -> int:
    """As many folds as asked while every fold's fit keeps at least 4 views."""
    k = min(folds, n_views)
    while k > 1 and n_views - int(np.ceil(n_views / k)) < _MIN_TRAIN:
        k += 1
        if k > n_views:
            return 0
    return k


@dataclass(frozen=True)
class _FoldScore:
    """One candidate's fit to one fold's training views, scored on its held-out views.

    Attributes
    ----------
    held_out : ndarray, shape (M,)
        Indices of the held-out views.
    per_view_px : ndarray, shape (M,)
        Their RMS reprojection error, px, with the fold's intrinsics held.
    fit_rms_px : float
        RMS residual of the fold's own fit, px.
    sigma_ms_px2 : float
        Mean square projection uncertainty over the image, px^2 (inf: none computed).
    """

    held_out: NDArray
    per_view_px: NDArray
    fit_rms_px: float
    sigma_ms_px2: float


def _fold_score(
    observations: list[TargetObservation],
    held_out: NDArray,
    K_start: NDArray,
    dist_start: NDArray,
    poses_start: NDArray,
    fixed: tuple[str, ...],
    max_points_per_ring: int,
    size: tuple[int, int],
) -> _FoldScore:
    """Fit the views not ``held_out`` (a boolean mask ``(V,)``) with the terms ``fixed`` held,
    then the held-out views' poses with the intrinsics held, and score them."""
    train = np.flatnonzero(~held_out)
    test = np.flatnonzero(held_out)
    x, res, prob, _ = _adjust(
        [observations[i] for i in train], K_start, dist_start, poses_start[train], None,
        max_points_per_ring, fixed,
    )  # fmt: skip
    K = camera_matrix(x)
    try:
        cov = intrinsics_covariance(prob, x, res, fixed)
        sigma_ms = float(np.mean(projection_uncertainty(K, x[4:9], cov, size).sigma_px ** 2))
    except np.linalg.LinAlgError:
        sigma_ms = float("inf")
    # The held-out views' poses, fitted with the intrinsics held (independent of each other,
    # so one adjustment fits them all).
    _, r, held, _ = _adjust(
        [observations[i] for i in test], K, x[4:9], poses_start[test], None,
        max_points_per_ring, PARAM_NAMES,
    )  # fmt: skip
    views = held.residual_views()
    per_view = np.array([float(np.sqrt(np.mean(r[views == j] ** 2))) for j in range(len(test))])
    return _FoldScore(test, per_view, float(np.sqrt(np.mean(res**2))), sigma_ms)


def select_distortion_model(
    observations: list[TargetObservation],
    K0: NDArray,
    poses0: NDArray,
    *,
    candidates: tuple[str, ...] = tuple(DISTORTION_MODELS),
    folds: int = 3,
    max_points_per_ring: int = 60,
    image_size: tuple[int, int] | None = None,
    check_cancelled: Callable[[], None] | None = None,
    workers: int = 2,
) -> ModelSelection:
    """Choose the distortion terms by their error on held-out views.

    Parameters
    ----------
    observations : list of TargetObservation
        The views the intrinsics are fitted to (found targets), V >= 5.
    K0 : ndarray, shape (3, 3)
        Starting camera matrix.
    poses0 : ndarray, shape (V, 6)
        Starting poses (rotation vector, translation mm) of the views.
    candidates : tuple of str
        Keys of :data:`DISTORTION_MODELS`, simplest first.
    folds : int
        Folds of the cross-validation (views dealt round-robin); fewer when the views are few.
    max_points_per_ring : int
        Edge points per ring in the candidates' fits (fewer than the final fit: faster, and
        the comparison needs no more; the uncertainties compared are all scaled alike).
    image_size : tuple of int, optional
        ``(width, height)``; by default the first observation's.
    check_cancelled : callable, optional
        Called before each fold's fit is started (every candidate's folds): whatever it
        raises stops the choice and comes out of this function (a PLC job's cancellation),
        once the fits already running (at most ``workers - 1``) have ended.
    workers : int
        Fits run at a time, on threads (NumPy's array steps release the GIL).

    Returns
    -------
    ModelSelection
        With fewer than 5 views no fold can be held out: the single radial term ``k1`` is
        chosen, and ``reason`` says so.
    """
    n = len(observations)
    k = _folds(n, folds)
    if k < 2:
        return ModelSelection("k1", (), 0, f"{n} views: too few to hold any out; k1 only")
    check = check_cancelled or (lambda: None)
    fold_of = np.arange(n) % k
    size = image_size or tuple(observations[0].image_size)
    # Every fit starts from one adjustment of all views with every term: the views' poses
    # there are close to any candidate's, so no fit (held-out poses above all) starts far off.
    x_all, _, _, _ = _adjust(observations, K0, np.zeros(5), poses0, None, max_points_per_ring)
    K_start, poses_start = camera_matrix(x_all), x_all[9:].reshape(n, 6)
    tasks = [(name, f) for name in candidates for f in range(k)]

    def run(task: tuple[str, int]) -> _FoldScore:
        name, f = task
        fixed = DISTORTION_MODELS[name]
        dist_start = x_all[4:9].copy()
        for term in fixed:
            dist_start[PARAM_NAMES.index(term) - 4] = 0.0
        return _fold_score(
            observations, fold_of == f, K_start, dist_start, poses_start, fixed,
            max_points_per_ring, size,
        )  # fmt: skip

    # The folds are independent fits (two at a time: NumPy's array steps release the GIL).
    done = thread_map(run, tasks, workers, check)
    scores = []
    for c, name in enumerate(candidates):
        per_view = np.full(n, np.nan)
        fit_rms, sigma_ms = [], []
        for fold in done[c * k : (c + 1) * k]:
            per_view[fold.held_out] = fold.per_view_px
            fit_rms.append(fold.fit_rms_px)
            sigma_ms.append(fold.sigma_ms_px2)
        held_out = float(np.sqrt(np.mean(per_view**2)))
        # A fold whose covariance could not be computed pins nothing: inf (never NaN).
        unc = float(np.sqrt(np.mean(sigma_ms)))
        scores.append(
            ModelScore(
                name=name,
                held_out_rms_px=held_out,
                uncertainty_rms_px=unc if np.isfinite(unc) else float("inf"),
                per_view_px=per_view,
                fit_rms_px=float(np.mean(fit_rms)),
            )
        )
    # Bias: a model is adequate when its held-out error is not worse than the best held-out
    # error by more than one standard error of the paired per-view difference (the views
    # share the noise, so the pairing sees a consistent excess that the RMS alone hides) nor
    # by more than 0.5 % of its mean square (differences below that are no lens's doing);
    # medians throughout, so that one held-out view whose pose fit ran away does not decide.
    best = min(scores, key=lambda s: s.held_out_rms_px)
    adequate = [s for s in scores if _paired_excess(s, best) <= 0.0]

    # Variance: of the adequate models, those whose projection is pinned over the image as
    # well as the best pinned one's (within 5 %), and of those the one with the most terms.
    # Terms the views pin that well cost no variance, and they remove a bias the held-out
    # views cannot see: a decentring term trades against the principal point (a held-out
    # view's pose turns to absorb both), which turns the camera frame and everything given in
    # it (0.1 px of p1 moved cy by 2.9 px on a randomised paper cell).
    # If no model's uncertainty could be computed, the fewest terms.
    least = min(s.uncertainty_rms_px for s in adequate)
    pinned = [s for s in adequate if s.uncertainty_rms_px <= (1.0 + _PINNED_AS_WELL) * least]
    n_fixed = {name: len(fixed) for name, fixed in DISTORTION_MODELS.items()}
    if np.isfinite(least):
        chosen = min(pinned, key=lambda s: n_fixed[s.name])
        why = (
            f"projection uncertainty RMS {chosen.uncertainty_rms_px:.4f} px, within "
            f"{100 * _PINNED_AS_WELL:.0f} % of the lowest ({least:.4f} px) of "
            f"{', '.join(s.name for s in adequate)}; the most terms of "
            f"{', '.join(s.name for s in pinned)}"
        )
    else:
        chosen = max(adequate, key=lambda s: n_fixed[s.name])
        why = (
            f"no projection uncertainty could be computed for "
            f"{', '.join(s.name for s in adequate)}: the fewest terms"
        )
    reason = (
        f"held-out RMS {chosen.held_out_rms_px:.4f} px, not worse than the best held-out "
        f"({best.name}, {best.held_out_rms_px:.4f} px) beyond one standard error; {why}"
    )
    return ModelSelection(chosen.name, tuple(scores), k, reason)


#: An adequate model's projection uncertainty this much above the lowest (relative) still
#: counts as pinned as well.
_PINNED_AS_WELL = 0.05

#: A held-out mean square this much above the best's (relative) is no real excess.
_NEGLIGIBLE_EXCESS = 0.005


def _paired_excess(score: ModelScore, best: ModelScore) -> float:
    """Mean per-view excess of squared held-out error over ``best``, less one standard error
    (and less a negligible 0.5 % of the best's mean square): > 0 means really worse. A view
    whose excess lies beyond ten robust standard deviations (its held-out pose fit ran away)
    is left out, so that one view does not decide."""
    diff = score.per_view_px**2 - best.per_view_px**2
    if score is best or len(diff) < 2:
        return 0.0
    spread = 1.4826 * float(np.median(np.abs(diff - np.median(diff))))
    if spread > 0:
        diff = diff[np.abs(diff - np.median(diff)) <= 10.0 * spread]
    se = float(np.std(diff, ddof=1) / np.sqrt(len(diff))) if len(diff) > 1 else 0.0
    floor = _NEGLIGIBLE_EXCESS * float(np.median(best.per_view_px**2))
    return float(np.mean(diff)) - max(se, floor)


@dataclass(frozen=True)
class UncertaintyMap:
    """1-sigma projection uncertainty over the image (pixels).

    Attributes
    ----------
    u_px, v_px : ndarray, shape (W',), (H',)
        Pixel coordinates of the grid's columns and rows.
    sigma_px : ndarray, shape (H', W')
        Root of the larger eigenvalue of the 2x2 projection covariance at each grid pixel.
    """

    u_px: NDArray
    v_px: NDArray
    sigma_px: NDArray

    @property
    def max_px(self) -> float:
        return float(np.nanmax(self.sigma_px))

    @property
    def median_px(self) -> float:
        return float(np.nanmedian(self.sigma_px))


def projection_uncertainty(
    K: NDArray,
    dist: NDArray,
    covariance9: NDArray,
    image_size: tuple[int, int],
    step_px: int = 32,
) -> UncertaintyMap:
    """Map the projection's 1-sigma uncertainty over the image from the intrinsics' covariance.

    Each grid pixel is unprojected with the model to its camera ray; the projection of a point
    on that ray is differentiated with respect to the nine intrinsics and the covariance
    propagated (first order). The covariance is the intrinsics' block of the adjustment's
    (marginal over the views' poses), so the map says how well the model itself is pinned;
    in this form it does not depend on the point's distance. What a small turn of the camera
    frame would do is taken out first (as mrcal compares models): a principal point traded
    against decentring terms moves every projection alike, and the views' poses turn with it.

    Parameters
    ----------
    K : ndarray, shape (3, 3)
    dist : ndarray, shape (5,)
    covariance9 : ndarray, shape (9, 9)
        Over :data:`PARAM_NAMES`; held terms have zero rows and columns.
    image_size : tuple of int
        ``(width, height)``.
    step_px : int
        Grid spacing.
    """
    w, h = image_size
    u = np.arange(step_px / 2, w, step_px)
    v = np.arange(step_px / 2, h, step_px)
    uu, vv = np.meshgrid(u, v)
    uv = np.column_stack([uu.ravel(), vv.ravel()])
    params = np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.asarray(dist, dtype=np.float64)[:5]]
    xy = _undistort(uv, params)
    points_cam = np.column_stack([xy, np.ones(len(xy))])
    eye = np.broadcast_to(np.eye(3), (len(xy), 3, 3))
    zero = np.zeros_like(points_cam)
    base, d = _project(params, eye, points_cam, zero, parts=True)
    # A turn of the camera frame is not an error of the model (every pose turns with it):
    # remove from each parameter's projection field its best fit by a small rotation.
    eps = 1e-6
    turns = np.stack(
        [(_project(params, eye, points_cam + eps * np.cross(axis, points_cam), zero) - base) / eps
         for axis in np.eye(3)],
        axis=-1,
    )  # fmt: skip
    fields = d.reshape(-1, 9)
    rot = turns.reshape(-1, 3)
    coeffs, *_ = np.linalg.lstsq(rot, fields, rcond=None)
    d = (fields - rot @ coeffs).reshape(d.shape)
    cov = np.einsum("pij,jk,plk->pil", d, np.nan_to_num(covariance9), d)
    sigma = np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, -1], 0.0))
    return UncertaintyMap(u, v, sigma.reshape(uu.shape))


def _undistort(uv: NDArray, params: NDArray, iterations: int = 20) -> NDArray:
    """Normalised coordinates ``(P, 2)`` of distorted pixels ``uv`` (fixed-point iteration)."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = params
    xd = (uv[:, 0] - cx) / fx
    yd = (uv[:, 1] - cy) / fy
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd - dx) / rad
        y = (yd - dy) / rad
    return np.column_stack([x, y])
