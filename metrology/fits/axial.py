"""Models of the cylinder and the 3-D circle for :func:`metrology.fits.robust.robust_fit`.

Both have a direction (the cylinder's axis, the circle's normal) that the least squares tilts
about two perpendicular unit vectors ``u, v``, starting from zero tilt: the parameters stay
well conditioned and the covariance is over those tilts. Both are fitted by
:func:`scipy.optimize.least_squares` with analytic Jacobians.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from metrology.fits.geometry import (
    circle_distance,
    circle_from_3,
    circle_scores,
    covariance,
    cylinder_from_normals,
    degenerate_rank,
    fibonacci_hemisphere,
    frame_std,
    orient,
    perp_basis,
    rownorm,
    scatter_eig,
    subsample,
    take,
)
from metrology.fits.lsq import Residuals, solve_lsq
from metrology.fits.results import CircleFit, CylinderFit
from metrology.fits.robust import CYLINDER_RANSAC_SUBSAMPLE, Params, RadialModel

__all__ = ["CircleModel", "CylinderModel"]

#: The cylinder's starting axes are ranked on at most this many inliers.
CYLINDER_START_SUBSAMPLE = 2000


# --------------------------------------------------------------------------------------------
# Cylinder
# --------------------------------------------------------------------------------------------


def _cylinder_residuals(
    a0: NDArray, u: NDArray, v: NDArray, c0: NDArray
) -> tuple[Residuals, Residuals]:
    """Residuals (distance to the axis minus radius) and Jacobian for parameters
    ``x = (tilt_u, tilt_v, shift_u, shift_v, r)``: axis ``a ~ a0 + tilt_u u + tilt_v v`` through
    ``c0 + shift_u u + shift_v v``, with ``a0, u, v`` (3,) orthonormal. For ``(N, 3)`` points
    they are of shape (N,) and (N, 5)."""
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

    return fun, jac


class _CylinderFrame:
    """Local parameters ``x = (tilt_u, tilt_v, shift_u, shift_v, r)`` (5,) about an axis
    through ``point`` (3,) along ``axis`` (3,): zero tilts and shifts are that axis."""

    def __init__(self, axis: NDArray, point: NDArray) -> None:
        self.a0 = axis / np.linalg.norm(axis)
        self.u, self.v = perp_basis(self.a0)
        self.c0 = point
        self.fun, self.jac = _cylinder_residuals(self.a0, self.u, self.v, point)

    def params(self, x: NDArray) -> Params:
        """``(axis (3,), axis point (3,), radius)`` of local parameters ``x``."""
        m = self.a0 + x[0] * self.u + x[1] * self.v
        return m / np.linalg.norm(m), self.c0 + x[2] * self.u + x[3] * self.v, float(x[4])

    def std(self, cov: NDArray) -> tuple[NDArray, NDArray, float]:
        """Standard deviations of the axis (3,), the axis point (3,) and the radius from the
        covariance (5, 5) of ``x``."""
        b = np.column_stack([self.u, self.v])
        return (
            frame_std(b, cov[:2, :2]), frame_std(b, cov[2:4, 2:4]),
            float(np.sqrt(max(cov[4, 4], 0))),
        )  # fmt: skip


def _recentred(point: NDArray, axis: NDArray, points: NDArray) -> NDArray:
    """The point of the axis (through ``point`` along unit ``axis``) nearest the centroid of
    ``points`` (N, 3)."""
    return point + ((points.mean(axis=0) - point) @ axis) * axis


def _direction_search(p: NDArray, n_directions: int = 400) -> list[tuple[NDArray, NDArray]]:
    """Candidate (axis, axis point) for ``(N, 3)`` points from a direction search: the
    projection of the points along the true axis is a circle, so rank directions by the RMS of
    a circle fit of the projection; the best three."""
    c, _, evec = scatter_eig(p)
    x = p - c
    dirs = np.vstack([fibonacci_hemisphere(n_directions), evec.T])
    us, vs = zip(*(perp_basis(d) for d in dirs))
    u, v = np.array(us), np.array(vs)
    cx, cy, r, rms = circle_scores(x @ u.T, x @ v.T)
    spread = rownorm(x).max()
    rms = np.where(np.isfinite(rms) & (r < 1e3 * spread), rms, np.inf)
    order = np.argsort(rms)[:3]
    return [(dirs[k], c + cx[k] * u[k] + cy[k] * v[k]) for k in order]


class CylinderModel(RadialModel[CylinderFit]):
    """Cylinder; parameters ``(axis (3,), axis point (3,), radius)``.

    Hypotheses come from two points and their Open3D normals. The rounds start from the best
    of several candidate axes (RANSAC's, ``axis_hint``'s, or without RANSAC a direction
    search), each refined on a small subsample.

    Parameters
    ----------
    radius_range_mm : (float, float), optional
        Radii a RANSAC hypothesis may have; without it, at most the cloud's extent.
    axis_hint : array_like, shape (3,), optional
        Approximate axis direction, tried besides the other candidates.
    """

    result_type = CylinderFit
    min_points = 6
    sample_size = 2
    ransac_subsample = CYLINDER_RANSAC_SUBSAMPLE
    min_round_inliers = 6
    no_hypothesis = "degenerate: RANSAC found no cylinder"

    def __init__(
        self,
        radius_range_mm: tuple[float, float] | None = None,
        axis_hint: ArrayLike | None = None,
    ) -> None:
        super().__init__(radius_range_mm)
        self.axis_hint = axis_hint

    def check_cloud(self, points: NDArray) -> str:
        if degenerate_rank(points) < 2:
            return "degenerate: the points are collinear, a cylinder is not determined"
        return ""

    def sample_data(self, points: NDArray) -> NDArray:
        """The points and their Open3D normals side by side, (N, 6)."""
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=min(20, len(points) - 1)))
        return np.hstack([points, np.asarray(pcd.normals)])

    def from_sample(self, sample: NDArray) -> Params | None:
        """The cylinder through two points whose normals (columns 3:6) meet its axis."""
        return cylinder_from_normals(sample[0, :3], sample[0, 3:], sample[1, :3], sample[1, 3:])

    def residuals(self, params: Params, points: NDArray) -> NDArray:
        """Radial deviations (N,) of ``(N, 3)`` points from the surface, positive outside."""
        axis, point, radius = params
        q = points - point
        return rownorm(q - np.outer(q @ axis, axis)) - radius

    def from_fit(self, fit: CylinderFit) -> tuple[Params, NDArray]:
        return (fit.axis, fit.point_mm, fit.radius_mm), fit.residuals_mm

    def initial(self, points: NDArray, hint: Params | None, rng: np.random.Generator) -> Any:
        """The best candidate axis, refined on a subsample of the ``(M, 3)`` inliers."""
        sub = points[subsample(len(points), CYLINDER_START_SUBSAMPLE, rng)]
        best, best_cost = None, math.inf
        for axis0, point0 in self._candidates(sub, hint):
            frame = _CylinderFrame(axis0, point0)
            r0 = float(np.median(self.residuals((frame.a0, point0, 0.0), sub)))
            x0 = np.array([0, 0, 0, 0, r0])
            try:
                sol = least_squares(frame.fun, x0, jac=frame.jac, args=(sub,), method="lm")
            except (ValueError, np.linalg.LinAlgError):
                continue
            if np.isfinite(sol.cost) and sol.cost < best_cost:
                best, best_cost = frame.params(sol.x), sol.cost
        return "no cylinder converged from any starting axis" if best is None else best

    def _candidates(self, sub: NDArray, hint: Params | None) -> list[tuple[NDArray, NDArray]]:
        """Starting (axis, axis point) pairs for the ``(M, 3)`` points ``sub``: RANSAC's,
        ``axis_hint`` through the centre of a circle fit, and without RANSAC a direction
        search."""
        candidates = [] if hint is None else [(hint[0], hint[1])]
        if self.axis_hint is not None:
            axis = np.asarray(self.axis_hint, dtype=np.float64).reshape(3)
            axis = axis / np.linalg.norm(axis)
            c = sub.mean(axis=0)
            u, v = perp_basis(axis)
            x = sub - c
            cx, cy, _, _ = circle_scores((x @ u)[:, None], (x @ v)[:, None])
            candidates.append((axis, c + cx[0] * u + cy[0] * v))
        if hint is None:
            candidates += _direction_search(sub)
        return candidates

    def refine(self, points: NDArray, params: Params, rng: np.random.Generator) -> Params:
        """Radial least squares on ``(M, 3)`` points, re-centred on the current axis (tilts and
        shifts start at zero)."""
        axis, point, radius = params
        frame = _CylinderFrame(axis, _recentred(point, axis, points))
        x = solve_lsq(frame.fun, frame.jac, np.array([0, 0, 0, 0, radius]), points, rng)
        axis, point, radius = frame.params(x)
        return axis, point, abs(radius)

    def result(self, params: Params, points: NDArray, mask: NDArray) -> CylinderFit:
        axis, point, radius = params
        inl = take(points, mask)
        finite = bool(np.all(np.isfinite(axis))) and math.isfinite(radius)
        reason = self.radius_failure(
            finite, radius, inl, 1e3, "planar points do not determine a cylinder"
        )
        if reason:
            return self.failure(reason)
        point = _recentred(point, axis, inl)
        axis = orient(axis)
        frame = _CylinderFrame(axis, point)
        x0 = np.array([0, 0, 0, 0, radius])
        res = frame.fun(x0, inl)
        cov = covariance(frame.jac(x0, inl), res)
        axis_std, point_std, radius_std = frame.std(cov)
        return self.make(
            mask, res, cov, axis=axis, point_mm=point, radius_mm=radius, axis_std=axis_std,
            point_std_mm=point_std, radius_std_mm=radius_std,
        )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Circle in 3-D
# --------------------------------------------------------------------------------------------


def _circle_residuals(n0: NDArray, u: NDArray, v: NDArray) -> tuple[Residuals, Residuals]:
    """Residuals and Jacobian for parameters ``x = (tilt_u, tilt_v, cx, cy, cz, r)``: normal
    ``n ~ n0 + tilt_u u + tilt_v v``. For ``(N, 3)`` points the residuals (2N,) are the
    distances from the circle's plane, then the in-plane radial deviations; the Jacobian is
    (2N, 6)."""

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
        return np.concatenate([w, rownorm(h) - x[5]])

    def jac(x: NDArray, p: NDArray) -> NDArray:
        n, mn, q, w, h = unpack(x, p)
        k = len(p)
        dist = np.maximum(rownorm(h), 1e-300)
        hh = h / dist[:, None]
        j = np.zeros((2 * k, 6))
        j[:k, 0] = (q @ u - w * (n @ u)) / mn
        j[:k, 1] = (q @ v - w * (n @ v)) / mn
        j[:k, 2:5] = -n
        j[k:, 0] = -w * (hh @ u) / mn
        j[k:, 1] = -w * (hh @ v) / mn
        j[k:, 2:5] = -hh
        j[k:, 5] = -1.0
        return j

    return fun, jac


class CircleModel(RadialModel[CircleFit]):
    """Circle in 3-D; parameters ``(center (3,), unit normal (3,), radius)``.

    Residuals are the 3-D distances to the circle (unsigned). The rounds start from the
    least-squares plane and an algebraic circle in it. See :class:`RadialModel` for the
    ``radius_range_mm`` argument.
    """

    result_type = CircleFit
    min_points = 4
    sample_size = 3
    signed = False
    min_round_inliers = 4
    no_hypothesis = "degenerate: RANSAC found no circle (collinear points?)"

    def from_sample(self, sample: NDArray) -> Params | None:
        """The circle through three points (3, 3), or None for (nearly) collinear ones."""
        return circle_from_3(*sample)

    def residuals(self, params: Params, points: NDArray) -> NDArray:
        """3-D distances (N,) of ``(N, 3)`` points from the circle."""
        return circle_distance(points, *params)

    def from_fit(self, fit: CircleFit) -> tuple[Params, NDArray]:
        return (fit.center_mm, fit.normal, fit.radius_mm), np.hypot(
            fit.residuals_mm, fit.out_of_plane_mm
        )

    def initial(self, points: NDArray, hint: Params | None, rng: np.random.Generator) -> Any:
        """Least-squares plane of the ``(M, 3)`` inliers, then an algebraic circle in it."""
        if degenerate_rank(points) < 2:
            return "degenerate: the points are collinear, a circle is not determined"
        c, _, evec = scatter_eig(points)
        n0 = evec[:, 0]
        u, v = perp_basis(n0)
        x = points - c
        cx, cy, r0, _ = circle_scores((x @ u)[:, None], (x @ v)[:, None])
        return c + cx[0] * u + cy[0] * v, n0, r0[0]

    def refine(self, points: NDArray, params: Params, rng: np.random.Generator) -> Params:
        """Least squares of the 3-D distances of ``(M, 3)`` points from ``params``."""
        centre, n0, radius = params
        u, v = perp_basis(n0)
        fun, jac = _circle_residuals(n0, u, v)
        sol = solve_lsq(fun, jac, np.r_[0.0, 0.0, centre, radius], points, rng)
        m = n0 + sol[0] * u + sol[1] * v
        return sol[2:5], m / np.linalg.norm(m), abs(sol[5])

    def result(self, params: Params, points: NDArray, mask: NDArray) -> CircleFit:
        centre, normal, radius = params[0], orient(params[1]), float(params[2])
        inl = take(points, mask)
        finite = bool(np.all(np.isfinite(centre)))
        reason = self.radius_failure(finite, radius, inl, 1e3, "nearly collinear points")
        if reason:
            return self.failure(reason)
        u, v = perp_basis(normal)
        fun, jac = _circle_residuals(normal, u, v)
        x0 = np.r_[0.0, 0.0, centre, radius]
        res2 = fun(x0, inl)
        k = len(inl)
        out_of_plane, radial = res2[:k], res2[k:]
        cov = covariance(jac(x0, inl), res2)
        b = np.column_stack([u, v])
        return CircleFit(
            inliers=mask, residuals_mm=radial, cov=cov, center_mm=centre.copy(), normal=normal,
            rms_mm=float(np.sqrt(np.mean(out_of_plane**2 + radial**2))),
            range_mm=float(np.ptp(radial)), radius_mm=radius,
            center_std_mm=np.sqrt(np.maximum(np.diag(cov)[2:5], 0)),
            normal_std=frame_std(b, cov[:2, :2]),
            radius_std_mm=float(np.sqrt(max(cov[5, 5], 0))), out_of_plane_mm=out_of_plane,
        )  # fmt: skip
