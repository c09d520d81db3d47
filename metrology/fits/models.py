"""Models of the plane, line and sphere for :func:`metrology.fits.robust.robust_fit`.

The plane and the line are closed form: their orthogonal least-squares fit is given by the
eigenvectors of the scatter matrix, so no iteration is needed. The sphere is fitted by
:func:`scipy.optimize.least_squares` on the radial distances, started from an algebraic (Kasa)
fit. The cylinder and the circle are in :mod:`metrology.fits.axial`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from metrology.fits.geometry import (
    DEGENERACY_RATIO,
    covariance,
    degenerate_rank,
    frame_std,
    orient,
    perp_basis,
    rownorm,
    scatter_eig,
    sphere_algebraic,
    subsample,
    take,
)
from metrology.fits.lsq import LSQ_SUBSAMPLE, solve_lsq
from metrology.fits.results import LineFit, PlaneFit, SphereFit
from metrology.fits.robust import MAX_ROUNDS, Model, Params, RadialModel

__all__ = ["LineModel", "PlaneModel", "SphereModel"]


class PlaneModel(Model[PlaneFit]):
    """Plane ``normal . p + d = 0``.

    Parameters: ``(normal (3,), d)`` from a sample, ``(normal (3,), d, centroid (3,))`` after a
    least-squares fit. The closed-form fit of the last inlier set is the result, so the rounds
    run one fit more than the iterative models (:data:`MAX_ROUNDS` inlier updates).
    """

    result_type = PlaneFit
    min_points = 3
    sample_size = 3
    max_rounds = MAX_ROUNDS + 1
    no_hypothesis = "degenerate: RANSAC found no plane (collinear points?)"

    def from_sample(self, sample: NDArray) -> Params | None:
        """The plane through three points (3, 3), or None for (nearly) collinear ones."""
        a, b, c = sample
        n = np.cross(b - a, c - a)
        nn = np.linalg.norm(n)
        if nn <= 1e-12 * max(1.0, np.linalg.norm(b - a) * np.linalg.norm(c - a)):
            return None
        n = n / nn
        return n, -float(n @ a)

    def residuals(self, params: Params, points: NDArray) -> NDArray:
        """Signed distances (N,) of ``(N, 3)`` points, positive on the normal's side."""
        return points @ params[0] + params[1]

    def refine(self, points: NDArray, params: Any, rng: np.random.Generator) -> Params | str:
        """Orthogonal least-squares plane of ``(M, 3)`` points (closed form)."""
        c, w, v = scatter_eig(points)
        s = np.sqrt(w)
        if s[1] <= DEGENERACY_RATIO * s[2]:
            return "degenerate: the points are collinear, a plane is not determined"
        n = orient(v[:, 0])
        return n, float(-n @ c), c

    def result(self, params: Params, points: NDArray, mask: NDArray) -> PlaneFit:
        n, d, c = params
        inl = take(points, mask)
        res = self.residuals(params, inl)
        # Covariance: tilt (a, b) about the in-plane axes and offset t at the centroid.
        u, v = perp_basis(n)
        x = inl - c
        cov = covariance(np.column_stack([x @ u, x @ v, -np.ones(len(inl))]), res)
        g = np.array([-(u @ c), -(v @ c), -1.0])  # dd/d(a, b, t)
        return self.make(
            mask, res, cov, normal=n, d_mm=d, centroid_mm=c,
            normal_std=frame_std(np.column_stack([u, v]), cov[:2, :2]),  # dn = a u + b v
            d_std_mm=float(np.sqrt(max(g @ cov @ g, 0.0))),
        )  # fmt: skip


class LineModel(Model[LineFit]):
    """3-D line through ``point`` along ``direction``.

    Parameters: ``(point (3,), direction (3,))``; after a least-squares fit the point is the
    inliers' centroid and the direction the scatter matrix's principal axis. Closed form, like
    :class:`PlaneModel`.
    """

    result_type = LineFit
    min_points = 3
    sample_size = 2
    signed = False
    max_rounds = MAX_ROUNDS + 1
    no_hypothesis = "degenerate: RANSAC found no line (coincident points?)"

    def from_sample(self, sample: NDArray) -> Params | None:
        """The line through two points (2, 3), or None if they coincide."""
        a, b = sample
        e = b - a
        en = np.linalg.norm(e)
        return None if en <= 1e-12 else (a, e / en)

    def residuals(self, params: Params, points: NDArray) -> NDArray:
        """Distances (N,) of ``(N, 3)`` points from the line."""
        q = points - params[0]
        e = params[1]
        return rownorm(q - np.outer(q @ e, e))

    def refine(self, points: NDArray, params: Any, rng: np.random.Generator) -> Params:
        """Orthogonal least-squares line of ``(M, 3)`` points (closed form)."""
        c, _, evec = scatter_eig(points)
        return c, evec[:, 2]

    def result(self, params: Params, points: NDArray, mask: NDArray) -> LineFit:
        inl = take(points, mask)
        if degenerate_rank(inl) == 0:
            return self.failure("degenerate: the points coincide, a line is not determined")
        c, e = params[0], orient(params[1])
        u, v = perp_basis(e)
        x = inl - c
        t = x @ e
        ru, rv = x @ u, x @ v
        k = len(inl)
        jac = np.zeros((2 * k, 4))
        jac[:k, 0], jac[:k, 1] = -1.0, -t
        jac[k:, 2], jac[k:, 3] = -1.0, -t
        cov = covariance(jac, np.r_[ru, rv])
        b = np.column_stack([u, v])
        return self.make(
            mask, np.hypot(ru, rv), cov, point_mm=c, direction=e,
            point_std_mm=frame_std(b, cov[np.ix_([0, 2], [0, 2])]),
            direction_std=frame_std(b, cov[np.ix_([1, 3], [1, 3])]),
        )  # fmt: skip


class _SphereResiduals:
    """Residuals ``|p - c| - r`` for parameters ``x = (cx, cy, cz, r)`` and their Jacobian,
    sharing the work between the two calls."""

    def __init__(self) -> None:
        self._key: tuple[bytes, int] | None = None

    def _eval(self, x: NDArray, p: NDArray) -> tuple[NDArray, NDArray]:
        key = (x.tobytes(), id(p))
        if key != self._key:
            q = p - x[:3]
            self._q, self._dist = q, rownorm(q)
            self._key = key
        return self._q, self._dist

    def fun(self, x: NDArray, p: NDArray) -> NDArray:
        """Residuals (N,) of ``(N, 3)`` points."""
        return self._eval(x, p)[1] - x[3]

    def jac(self, x: NDArray, p: NDArray) -> NDArray:
        """Jacobian (N, 4) of the residuals."""
        q, dist = self._eval(x, p)
        jac = np.empty((len(p), 4))
        np.divide(q, -np.maximum(dist, 1e-300)[:, None], out=jac[:, :3])
        jac[:, 3] = -1.0
        return jac


class SphereModel(RadialModel[SphereFit]):
    """Sphere; parameters ``(center (3,), radius)``. See :class:`RadialModel` for the
    ``radius_range_mm`` argument."""

    result_type = SphereFit
    min_points = 4
    sample_size = 4
    min_round_inliers = 5
    no_hypothesis = "degenerate: RANSAC found no sphere (coplanar points?)"

    def from_sample(self, sample: NDArray) -> Params | None:
        """The sphere through four points (4, 3), or None for (nearly) coplanar ones."""
        s = sample
        # |p_i - c|^2 = |p_0 - c|^2  ->  2 (p_i - p_0) . c = |p_i|^2 - |p_0|^2
        a = 2 * (s[1:] - s[0])
        b = np.einsum("ij,ij->i", s[1:], s[1:]) - s[0] @ s[0]
        if abs(np.linalg.det(a)) < 1e-9 * np.abs(a).max() ** 3:
            return None
        c = np.linalg.solve(a, b)
        return c, float(np.linalg.norm(s[0] - c))

    def residuals(self, params: Params, points: NDArray) -> NDArray:
        """Radial deviations ``|p - c| - r`` (N,) of ``(N, 3)`` points."""
        return rownorm(points - params[0]) - params[1]

    def from_fit(self, fit: SphereFit) -> tuple[Params, NDArray]:
        return (fit.center_mm, fit.radius_mm), fit.residuals_mm

    def initial(self, points: NDArray, hint: Params | None, rng: np.random.Generator) -> Any:
        """Algebraic fit of (a subsample of) the ``(M, 3)`` inliers, after a rank check."""
        rank = degenerate_rank(points)
        if rank < 3:
            what = {0: "coincident", 1: "collinear", 2: "coplanar"}[rank]
            return f"degenerate: the points are {what}, a sphere is not determined"
        init = sphere_algebraic(points[subsample(len(points), LSQ_SUBSAMPLE, rng)])
        return "degenerate: no sphere through the points (algebraic fit)" if init is None else init

    def refine(self, points: NDArray, params: Params, rng: np.random.Generator) -> Params:
        """Radial least squares on ``(M, 3)`` points from ``params``."""
        res = _SphereResiduals()
        x = solve_lsq(res.fun, res.jac, np.r_[params[0], params[1]], points, rng)
        return x[:3], x[3]

    def result(self, params: Params, points: NDArray, mask: NDArray) -> SphereFit:
        inl = take(points, mask)
        c, r = params[0], float(abs(params[1]))
        finite = bool(np.all(np.isfinite(c))) and math.isfinite(r)
        reason = self.radius_failure(
            finite, r, inl, 1e4, "nearly planar points do not determine a sphere"
        )
        if reason:
            return self.failure(reason)
        res = self.residuals((c, r), inl)
        cov = covariance(_SphereResiduals().jac(np.r_[c, r], inl), res)
        std = np.sqrt(np.maximum(np.diag(cov), 0))
        return self.make(
            mask, res, cov, center_mm=c.copy(), radius_mm=r, center_std_mm=std[:3],
            radius_std_mm=float(std[3]),
        )  # fmt: skip
