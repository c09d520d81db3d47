"""Geometric fits of plane, sphere, cylinder, 3-D circle and line to point clouds.

Each fit runs in two steps:

1. **Robust detection** (optional, when ``threshold_mm`` is given): MSAC, a RANSAC variant that
   scores a hypothesis by its truncated squared distances, on a seeded random subsample of at
   most :data:`RANSAC_SUBSAMPLE` points, with the iteration count adapted to the inlier ratio.
   The best model's inliers are then taken from the full cloud (for a big cloud, after the
   whole robust fit has run on the subsample), alternating with the least squares until the
   inlier set is stable. The inlier band is the threshold, widened to :data:`BAND_SIGMAS`
   robust standard deviations of the residuals where the noise is wider: a band narrower than
   the noise would clip the residuals and report the threshold as the form error.
2. **Geometric least squares** on the inliers: orthogonal distances minimised by
   :func:`scipy.optimize.least_squares` with analytic Jacobians, started from a closed-form or
   algebraic estimate (for the plane and the line the orthogonal least-squares solution *is*
   closed form: the eigenvectors of the scatter matrix, so no iteration is needed). Clouds of
   more than :data:`LSQ_SUBSAMPLE` points are solved on a subsample first and finished on all
   points, which keeps a fit on a million points well under a second.

Every fit returns a frozen dataclass with its parameters, their standard deviations
(``sigma^2 (J^T J)^-1`` with ``sigma^2`` the residual variance, ``sum r^2 / (m - p)``), the
RMS and range (max - min) of the residuals, and the inlier mask. A fit that cannot succeed
(too few points, a degenerate point set such as collinear points for a plane or coplanar
points for a sphere) is falsy and says why in ``reason``; its numbers are NaN.

Orientation: the unit vectors (plane normal, cylinder axis, circle normal, line direction) are
returned with their largest-magnitude component positive, so repeated fits agree in sign.

Form: ``range_mm`` is the form error relative to the least-squares feature. With
``min_zone=True`` the plane and sphere fits also evaluate the minimum-zone (Chebyshev) form,
the smallest possible range over all planes or centres, by linear programming
(:func:`scipy.optimize.linprog`) started from the least-squares fit.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares, linprog

from scanner.core.conventions import check_points

__all__ = [
    "LSQ_SUBSAMPLE",
    "RANSAC_SUBSAMPLE",
    "CircleFit",
    "CylinderFit",
    "Fit",
    "LineFit",
    "PlaneFit",
    "SphereFit",
    "fit_circle",
    "fit_cylinder",
    "fit_line",
    "fit_plane",
    "fit_sphere",
    "min_zone_flatness",
    "min_zone_sphericity",
]

log = logging.getLogger(__name__)

#: RANSAC hypotheses are scored on at most this many points (a seeded random subsample).
RANSAC_SUBSAMPLE = 20_000
#: The cylinder's RANSAC (two points and their normals) runs on at most this many points.
CYLINDER_RANSAC_SUBSAMPLE = 5_000
#: Least squares converges on at most this many points before the final pass on all of them.
LSQ_SUBSAMPLE = 50_000
#: After RANSAC, least squares and the inlier set are alternated until the set is stable, at
#: most this many times.
MAX_ROUNDS = 6
#: After RANSAC the inlier band widens to this many robust standard deviations of the
#: residuals where the noise is wider than the threshold.
BAND_SIGMAS = 4.0
#: Relative size of the smallest singular value below which a point set counts as degenerate.
DEGENERACY_RATIO = 1e-6

_NAN3 = (math.nan, math.nan, math.nan)

SeedLike = int | np.random.Generator | None


def _nan_array(n: int) -> NDArray:
    return np.full(n, np.nan)


def _empty_mask() -> NDArray:
    return np.zeros(0, dtype=bool)


def _empty() -> NDArray:
    return np.zeros(0)


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True, eq=False)
class Fit:
    """What every fit carries; subclasses add the feature's parameters.

    Attributes
    ----------
    reason : str
        Empty for a successful fit; why it failed otherwise (the fit is then falsy).
    inliers : ndarray of bool, shape (N,)
        Which input points the least squares used (all of them without RANSAC).
    residuals_mm : ndarray, shape (M,)
        Signed orthogonal residuals of the M inliers, in input order, mm.
    rms_mm, range_mm : float
        RMS and range (max - min) of the residuals: the least-squares form error.
    min_zone_mm : float or None
        Minimum-zone (Chebyshev) form error when it was requested and is defined.
    cov : ndarray, shape (p, p)
        Covariance of the fit's internal parameters (see the subclass).
    """

    reason: str = ""
    inliers: NDArray = field(default_factory=_empty_mask)
    residuals_mm: NDArray = field(default_factory=_empty)
    rms_mm: float = math.nan
    range_mm: float = math.nan
    min_zone_mm: float | None = None
    cov: NDArray = field(default_factory=lambda: np.zeros((0, 0)))

    kind: str = "fit"

    @property
    def ok(self) -> bool:
        return not self.reason

    def __bool__(self) -> bool:
        return self.ok

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    @property
    def inlier_indices(self) -> NDArray:
        return np.flatnonzero(self.inliers)

    def signed_distance(self, points: ArrayLike) -> NDArray:  # pragma: no cover - abstract
        raise NotImplementedError

    def _params_json(self) -> dict[str, Any]:  # pragma: no cover - abstract
        return {}

    def to_json(self) -> dict[str, Any]:
        """Parameters, their standard deviations and the residual figures (JSON-ready)."""
        out: dict[str, Any] = {"kind": self.kind, "ok": self.ok}
        if not self.ok:
            out["reason"] = self.reason
            return out
        out.update(self._params_json())
        out.update(
            {
                "n_points": int(self.inliers.size),
                "n_inliers": self.n_inliers,
                "rms_mm": float(self.rms_mm),
                "range_mm": float(self.range_mm),
            }
        )
        if self.min_zone_mm is not None:
            out["min_zone_mm"] = float(self.min_zone_mm)
        return _finite_or_none(out)


def _finite_or_none(value: Any) -> Any:
    """NaN and inf (an undetermined standard deviation) become None: JSON has no NaN."""
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_or_none(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


@dataclass(frozen=True, kw_only=True, eq=False)
class PlaneFit(Fit):
    """Plane ``normal . p + d_mm = 0`` with ``|normal| = 1``.

    ``cov`` is over (tilt about ``u``, tilt about ``v`` [rad], offset along the normal at the
    centroid [mm]) where ``u, v`` complete the normal to a right-handed frame.
    """

    normal: NDArray = field(default_factory=lambda: _nan_array(3))
    d_mm: float = math.nan
    centroid_mm: NDArray = field(default_factory=lambda: _nan_array(3))
    normal_std: NDArray = field(default_factory=lambda: _nan_array(3))
    d_std_mm: float = math.nan
    kind: str = "plane"

    def signed_distance(self, points: ArrayLike) -> NDArray:
        """Signed distance of ``(N, 3)`` points from the plane, positive on the normal's side."""
        return np.asarray(points, dtype=np.float64) @ self.normal + self.d_mm

    def _params_json(self) -> dict[str, Any]:
        return {
            "normal": self.normal.tolist(),
            "d_mm": float(self.d_mm),
            "centroid_mm": self.centroid_mm.tolist(),
            "normal_std": self.normal_std.tolist(),
            "d_std_mm": float(self.d_std_mm),
        }


@dataclass(frozen=True, kw_only=True, eq=False)
class SphereFit(Fit):
    """Sphere of centre ``center_mm`` and radius ``radius_mm``; ``cov`` over (cx, cy, cz, r)."""

    center_mm: NDArray = field(default_factory=lambda: _nan_array(3))
    radius_mm: float = math.nan
    center_std_mm: NDArray = field(default_factory=lambda: _nan_array(3))
    radius_std_mm: float = math.nan
    kind: str = "sphere"

    @property
    def diameter_mm(self) -> float:
        return 2.0 * self.radius_mm

    def signed_distance(self, points: ArrayLike) -> NDArray:
        """Radial deviation ``|p - c| - r`` of ``(N, 3)`` points, positive outside."""
        p = np.asarray(points, dtype=np.float64)
        return _rownorm(p - self.center_mm) - self.radius_mm

    def _params_json(self) -> dict[str, Any]:
        return {
            "center_mm": self.center_mm.tolist(),
            "radius_mm": float(self.radius_mm),
            "diameter_mm": float(self.diameter_mm),
            "center_std_mm": self.center_std_mm.tolist(),
            "radius_std_mm": float(self.radius_std_mm),
        }


@dataclass(frozen=True, kw_only=True, eq=False)
class CylinderFit(Fit):
    """Cylinder of unit ``axis`` through ``point_mm`` (the axis point nearest the inliers'
    centroid) and radius ``radius_mm``.

    ``cov`` is over (axis tilt about ``u``, about ``v`` [rad], axis shift along ``u``, along
    ``v`` [mm], radius [mm]) with ``u, v`` perpendicular to the axis.
    """

    axis: NDArray = field(default_factory=lambda: _nan_array(3))
    point_mm: NDArray = field(default_factory=lambda: _nan_array(3))
    radius_mm: float = math.nan
    axis_std: NDArray = field(default_factory=lambda: _nan_array(3))
    point_std_mm: NDArray = field(default_factory=lambda: _nan_array(3))
    radius_std_mm: float = math.nan
    kind: str = "cylinder"

    @property
    def diameter_mm(self) -> float:
        return 2.0 * self.radius_mm

    def signed_distance(self, points: ArrayLike) -> NDArray:
        """Radial deviation of ``(N, 3)`` points from the cylinder surface, positive outside."""
        q = np.asarray(points, dtype=np.float64) - self.point_mm
        h = q - np.outer(q @ self.axis, self.axis)
        return _rownorm(h) - self.radius_mm

    def _params_json(self) -> dict[str, Any]:
        return {
            "axis": self.axis.tolist(),
            "point_mm": self.point_mm.tolist(),
            "radius_mm": float(self.radius_mm),
            "diameter_mm": float(self.diameter_mm),
            "axis_std": self.axis_std.tolist(),
            "point_std_mm": self.point_std_mm.tolist(),
            "radius_std_mm": float(self.radius_std_mm),
        }


@dataclass(frozen=True, kw_only=True, eq=False)
class CircleFit(Fit):
    """Circle in 3-D: centre, unit normal of its plane and radius.

    ``residuals_mm`` are the in-plane radial deviations (roundness); ``out_of_plane_mm`` the
    distances from the circle's plane; ``rms_mm`` is over the full 3-D distances to the circle.
    ``cov`` is over (normal tilt about ``u``, about ``v`` [rad], centre x, y, z [mm], radius).
    """

    center_mm: NDArray = field(default_factory=lambda: _nan_array(3))
    normal: NDArray = field(default_factory=lambda: _nan_array(3))
    radius_mm: float = math.nan
    center_std_mm: NDArray = field(default_factory=lambda: _nan_array(3))
    normal_std: NDArray = field(default_factory=lambda: _nan_array(3))
    radius_std_mm: float = math.nan
    out_of_plane_mm: NDArray = field(default_factory=_empty)
    kind: str = "circle"

    @property
    def diameter_mm(self) -> float:
        return 2.0 * self.radius_mm

    def signed_distance(self, points: ArrayLike) -> NDArray:
        """In-plane radial deviation of ``(N, 3)`` points, positive outside the circle."""
        q = np.asarray(points, dtype=np.float64) - self.center_mm
        h = q - np.outer(q @ self.normal, self.normal)
        return _rownorm(h) - self.radius_mm

    def distance(self, points: ArrayLike) -> NDArray:
        """Unsigned 3-D distance of ``(N, 3)`` points from the circle."""
        return _circle_distance(
            np.asarray(points, dtype=np.float64), self.center_mm, self.normal, self.radius_mm
        )

    def _params_json(self) -> dict[str, Any]:
        return {
            "center_mm": self.center_mm.tolist(),
            "normal": self.normal.tolist(),
            "radius_mm": float(self.radius_mm),
            "diameter_mm": float(self.diameter_mm),
            "center_std_mm": self.center_std_mm.tolist(),
            "normal_std": self.normal_std.tolist(),
            "radius_std_mm": float(self.radius_std_mm),
        }


@dataclass(frozen=True, kw_only=True, eq=False)
class LineFit(Fit):
    """Line through ``point_mm`` (the inliers' centroid) along unit ``direction``.

    ``residuals_mm`` are the (unsigned) distances from the line; ``cov`` is over (offset along
    ``u``, slope along ``u``, offset along ``v``, slope along ``v``) in a frame whose third axis
    is the direction.
    """

    point_mm: NDArray = field(default_factory=lambda: _nan_array(3))
    direction: NDArray = field(default_factory=lambda: _nan_array(3))
    point_std_mm: NDArray = field(default_factory=lambda: _nan_array(3))
    direction_std: NDArray = field(default_factory=lambda: _nan_array(3))
    kind: str = "line"

    def signed_distance(self, points: ArrayLike) -> NDArray:
        """Distance of ``(N, 3)`` points from the line (never negative)."""
        q = np.asarray(points, dtype=np.float64) - self.point_mm
        return _rownorm(q - np.outer(q @ self.direction, self.direction))

    def _params_json(self) -> dict[str, Any]:
        return {
            "point_mm": self.point_mm.tolist(),
            "direction": self.direction.tolist(),
            "point_std_mm": self.point_std_mm.tolist(),
            "direction_std": self.direction_std.tolist(),
        }


# --------------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------------


def _rng(seed: SeedLike) -> np.random.Generator:
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


def _orient(v: NDArray) -> NDArray:
    """Unit vector with its largest-magnitude component positive."""
    v = v / np.linalg.norm(v)
    return -v if v[np.argmax(np.abs(v))] < 0 else v


def _perp_basis(n: NDArray) -> tuple[NDArray, NDArray]:
    """Unit ``u, v`` with ``(u, v, n)`` right-handed and orthonormal."""
    helper = np.eye(3)[np.argmin(np.abs(n))]
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def _scatter_eig(points: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Centroid, eigenvalues (ascending) and eigenvectors (columns) of the scatter matrix."""
    c = points.mean(axis=0)
    x = points - c
    w, v = np.linalg.eigh(x.T @ x)
    return c, np.maximum(w, 0.0), v


def _degenerate_rank(points: NDArray) -> int:
    """Numerical rank of the centred point set: 0 coincident, 1 collinear, 2 coplanar, 3."""
    _, w, _ = _scatter_eig(points)
    s = np.sqrt(w)
    if s[2] <= 1e-12 * max(1.0, float(np.abs(points).max())):
        return 0
    return int(1 + (s[1] > DEGENERACY_RATIO * s[2]) + (s[0] > DEGENERACY_RATIO * s[2]))


def _rownorm(a: NDArray) -> NDArray:
    """Euclidean norm of each row of an ``(N, 3)`` array (faster than ``linalg.norm``)."""
    return np.sqrt(np.einsum("ij,ij->i", a, a))


def _extent(points: NDArray) -> float:
    """Largest side of the bounding box (from at most ~100k points: only a scale is needed)."""
    step = max(1, len(points) // 100_000)
    return float(np.ptp(points[::step], axis=0).max())


def _take(points: NDArray, mask: NDArray) -> NDArray:
    """``points[mask]`` without the copy when every point is selected."""
    return points if mask.all() else points[mask]


def _subsample(n: int, k: int, rng: np.random.Generator) -> NDArray:
    return np.arange(n) if n <= k else np.sort(rng.choice(n, size=k, replace=False))


def _residual_stats(res: NDArray) -> tuple[float, float]:
    return float(np.sqrt(np.mean(res**2))), float(res.max() - res.min())


def _cov(jac: NDArray, res: NDArray) -> NDArray:
    """``sigma^2 (J^T J)^-1`` with ``sigma^2 = sum r^2 / (m - p)``."""
    m, p = jac.shape
    dof = max(m - p, 1)
    sigma2 = float(res @ res) / dof
    jtj = jac.T @ jac
    try:
        return sigma2 * np.linalg.inv(jtj)
    except np.linalg.LinAlgError:
        return np.full((p, p), np.nan)


def _gauss_newton_polish(
    fun: Callable[[NDArray, NDArray], NDArray],
    jac: Callable[[NDArray, NDArray], NDArray],
    x: NDArray,
    pts: NDArray,
    max_steps: int = 3,
) -> NDArray | None:
    """Gauss-Newton steps on all points from a nearly converged ``x``; None if a step fails
    to lower the cost (the caller then runs the full least squares)."""
    r = fun(x, pts)
    cost = float(r @ r)
    for _ in range(max_steps):
        j = jac(x, pts)
        jtj = j.T @ j
        try:
            step = np.linalg.solve(jtj, -(j.T @ r))
            # parameter standard deviations: a step far below them changes nothing that matters
            std = np.sqrt(np.abs(np.diag(np.linalg.inv(jtj))) * cost / max(len(r) - len(x), 1))
        except np.linalg.LinAlgError:
            return None
        x_new = x + step
        r_new = fun(x_new, pts)
        cost_new = float(r_new @ r_new)
        if not math.isfinite(cost_new) or cost_new > cost * (1 + 1e-9) + 1e-24 * len(pts):
            return None
        x, r, cost = x_new, r_new, cost_new
        if np.all(np.abs(step) <= np.maximum(1e-4 * std, 1e-12 * (1.0 + np.abs(x)))):
            break
    return x


def _lsq(
    fun: Callable[[NDArray, NDArray], NDArray],
    jac: Callable[[NDArray, NDArray], NDArray],
    x0: NDArray,
    pts: NDArray,
    rng: np.random.Generator,
) -> NDArray:
    """Minimise ``sum fun(x, pts)^2`` with :func:`scipy.optimize.least_squares`.

    A cloud of more than :data:`LSQ_SUBSAMPLE` points is solved on a random subsample first;
    from there (within about ``sigma / sqrt(LSQ_SUBSAMPLE)`` of the optimum) Gauss-Newton steps
    on all points converge quadratically, at a fraction of the cost of a full solver run. If a
    step does not lower the cost, ``least_squares`` runs on all points instead.
    """
    x = np.asarray(x0, dtype=np.float64)
    if len(pts) > LSQ_SUBSAMPLE:
        sub = pts[_subsample(len(pts), LSQ_SUBSAMPLE, rng)]
        x = least_squares(fun, x, jac=jac, args=(sub,), method="lm", xtol=1e-12, ftol=1e-12).x
        polished = _gauss_newton_polish(fun, jac, x, pts)
        if polished is not None:
            return polished
        log.debug("Gauss-Newton polish did not converge; full least squares")
    sol = least_squares(fun, x, jac=jac, args=(pts,), method="lm", xtol=1e-13, ftol=1e-12)
    log.debug("least squares on %d points: %d evaluations", len(pts), sol.nfev)
    return sol.x


def _ransac(
    n: int,
    sample_size: int,
    model_from_sample: Callable[[NDArray], Any],
    distances: Callable[[Any], NDArray],
    threshold: float,
    rng: np.random.Generator,
    max_iterations: int,
    confidence: float = 0.999,
) -> Any:
    """MSAC: the model with the smallest sum of truncated squared distances, or None."""
    best, best_cost = None, math.inf
    needed = max_iterations
    it = 0
    t2 = threshold * threshold
    while it < min(needed, max_iterations):
        it += 1
        idx = rng.choice(n, size=sample_size, replace=False)
        model = model_from_sample(idx)
        if model is None:
            continue
        d = distances(model)
        if not np.all(np.isfinite(d)):
            continue
        cost = float(np.minimum(d * d, t2).sum())
        if cost < best_cost:
            best, best_cost = model, cost
            w = float(np.count_nonzero(d < threshold)) / n
            if w >= 1.0:
                needed = it
            elif w > 0:
                denom = math.log(max(1e-300, 1.0 - w**sample_size))
                if denom < 0:
                    needed = min(needed, math.ceil(math.log(1.0 - confidence) / denom))
    log.debug("RANSAC: %d iterations, cost %.4g", it, best_cost)
    return best


def _radius_bounds(
    radius_range_mm: tuple[float, float] | None, sub: NDArray
) -> tuple[float, float]:
    """Radii a RANSAC hypothesis may have: the given range, else up to the sample's extent
    (a sphere or cylinder much larger than the cloud is a plane in disguise)."""
    if radius_range_mm is None:
        return 0.0, _extent(sub)
    lo, hi = (float(r) for r in radius_range_mm)
    if not (0 <= lo < hi and math.isfinite(hi)):
        raise ValueError(f"radius_range_mm: expected 0 <= min < max, got {radius_range_mm}")
    return lo, hi


def _band(threshold_mm: float, residuals: NDArray, signed: bool = True) -> float:
    """Inlier band after RANSAC: the threshold, or :data:`BAND_SIGMAS` robust standard
    deviations of the current inliers' residuals when the noise is wider (a band narrower than
    the noise would clip the residuals and report the threshold as the form error).

    ``signed``: residuals are signed (MAD estimate); otherwise they are 2-D distances (line,
    circle), whose median is ``1.1774 sigma`` (Rayleigh).
    """
    r = np.asarray(residuals, dtype=np.float64)
    if r.size < 10:
        return threshold_mm
    if signed:
        sigma = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    else:
        sigma = float(np.median(np.abs(r))) / 1.1774
    return max(threshold_mm, BAND_SIGMAS * sigma)


def _check_threshold(threshold_mm: float | None) -> None:
    if threshold_mm is not None and not (math.isfinite(threshold_mm) and threshold_mm > 0):
        raise ValueError(f"threshold_mm: expected a positive number or None, got {threshold_mm}")


# --------------------------------------------------------------------------------------------
# Plane
# --------------------------------------------------------------------------------------------


def _plane_from_points(p: NDArray) -> tuple[NDArray, float, NDArray] | None:
    c, w, v = _scatter_eig(p)
    s = np.sqrt(w)
    if s[1] <= DEGENERACY_RATIO * s[2]:
        return None
    n = _orient(v[:, 0])
    return n, float(-n @ c), c


def fit_plane(
    points: ArrayLike,
    threshold_mm: float | None = None,
    *,
    min_zone: bool = False,
    seed: SeedLike = 0,
    max_iterations: int = 1000,
) -> PlaneFit:
    """Fit a plane by orthogonal least squares, optionally after RANSAC.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points in any frame, mm. N >= 3, not collinear.
    threshold_mm : float, optional
        RANSAC inlier distance; without it every point is an inlier.
    min_zone : bool
        Also evaluate the minimum-zone flatness (``min_zone_mm``).
    seed : int or Generator
        Seeds the RANSAC sampling (a fit is repeatable).

    Returns
    -------
    PlaneFit
        Unit normal and offset (``normal . p + d = 0``), their standard deviations, residual
        RMS and range, or a failed fit (falsy) whose ``reason`` says why.
    """
    pts = check_points(points, min_count=0)
    _check_threshold(threshold_mm)
    n_all = len(pts)
    if n_all < 3:
        return PlaneFit(reason=f"too few points: expected at least 3, got {n_all}")
    rng = _rng(seed)
    mask = np.ones(n_all, dtype=bool)
    if threshold_mm is not None:
        sub_idx = _subsample(n_all, RANSAC_SUBSAMPLE, rng)
        sub = pts[sub_idx]

        def model(idx: NDArray) -> Any:
            a, b, c = sub[idx]
            n = np.cross(b - a, c - a)
            nn = np.linalg.norm(n)
            if nn <= 1e-12 * max(1.0, np.linalg.norm(b - a) * np.linalg.norm(c - a)):
                return None
            n = n / nn
            return n, -float(n @ a)

        best = _ransac(
            len(sub), 3, model, lambda m: np.abs(sub @ m[0] + m[1]), threshold_mm, rng,
            max_iterations,
        )  # fmt: skip
        if best is None:
            return PlaneFit(reason="degenerate: RANSAC found no plane (collinear points?)")
        mask = np.abs(pts @ best[0] + best[1]) < threshold_mm
        for _ in range(MAX_ROUNDS):  # refine the inlier set once the plane is least-squares
            if np.count_nonzero(mask) < 3:
                break
            est = _plane_from_points(_take(pts, mask))
            if est is None:
                break
            dist = pts @ est[0] + est[1]
            new = np.abs(dist) < _band(threshold_mm, dist[mask])
            if np.array_equal(new, mask):
                break
            mask = new
    inl = _take(pts, mask)
    if len(inl) < 3:
        return PlaneFit(reason=f"too few inliers: expected at least 3, got {len(inl)}")
    est = _plane_from_points(inl)
    if est is None:
        return PlaneFit(reason="degenerate: the points are collinear, a plane is not determined")
    n, d, c = est
    res = inl @ n + d
    rms, rng_ = _residual_stats(res)
    # Covariance: tilt (a, b) about the in-plane axes and offset t at the centroid.
    u, v = _perp_basis(n)
    x = inl - c
    jac = np.column_stack([x @ u, x @ v, -np.ones(len(inl))])
    cov = _cov(jac, res) if len(inl) > 3 else np.full((3, 3), np.nan)
    b = np.column_stack([u, v])  # dn = a u + b v
    cov_n = b @ cov[:2, :2] @ b.T
    g = np.array([-(u @ c), -(v @ c), -1.0])  # dd/d(a, b, t)
    mz = min_zone_flatness(inl, n) if min_zone else None
    return PlaneFit(
        inliers=mask, residuals_mm=res, rms_mm=rms, range_mm=rng_, min_zone_mm=mz, cov=cov,
        normal=n, d_mm=d, centroid_mm=c, normal_std=np.sqrt(np.maximum(np.diag(cov_n), 0)),
        d_std_mm=float(np.sqrt(max(g @ cov @ g, 0.0))),
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Sphere
# --------------------------------------------------------------------------------------------


def _sphere_algebraic(p: NDArray) -> tuple[NDArray, float] | None:
    """Kasa fit: ``|p|^2 = 2 c . p + (r^2 - |c|^2)`` by linear least squares (centred data)."""
    c0 = p.mean(axis=0)
    x = p - c0
    a = np.column_stack([2 * x, np.ones(len(x))])
    b = np.einsum("ij,ij->i", x, x)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    r2 = sol[3] + sol[:3] @ sol[:3]
    if not np.all(np.isfinite(sol)) or r2 <= 0:
        return None
    return c0 + sol[:3], float(np.sqrt(r2))


class _SphereModel:
    """Residuals ``|p - c| - r`` and their Jacobian, sharing the work between the two calls."""

    def __init__(self) -> None:
        self._key: tuple[bytes, int] | None = None

    def _eval(self, x: NDArray, p: NDArray) -> tuple[NDArray, NDArray]:
        key = (x.tobytes(), id(p))
        if key != self._key:
            q = p - x[:3]
            self._q, self._dist = q, _rownorm(q)
            self._key = key
        return self._q, self._dist

    def fun(self, x: NDArray, p: NDArray) -> NDArray:
        return self._eval(x, p)[1] - x[3]

    def jac(self, x: NDArray, p: NDArray) -> NDArray:
        q, dist = self._eval(x, p)
        jac = np.empty((len(p), 4))
        np.divide(q, -np.maximum(dist, 1e-300)[:, None], out=jac[:, :3])
        jac[:, 3] = -1.0
        return jac


def _sphere_fun(x: NDArray, p: NDArray) -> NDArray:
    return _rownorm(p - x[:3]) - x[3]


def fit_sphere(
    points: ArrayLike,
    threshold_mm: float | None = None,
    *,
    min_zone: bool = False,
    seed: SeedLike = 0,
    max_iterations: int = 1000,
    radius_range_mm: tuple[float, float] | None = None,
) -> SphereFit:
    """Fit a sphere by orthogonal (radial) least squares, optionally after RANSAC.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points on the sphere, mm. N >= 4, not coplanar.
    threshold_mm : float, optional
        RANSAC inlier distance; without it every point is an inlier.
    min_zone : bool
        Also evaluate the minimum-zone sphericity (``min_zone_mm``).
    radius_range_mm : (float, float), optional
        Radii a RANSAC hypothesis may have (e.g. nominal +-20 %); without it, at most the
        cloud's extent, so that a plane is not taken for a huge sphere.
    seed : int or Generator
        Seeds RANSAC and the least-squares subsample.

    Returns
    -------
    SphereFit
        Centre, radius, their standard deviations, residual RMS and range (the probing form
        error), or a failed fit (falsy) whose ``reason`` says why.
    """
    pts = check_points(points, min_count=0)
    _check_threshold(threshold_mm)
    n_all = len(pts)
    if n_all < 4:
        return SphereFit(reason=f"too few points: expected at least 4, got {n_all}")
    rng = _rng(seed)
    mask = np.ones(n_all, dtype=bool)
    presolved = False
    if threshold_mm is not None and n_all > RANSAC_SUBSAMPLE:
        # RANSAC and the inlier rounds on a subsample, then the full cloud from that model
        pre = fit_sphere(
            pts[_subsample(n_all, RANSAC_SUBSAMPLE, rng)], threshold_mm, seed=rng,
            max_iterations=max_iterations, radius_range_mm=radius_range_mm,
        )  # fmt: skip
        if not pre:
            return pre
        mask = np.abs(pre.signed_distance(pts)) < _band(threshold_mm, pre.residuals_mm)
        presolved = True
    if threshold_mm is not None and not presolved:
        sub = pts[_subsample(n_all, RANSAC_SUBSAMPLE, rng)]
        r_lo, r_hi = _radius_bounds(radius_range_mm, sub)

        def model(idx: NDArray) -> Any:
            s = sub[idx]
            # |p_i - c|^2 = |p_0 - c|^2  ->  2 (p_i - p_0) . c = |p_i|^2 - |p_0|^2
            a = 2 * (s[1:] - s[0])
            b = np.einsum("ij,ij->i", s[1:], s[1:]) - s[0] @ s[0]
            if abs(np.linalg.det(a)) < 1e-9 * np.abs(a).max() ** 3:
                return None
            c = np.linalg.solve(a, b)
            r = float(np.linalg.norm(s[0] - c))
            return (c, r) if r_lo <= r <= r_hi else None

        best = _ransac(
            len(sub), 4, model,
            lambda m: np.abs(_rownorm(sub - m[0]) - m[1]),
            threshold_mm, rng, max_iterations,
        )  # fmt: skip
        if best is None:
            return SphereFit(reason="degenerate: RANSAC found no sphere (coplanar points?)")
        mask = np.abs(_rownorm(pts - best[0]) - best[1]) < threshold_mm
    rank = _degenerate_rank(_take(pts, mask)) if np.count_nonzero(mask) >= 4 else -1
    if rank == -1:
        return SphereFit(
            reason=f"too few inliers: expected at least 4, got {np.count_nonzero(mask)}"
        )
    if rank < 3:
        what = {0: "coincident", 1: "collinear", 2: "coplanar"}[rank]
        return SphereFit(reason=f"degenerate: the points are {what}, a sphere is not determined")
    x = None
    for rnd in range(MAX_ROUNDS if threshold_mm is not None else 1):
        inl = _take(pts, mask)
        init = (
            (x[:3], x[3])
            if x is not None
            else _sphere_algebraic(inl[_subsample(len(inl), LSQ_SUBSAMPLE, rng)])
        )
        if init is None:
            return SphereFit(reason="degenerate: no sphere through the points (algebraic fit)")
        model = _SphereModel()
        x = _lsq(model.fun, model.jac, np.r_[init[0], init[1]], inl, rng)
        if threshold_mm is None:
            break
        dist = _sphere_fun(x, pts)
        new = np.abs(dist) < _band(threshold_mm, dist[mask])
        if np.array_equal(new, mask) or np.count_nonzero(new) < 5 or rnd == MAX_ROUNDS - 1:
            break  # (on the last round keep the mask the parameters belong to)
        mask = new
    inl = _take(pts, mask)
    c, r = x[:3], float(abs(x[3]))
    extent = _extent(inl)
    if not (np.all(np.isfinite(x)) and r < 1e4 * extent):
        return SphereFit(reason=f"degenerate: radius {r:.4g} mm for points spanning {extent:.4g} mm "
                         "(nearly planar points do not determine a sphere)")  # fmt: skip
    res = _sphere_fun(np.r_[c, r], inl)
    rms, rng_ = _residual_stats(res)
    jac = _SphereModel().jac(np.r_[c, r], inl)
    cov = _cov(jac, res) if len(inl) > 4 else np.full((4, 4), np.nan)
    std = np.sqrt(np.maximum(np.diag(cov), 0))
    mz = min_zone_sphericity(inl, c) if min_zone else None
    return SphereFit(
        inliers=mask, residuals_mm=res, rms_mm=rms, range_mm=rng_, min_zone_mm=mz, cov=cov,
        center_mm=c.copy(), radius_mm=r, center_std_mm=std[:3], radius_std_mm=float(std[3]),
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Cylinder
# --------------------------------------------------------------------------------------------


def _fibonacci_hemisphere(n: int) -> NDArray:
    i = np.arange(n) + 0.5
    z = i / n  # uniform in z on (0, 1]: uniform on the hemisphere
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    r = np.sqrt(1 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _circle_scores(x: NDArray, y: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Kasa circle fits of ``(M, D)`` coordinate columns: centres, radii, geometric RMS."""
    m = x.shape[0]
    z = x * x + y * y
    sxx, syy, sxy = (x * x).sum(0), (y * y).sum(0), (x * y).sum(0)
    sx, sy = x.sum(0), y.sum(0)
    sxz, syz, sz = (x * z).sum(0), (y * z).sum(0), z.sum(0)
    a = np.stack(
        [np.stack([sxx, sxy, sx], -1), np.stack([sxy, syy, sy], -1),
         np.stack([sx, sy, np.full_like(sx, m)], -1)], -2,
    )  # fmt: skip
    b = np.stack([sxz, syz, sz], -1)
    sol = np.linalg.solve(a + 1e-12 * np.eye(3), b[..., None])[..., 0]
    cx, cy = sol[:, 0] / 2, sol[:, 1] / 2
    r = np.sqrt(np.maximum(sol[:, 2] + cx * cx + cy * cy, 0))
    rms = np.sqrt(np.mean((np.hypot(x - cx, y - cy) - r) ** 2, axis=0))
    return cx, cy, r, rms


def _cyl_setup(axis: NDArray, point: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    a0 = axis / np.linalg.norm(axis)
    u, v = _perp_basis(a0)
    return a0, u, v, point


def _cyl_fun_factory(
    a0: NDArray, u: NDArray, v: NDArray, c0: NDArray
) -> tuple[Callable[..., NDArray], Callable[..., NDArray], Callable[..., Any]]:
    """Residuals (distance to the axis minus radius) and Jacobian for parameters
    ``(tilt_u, tilt_v, shift_u, shift_v, r)``: axis ``a ~ a0 + tilt_u u + tilt_v v`` through
    ``c0 + shift_u u + shift_v v``."""
    cache: dict[str, Any] = {"key": None}

    def unpack(x: NDArray, p: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray, float]:
        key = (x.tobytes(), id(p))
        if cache["key"] != key:
            m = a0 + x[0] * u + x[1] * v
            mn = float(np.linalg.norm(m))
            a = m / mn
            q = p - (c0 + x[2] * u + x[3] * v)
            t = q @ a
            qu, qv = q @ u, q @ v
            dist = np.sqrt(np.maximum(np.einsum("ij,ij->i", q, q) - t * t, 0.0))
            cache.update(key=key, val=(t, qu - t * (a @ u), qv - t * (a @ v), dist, mn))
        return cache["val"]

    def fun(x: NDArray, p: NDArray) -> NDArray:
        return unpack(x, p)[3] - x[4]

    def jac(x: NDArray, p: NDArray) -> NDArray:
        t, hu, hv, dist, mn = unpack(x, p)
        inv = 1.0 / np.maximum(dist, 1e-300)
        hu, hv = hu * inv, hv * inv
        j = np.empty((len(p), 5))
        np.multiply(t, hu, out=j[:, 0])
        j[:, 0] *= -1.0 / mn
        np.multiply(t, hv, out=j[:, 1])
        j[:, 1] *= -1.0 / mn
        np.negative(hu, out=j[:, 2])
        np.negative(hv, out=j[:, 3])
        j[:, 4] = -1.0
        return j

    return fun, jac, unpack


def _cylinder_from_normals(
    p1: NDArray, n1: NDArray, p2: NDArray, n2: NDArray
) -> tuple[NDArray, NDArray, float] | None:
    """Axis, axis point and radius from two surface points and their normals."""
    a = np.cross(n1, n2)
    an = np.linalg.norm(a)
    if an < 1e-3:
        return None
    a /= an
    u, v = _perp_basis(a)
    q1, q2 = np.array([p1 @ u, p1 @ v]), np.array([p2 @ u, p2 @ v])
    m1, m2 = np.array([n1 @ u, n1 @ v]), np.array([n2 @ u, n2 @ v])
    # q1 + s m1 = q2 + t m2 (the normal lines meet at the axis)
    mat = np.column_stack([m1, -m2])
    if abs(np.linalg.det(mat)) < 1e-6:
        return None
    s, t = np.linalg.solve(mat, q2 - q1)
    c2 = 0.5 * (q1 + s * m1 + q2 + t * m2)
    r = 0.5 * (np.linalg.norm(q1 - c2) + np.linalg.norm(q2 - c2))
    point = c2[0] * u + c2[1] * v
    return a, point, float(r)


def _cylinder_initial_axes(p: NDArray, n_directions: int = 400) -> list[tuple[NDArray, NDArray]]:
    """Candidate (axis, axis point) from a direction search: the projection of the points along
    the true axis is a circle, so rank directions by the RMS of a circle fit of the projection."""
    c, _, evec = _scatter_eig(p)
    x = p - c
    dirs = np.vstack([_fibonacci_hemisphere(n_directions), evec.T])
    us, vs = zip(*(_perp_basis(d) for d in dirs))
    u, v = np.array(us), np.array(vs)
    cx, cy, r, rms = _circle_scores(x @ u.T, x @ v.T)
    spread = _rownorm(x).max()
    rms = np.where(np.isfinite(rms) & (r < 1e3 * spread), rms, np.inf)
    order = np.argsort(rms)[:3]
    return [(dirs[k], c + cx[k] * u[k] + cy[k] * v[k]) for k in order]


def fit_cylinder(
    points: ArrayLike,
    threshold_mm: float | None = None,
    *,
    seed: SeedLike = 0,
    max_iterations: int = 1000,
    radius_range_mm: tuple[float, float] | None = None,
    axis_hint: ArrayLike | None = None,
) -> CylinderFit:
    """Fit a cylinder by orthogonal (radial) least squares, optionally after RANSAC.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points on the cylinder's surface, mm (a partial arc will do). N >= 5.
    threshold_mm : float, optional
        RANSAC inlier distance (hypotheses from two points and their Open3D normals); without
        it every point is an inlier.
    radius_range_mm : (float, float), optional
        Radii a RANSAC hypothesis may have (e.g. nominal +-20 %); without it, at most the
        cloud's extent, so that a plane is not taken for a huge sphere.
    seed : int or Generator
        Seeds RANSAC and the subsamples.
    axis_hint : array_like, shape (3,), optional
        Approximate axis direction (e.g. the nominal), tried besides the direction search.

    Returns
    -------
    CylinderFit
        Axis, axis point, radius and their standard deviations, residual RMS and range, or a
        failed fit (falsy) whose ``reason`` says why.
    """
    pts = check_points(points, min_count=0)
    _check_threshold(threshold_mm)
    n_all = len(pts)
    if n_all < 6:
        return CylinderFit(reason=f"too few points: expected at least 6, got {n_all}")
    rank = _degenerate_rank(pts)
    if rank < 2:
        return CylinderFit(
            reason="degenerate: the points are collinear, a cylinder is not determined"
        )
    rng = _rng(seed)
    mask = np.ones(n_all, dtype=bool)
    candidates: list[tuple[NDArray, NDArray]] = []
    presolved = False
    if threshold_mm is not None and n_all > CYLINDER_RANSAC_SUBSAMPLE:
        pre = fit_cylinder(
            pts[_subsample(n_all, CYLINDER_RANSAC_SUBSAMPLE, rng)], threshold_mm, seed=rng,
            max_iterations=max_iterations, radius_range_mm=radius_range_mm, axis_hint=axis_hint,
        )  # fmt: skip
        if not pre:
            return pre
        mask = np.abs(pre.signed_distance(pts)) < _band(threshold_mm, pre.residuals_mm)
        candidates.append((pre.axis, pre.point_mm))
        presolved = True
    if threshold_mm is not None and not presolved:
        import open3d as o3d

        sub = pts[_subsample(n_all, CYLINDER_RANSAC_SUBSAMPLE, rng)]
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sub))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=min(20, len(sub) - 1)))
        normals = np.asarray(pcd.normals)
        r_lo, r_hi = _radius_bounds(radius_range_mm, sub)

        def model(idx: NDArray) -> Any:
            i, j = idx
            m = _cylinder_from_normals(sub[i], normals[i], sub[j], normals[j])
            return m if m is not None and r_lo <= m[2] <= r_hi else None

        def dist(m: Any) -> NDArray:
            q = sub - m[1]
            return np.abs(_rownorm(q - np.outer(q @ m[0], m[0])) - m[2])

        best = _ransac(len(sub), 2, model, dist, threshold_mm, rng, max_iterations)
        if best is None:
            return CylinderFit(reason="degenerate: RANSAC found no cylinder")
        q = pts - best[1]
        mask = np.abs(_rownorm(q - np.outer(q @ best[0], best[0])) - best[2]) < (threshold_mm)
        candidates.append((best[0], best[1]))
    inl = _take(pts, mask)
    if len(inl) < 6:
        return CylinderFit(reason=f"too few inliers: expected at least 6, got {len(inl)}")
    sub = inl[_subsample(len(inl), 2000, rng)]
    if axis_hint is not None:
        hint = np.asarray(axis_hint, dtype=np.float64).reshape(3)
        hint /= np.linalg.norm(hint)
        c = sub.mean(axis=0)
        u, v = _perp_basis(hint)
        x = sub - c
        cx, cy, _, _ = _circle_scores((x @ u)[:, None], (x @ v)[:, None])
        candidates.append((hint, c + cx[0] * u + cy[0] * v))
    if not candidates or threshold_mm is None:
        candidates += _cylinder_initial_axes(sub)
    # Refine each candidate on the small subsample; keep the best.
    best_x, best_cost, best_frame = None, math.inf, None
    for axis0, point0 in candidates:
        a0, u, v, c0 = _cyl_setup(axis0, point0)
        fun, jac, _ = _cyl_fun_factory(a0, u, v, c0)
        r0 = float(np.median(_rownorm((sub - c0) - np.outer((sub - c0) @ a0, a0))))
        try:
            sol = least_squares(fun, np.array([0, 0, 0, 0, r0]), jac=jac, args=(sub,), method="lm")
        except (ValueError, np.linalg.LinAlgError):
            continue
        if np.isfinite(sol.cost) and sol.cost < best_cost:
            best_x, best_cost, best_frame = sol.x, sol.cost, (a0, u, v, c0)
    if best_x is None:
        return CylinderFit(reason="no cylinder converged from any starting axis")
    a0, u, v, c0 = best_frame
    axis = (a0 + best_x[0] * u + best_x[1] * v) / np.linalg.norm(a0 + best_x[0] * u + best_x[1] * v)
    point = c0 + best_x[2] * u + best_x[3] * v
    radius = float(best_x[4])
    for rnd in range(MAX_ROUNDS if threshold_mm is not None else 1):
        inl = _take(pts, mask)
        # Re-centre the parameterisation on the current axis (tilts and shifts start at zero).
        centroid = inl.mean(axis=0)
        point = point + ((centroid - point) @ axis) * axis
        a0, u, v, c0 = _cyl_setup(axis, point)
        fun, jac, _ = _cyl_fun_factory(a0, u, v, c0)
        x = _lsq(fun, jac, np.array([0, 0, 0, 0, radius]), inl, rng)
        m = a0 + x[0] * u + x[1] * v
        axis = m / np.linalg.norm(m)
        point = c0 + x[2] * u + x[3] * v
        radius = float(abs(x[4]))
        if threshold_mm is None:
            break
        q = pts - point
        dist = _rownorm(q - np.outer(q @ axis, axis)) - radius
        new = np.abs(dist) < _band(threshold_mm, dist[mask])
        if np.array_equal(new, mask) or np.count_nonzero(new) < 6 or rnd == MAX_ROUNDS - 1:
            break  # (on the last round keep the mask the parameters belong to)
        mask = new
    inl = _take(pts, mask)
    extent = _extent(inl)
    if not (np.all(np.isfinite(axis)) and math.isfinite(radius) and radius < 1e3 * extent):
        return CylinderFit(reason=f"degenerate: radius {radius:.4g} mm for points spanning "
                           f"{extent:.4g} mm (planar points do not determine a cylinder)")  # fmt: skip
    centroid = inl.mean(axis=0)
    point = point + ((centroid - point) @ axis) * axis
    axis = _orient(axis)
    a0, u, v, c0 = _cyl_setup(axis, point)
    fun, jac, _ = _cyl_fun_factory(a0, u, v, c0)
    x0 = np.array([0, 0, 0, 0, radius])
    res = fun(x0, inl)
    rms, rng_ = _residual_stats(res)
    cov = _cov(jac(x0, inl), res) if len(inl) > 5 else np.full((5, 5), np.nan)
    b = np.column_stack([u, v])
    axis_std = np.sqrt(np.maximum(np.diag(b @ cov[:2, :2] @ b.T), 0))
    point_std = np.sqrt(np.maximum(np.diag(b @ cov[2:4, 2:4] @ b.T), 0))
    return CylinderFit(
        inliers=mask, residuals_mm=res, rms_mm=rms, range_mm=rng_, cov=cov, axis=axis,
        point_mm=point, radius_mm=radius, axis_std=axis_std, point_std_mm=point_std,
        radius_std_mm=float(np.sqrt(max(cov[4, 4], 0))),
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Circle in 3-D
# --------------------------------------------------------------------------------------------


def _circle_distance(p: NDArray, c: NDArray, n: NDArray, r: float) -> NDArray:
    q = p - c
    w = q @ n
    rho = _rownorm(q - np.outer(w, n)) - r
    return np.hypot(w, rho)


def _circle_from_3(a: NDArray, b: NDArray, c: NDArray) -> tuple[NDArray, NDArray, float] | None:
    ab, ac = b - a, c - a
    n = np.cross(ab, ac)
    nn2 = n @ n
    if nn2 <= 1e-18 * (ab @ ab) * (ac @ ac) or nn2 == 0:
        return None
    centre = a + (np.cross(n, ab) * (ac @ ac) + np.cross(ac, n) * (ab @ ab)) / (2 * nn2)
    return centre, n / math.sqrt(nn2), float(np.linalg.norm(a - centre))


def _circle_fun_factory(
    n0: NDArray, u: NDArray, v: NDArray
) -> tuple[Callable[..., NDArray], Callable[..., NDArray]]:
    def unpack(x: NDArray, p: NDArray) -> tuple[NDArray, float, NDArray, NDArray, NDArray]:
        m = n0 + x[0] * u + x[1] * v
        mn = float(np.linalg.norm(m))
        n = m / mn
        q = p - x[2:5]
        w = q @ n
        h = q - np.outer(w, n)
        return n, mn, q, w, h

    def fun(x: NDArray, p: NDArray) -> NDArray:
        _, _, _, w, h = unpack(x, p)
        return np.concatenate([w, _rownorm(h) - x[5]])

    def jac(x: NDArray, p: NDArray) -> NDArray:
        n, mn, q, w, h = unpack(x, p)
        k = len(p)
        dist = np.maximum(_rownorm(h), 1e-300)
        hh = h / dist[:, None]
        j = np.zeros((2 * k, 6))
        qn = w
        j[:k, 0] = (q @ u - qn * (n @ u)) / mn
        j[:k, 1] = (q @ v - qn * (n @ v)) / mn
        j[:k, 2:5] = -n
        j[k:, 0] = -w * (hh @ u) / mn
        j[k:, 1] = -w * (hh @ v) / mn
        j[k:, 2:5] = -hh
        j[k:, 5] = -1.0
        return j

    return fun, jac


def fit_circle(
    points: ArrayLike,
    threshold_mm: float | None = None,
    *,
    seed: SeedLike = 0,
    max_iterations: int = 1000,
    radius_range_mm: tuple[float, float] | None = None,
) -> CircleFit:
    """Fit a circle in 3-D by orthogonal least squares (3-D distance to the circle).

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points on or near the circle (an arc will do), mm. N >= 3, not collinear.
    threshold_mm : float, optional
        RANSAC inlier distance (3-D distance to the circle); without it every point is an
        inlier.
    radius_range_mm : (float, float), optional
        Radii a RANSAC hypothesis may have (e.g. nominal +-20 %); without it, at most the
        cloud's extent, so that a plane is not taken for a huge sphere.
    seed : int or Generator
        Seeds RANSAC and the least-squares subsample.

    Returns
    -------
    CircleFit
        Centre, normal, radius and their standard deviations, residual figures, or a failed
        fit (falsy) whose ``reason`` says why.
    """
    pts = check_points(points, min_count=0)
    _check_threshold(threshold_mm)
    n_all = len(pts)
    if n_all < 4:
        return CircleFit(reason=f"too few points: expected at least 4, got {n_all}")
    rng = _rng(seed)
    mask = np.ones(n_all, dtype=bool)
    presolved = False
    if threshold_mm is not None and n_all > RANSAC_SUBSAMPLE:
        pre = fit_circle(
            pts[_subsample(n_all, RANSAC_SUBSAMPLE, rng)], threshold_mm, seed=rng,
            max_iterations=max_iterations, radius_range_mm=radius_range_mm,
        )  # fmt: skip
        if not pre:
            return pre
        band = _band(threshold_mm, np.hypot(pre.residuals_mm, pre.out_of_plane_mm), signed=False)
        mask = pre.distance(pts) < band
        presolved = True
    if threshold_mm is not None and not presolved:
        sub = pts[_subsample(n_all, RANSAC_SUBSAMPLE, rng)]
        r_lo, r_hi = _radius_bounds(radius_range_mm, sub)

        def model(idx: NDArray) -> Any:
            m = _circle_from_3(*sub[idx])
            return m if m is not None and r_lo <= m[2] <= r_hi else None

        best = _ransac(
            len(sub), 3, model,
            lambda m: _circle_distance(sub, *m), threshold_mm, rng, max_iterations,
        )  # fmt: skip
        if best is None:
            return CircleFit(reason="degenerate: RANSAC found no circle (collinear points?)")
        mask = _circle_distance(pts, *best) < threshold_mm
    inl = _take(pts, mask)
    if len(inl) < 4:
        return CircleFit(reason=f"too few inliers: expected at least 4, got {len(inl)}")
    if _degenerate_rank(inl) < 2:
        return CircleFit(reason="degenerate: the points are collinear, a circle is not determined")
    # Initial guess: least-squares plane, then an algebraic circle in it.
    c, _, evec = _scatter_eig(inl)
    n0 = evec[:, 0]
    u, v = _perp_basis(n0)
    x = inl - c
    cx, cy, r0, _ = _circle_scores((x @ u)[:, None], (x @ v)[:, None])
    x_init = np.r_[0.0, 0.0, c + cx[0] * u + cy[0] * v, r0[0]]
    sol = None
    for rnd in range(MAX_ROUNDS if threshold_mm is not None else 1):
        fun, jac = _circle_fun_factory(n0, u, v)
        sol = _lsq(fun, jac, x_init, inl, rng)
        m = n0 + sol[0] * u + sol[1] * v
        n0 = m / np.linalg.norm(m)
        u, v = _perp_basis(n0)
        x_init = np.r_[0.0, 0.0, sol[2:5], abs(sol[5])]
        if threshold_mm is None:
            break
        dist = _circle_distance(pts, sol[2:5], n0, abs(sol[5]))
        new = dist < _band(threshold_mm, dist[mask], signed=False)
        if np.array_equal(new, mask) or np.count_nonzero(new) < 4 or rnd == MAX_ROUNDS - 1:
            break  # (on the last round keep the mask the parameters belong to)
        mask = new
        inl = _take(pts, mask)
    inl = _take(pts, mask)
    normal = _orient(n0)
    u, v = _perp_basis(normal)
    centre, radius = x_init[2:5], float(x_init[5])
    extent = _extent(inl)
    if not (np.all(np.isfinite(centre)) and radius < 1e3 * extent):
        return CircleFit(reason=f"degenerate: radius {radius:.4g} mm for points spanning "
                         f"{extent:.4g} mm (nearly collinear points)")  # fmt: skip
    fun, jac = _circle_fun_factory(normal, u, v)
    x0 = np.r_[0.0, 0.0, centre, radius]
    res2 = fun(x0, inl)
    k = len(inl)
    out_of_plane, radial = res2[:k], res2[k:]
    rms = float(np.sqrt(np.mean(out_of_plane**2 + radial**2)))
    cov = _cov(jac(x0, inl), res2) if 2 * k > 6 else np.full((6, 6), np.nan)
    b = np.column_stack([u, v])
    return CircleFit(
        inliers=mask, residuals_mm=radial, rms_mm=rms, range_mm=float(np.ptp(radial)), cov=cov,
        center_mm=centre.copy(), normal=normal, radius_mm=radius,
        center_std_mm=np.sqrt(np.maximum(np.diag(cov)[2:5], 0)),
        normal_std=np.sqrt(np.maximum(np.diag(b @ cov[:2, :2] @ b.T), 0)),
        radius_std_mm=float(np.sqrt(max(cov[5, 5], 0))), out_of_plane_mm=out_of_plane,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Line
# --------------------------------------------------------------------------------------------


def fit_line(
    points: ArrayLike,
    threshold_mm: float | None = None,
    *,
    seed: SeedLike = 0,
    max_iterations: int = 1000,
) -> LineFit:
    """Fit a 3-D line by orthogonal least squares (closed form), optionally after RANSAC.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points along the line, mm. N >= 3, not all coincident.
    threshold_mm : float, optional
        RANSAC inlier distance; without it every point is an inlier.

    Returns
    -------
    LineFit
        Centroid, unit direction and their standard deviations, the distances' RMS and range,
        or a failed fit (falsy) whose ``reason`` says why.
    """
    pts = check_points(points, min_count=0)
    _check_threshold(threshold_mm)
    n_all = len(pts)
    if n_all < 3:
        return LineFit(reason=f"too few points: expected at least 3, got {n_all}")
    rng = _rng(seed)
    mask = np.ones(n_all, dtype=bool)

    def line_dist(p: NDArray, c: NDArray, e: NDArray) -> NDArray:
        q = p - c
        return _rownorm(q - np.outer(q @ e, e))

    if threshold_mm is not None:
        sub = pts[_subsample(n_all, RANSAC_SUBSAMPLE, rng)]

        def model(idx: NDArray) -> Any:
            a, b = sub[idx]
            e = b - a
            en = np.linalg.norm(e)
            return None if en <= 1e-12 else (a, e / en)

        best = _ransac(
            len(sub), 2, model, lambda m: line_dist(sub, *m), threshold_mm, rng, max_iterations
        )
        if best is None:
            return LineFit(reason="degenerate: RANSAC found no line (coincident points?)")
        mask = line_dist(pts, *best) < threshold_mm
        for _ in range(MAX_ROUNDS):
            if np.count_nonzero(mask) < 3:
                break
            c, _, evec = _scatter_eig(_take(pts, mask))
            dist = line_dist(pts, c, evec[:, 2])
            new = dist < _band(threshold_mm, dist[mask], signed=False)
            if np.array_equal(new, mask):
                break
            mask = new
    inl = _take(pts, mask)
    if len(inl) < 3:
        return LineFit(reason=f"too few inliers: expected at least 3, got {len(inl)}")
    if _degenerate_rank(inl) == 0:
        return LineFit(reason="degenerate: the points coincide, a line is not determined")
    c, _, evec = _scatter_eig(inl)
    e = _orient(evec[:, 2])
    u, v = _perp_basis(e)
    x = inl - c
    t = x @ e
    ru, rv = x @ u, x @ v
    dist = np.hypot(ru, rv)
    rms, rng_ = _residual_stats(dist)
    k = len(inl)
    jac = np.zeros((2 * k, 4))
    jac[:k, 0], jac[:k, 1] = -1.0, -t
    jac[k:, 2], jac[k:, 3] = -1.0, -t
    cov = _cov(jac, np.r_[ru, rv]) if 2 * k > 4 else np.full((4, 4), np.nan)
    b = np.column_stack([u, v])
    dir_std = np.sqrt(np.maximum(np.diag(b @ cov[np.ix_([1, 3], [1, 3])] @ b.T), 0))
    pt_std = np.sqrt(np.maximum(np.diag(b @ cov[np.ix_([0, 2], [0, 2])] @ b.T), 0))
    return LineFit(
        inliers=mask, residuals_mm=dist, rms_mm=rms, range_mm=rng_, cov=cov, point_mm=c,
        direction=e, point_std_mm=pt_std, direction_std=dir_std,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Minimum-zone form
# --------------------------------------------------------------------------------------------


def _min_range_lp(a: NDArray, b: NDArray, bound: float) -> tuple[NDArray, float] | None:
    """``delta`` (|delta_i| <= bound) minimising ``max(b - a delta) - min(b - a delta)``."""
    m, k = a.shape
    # variables: delta (k), lo, h ;  lo <= b - a delta <= lo + h
    c = np.zeros(k + 2)
    c[-1] = 1.0
    ones = np.ones((m, 1))
    a_ub = np.vstack([np.hstack([-a, -ones, -ones]), np.hstack([a, ones, np.zeros((m, 1))])])
    b_ub = np.r_[-b, b]
    bounds = [(-bound, bound)] * k + [(None, None), (0, None)]
    sol = linprog(c, A_ub=a_ub, b_ub=b_ub, bounds=bounds, method="highs")
    if sol.status != 0:
        return None
    return sol.x[:k], float(sol.x[-1])


def _active_set_candidates(values: NDArray, k: int) -> NDArray:
    if len(values) <= 2 * k:
        return np.arange(len(values))
    part = np.argpartition(values, (k, len(values) - k))
    return np.unique(np.r_[part[:k], part[-k:]])


def min_zone_flatness(points: ArrayLike, normal: ArrayLike | None = None) -> float:
    """Minimum-zone flatness: the smallest distance between two parallel planes enclosing the
    points, mm (never more than the least-squares range).

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points on the surface, mm (inliers only).
    normal : array_like, shape (3,), optional
        Starting normal (the least-squares one if omitted).

    Notes
    -----
    Linear programming on the heights over the current plane (tilts ``a, b``), re-linearised
    about the new normal until the zone stops shrinking. Large clouds are solved on the
    points that bound the zone (an active set grown until every point lies inside).
    """
    pts = check_points(points, min_count=3)
    c = pts.mean(axis=0)
    x = pts - c
    if normal is None:
        _, _, evec = _scatter_eig(pts)
        n = evec[:, 0]
    else:
        n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    best = float(np.ptp(x @ n))
    for _ in range(6):
        u, v = _perp_basis(n)
        xu, xv, z = x @ u, x @ v, x @ n
        active = _active_set_candidates(z, 200)
        sol = None
        for _ in range(20):
            res = _min_range_lp(np.column_stack([xu, xv])[active], z[active], 0.2)
            if res is None:
                break
            (ta, tb), _h = res
            zz = z - ta * xu - tb * xv
            lo, hi = zz[active].min(), zz[active].max()
            outside = np.flatnonzero((zz < lo - 1e-12) | (zz > hi + 1e-12))
            sol = (ta, tb)
            if outside.size == 0:
                break
            extra = _active_set_candidates(zz, 50)
            active = np.union1d(active, np.r_[outside[:2000], extra])
        if sol is None:
            break
        n_new = n - sol[0] * u - sol[1] * v
        n_new /= np.linalg.norm(n_new)
        zone = float(np.ptp(x @ n_new))
        if zone >= best * (1 - 1e-12):
            break
        best, n = zone, n_new
    return best


def min_zone_sphericity(points: ArrayLike, center: ArrayLike | None = None) -> float:
    """Minimum-zone sphericity: the smallest radial difference of two concentric spheres
    enclosing the points, mm (never more than the least-squares range).

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points on the sphere, mm (inliers only).
    center : array_like, shape (3,), optional
        Starting centre (the algebraic fit's if omitted).

    Notes
    -----
    Sequential linear programming on the centre: the radii are linearised about the current
    centre, the LP shrinks the zone within a trust region, and the step is accepted only if
    the exact zone shrinks.
    """
    pts = check_points(points, min_count=4)
    if center is None:
        init = _sphere_algebraic(pts)
        if init is None:
            raise ValueError("points: expected points on a sphere, got a degenerate set")
        c = init[0]
    else:
        c = np.asarray(center, dtype=np.float64).reshape(3)
    rho = _rownorm(pts - c)
    best = float(np.ptp(rho))
    step = max(best, 1e-9)
    for _ in range(30):
        q = pts - c
        rho = _rownorm(q)
        unit = q / rho[:, None]
        active = _active_set_candidates(rho, 200)
        res = _min_range_lp(unit[active], rho[active], step)
        if res is None:
            break
        delta = res[0]
        c_new = c + delta
        zone = float(np.ptp(_rownorm(pts - c_new)))
        if zone < best * (1 - 1e-12):
            best, c = zone, c_new
            if np.linalg.norm(delta) < 1e-10:
                break
        else:
            step *= 0.3
            if step < 1e-9:
                break
    return best
