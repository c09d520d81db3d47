"""The default intrinsics' adjustment: geometric image distances of rings, lines and points.

One robust nonlinear least-squares adjustment of fx, fy, cx, cy, k1, k2, p1, p2, k3
(:data:`PARAM_NAMES`) and every view's pose. A ring edge point's residual is its distance to
the projected circle of its radius, a diameter-line point's to the projected line (each
point's curve parameter kept at its foot point); a chessboard's or circle grid's point
gives its reprojection error. Levenberg-Marquardt on normal equations assembled view by view,
with a soft-L1 loss.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from calibration.detection.observations import TargetObservation
from scanner.core.jit import njit

__all__ = ["PARAM_NAMES", "adjustment_covariances", "camera_matrix", "intrinsics_covariance"]

#: The nine intrinsics, in the order of the adjustment's parameter vector (then 6 per view).
PARAM_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def camera_matrix(x: NDArray) -> NDArray:
    """The camera matrix ``(3, 3)`` of a parameter vector (fx, fy, cx, cy first)."""
    return np.array([[x[0], 0, x[2]], [0, x[1], x[3]], [0, 0, 1.0]])


# Curve kinds of the adjustment's observations.
_CIRCLE, _XLINE, _YLINE, _POINT = 0, 1, 2, 3


@dataclass
class _Data:
    view: NDArray  # (P,) int
    kind: NDArray  # (P,) int
    radius: NDArray  # (P,) mm (circle) or 0
    obs: NDArray  # (P, 2) px
    fixed: NDArray  # (P, 3) target points for _POINT
    psi: NDArray  # (P,) curve parameter (angle rad or position mm)


def _project(
    params9: NDArray, R: NDArray, t: NDArray, pts: NDArray, parts: bool = False
) -> NDArray | tuple[NDArray, NDArray]:
    """Distorted pixels ``(P, 2)`` of planar target points ``pts`` (P, 3), z = 0.

    ``R`` (P, 3, 3) and ``t`` (P, 3) are each point's view pose. With ``parts``, also the
    derivatives ``(P, 2, 9)`` of the pixels with respect to the nine intrinsics.
    """
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = params9
    pc = R[:, :, 0] * pts[:, 0:1] + R[:, :, 1] * pts[:, 1:2] + t
    x = pc[:, 0] / pc[:, 2]
    y = pc[:, 1] / pc[:, 2]
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    uv = np.column_stack([fx * xd + cx, fy * yd + cy])
    if not parts:
        return uv
    n = len(x)
    D = np.zeros((n, 2, 9))
    D[:, 0, 0] = xd
    D[:, 1, 1] = yd
    D[:, 0, 2] = 1.0
    D[:, 1, 3] = 1.0
    r4 = r2 * r2
    for col, rr in ((4, r2), (5, r4), (8, r4 * r2)):
        D[:, 0, col] = fx * x * rr
        D[:, 1, col] = fy * y * rr
    D[:, 0, 6] = fx * 2 * x * y
    D[:, 1, 6] = fy * (r2 + 2 * y * y)
    D[:, 0, 7] = fx * (r2 + 2 * x * x)
    D[:, 1, 7] = fy * 2 * x * y
    return uv, D


@njit(cache=True, nogil=True)
def _distorted(params9, R, t, v, X, Y):  # pragma: no cover - compiled
    """The target point ``(X, Y, 0)`` in view ``v``: its normalised image ``x, y``, their
    ``r2`` and the distorted ``xd, yd``, with :func:`_project`'s arithmetic."""
    k1, k2, p1, p2, k3 = params9[4], params9[5], params9[6], params9[7], params9[8]
    pc0 = R[v, 0, 0] * X + R[v, 0, 1] * Y + t[v, 0]
    pc1 = R[v, 1, 0] * X + R[v, 1, 1] * Y + t[v, 1]
    pc2 = R[v, 2, 0] * X + R[v, 2, 1] * Y + t[v, 2]
    x = pc0 / pc2
    y = pc1 / pc2
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return x, y, r2, xd, yd


@njit(cache=True, nogil=True)
def _pixel(params9, R, t, v, X, Y):  # pragma: no cover - compiled
    """:func:`_project` of the target point ``(X, Y, 0)`` in view ``v``, the same arithmetic."""
    _, _, _, xd, yd = _distorted(params9, R, t, v, X, Y)
    return params9[0] * xd + params9[2], params9[1] * yd + params9[3]


@njit(cache=True, nogil=True)
def _curve_point(kind, radius, psi, fixed, p):  # pragma: no cover - compiled
    """Observation ``p``'s target point (x, y) mm: on its ring at angle ``psi``, on the x or
    y diameter at ``psi`` mm, or its fixed point."""
    k = kind[p]
    if k == _CIRCLE:
        return radius[p] * np.cos(psi[p]), radius[p] * np.sin(psi[p])
    if k == _XLINE:
        return psi[p], 0.0
    if k == _YLINE:
        return 0.0, psi[p]
    return fixed[p, 0], fixed[p, 1]


@njit(cache=True, nogil=True)
def _curve_pixels(params9, R, t, view, kind, radius, psi, fixed, out):  # pragma: no cover
    """Each observation's target point at ``psi`` projected into its view: ``out`` (P, 2)."""
    for p in range(view.shape[0]):
        X, Y = _curve_point(kind, radius, psi, fixed, p)
        out[p, 0], out[p, 1] = _pixel(params9, R, t, view[p], X, Y)


@njit(cache=True, nogil=True)
def _curve_residuals(
    params9, R, t, view, kind, radius, psi, fixed, obs, nrm, slot, out
):  # pragma: no cover - compiled
    """The residuals at ``psi``: a curve point's distance along ``nrm`` into ``out[slot]``, a
    fixed point's two pixel errors into ``out[slot]`` and ``out[slot + 1]``."""
    for p in range(view.shape[0]):
        X, Y = _curve_point(kind, radius, psi, fixed, p)
        u, v = _pixel(params9, R, t, view[p], X, Y)
        du = obs[p, 0] - u
        dv = obs[p, 1] - v
        if kind[p] == _POINT:
            out[slot[p]] = du
            out[slot[p] + 1] = dv
        else:
            out[slot[p]] = du * nrm[p, 0] + dv * nrm[p, 1]


@njit(cache=True, nogil=True)
def _intrinsics_jacobian(
    params9, R, t, view, kind, radius, psi, fixed, nrm, slot, out
):  # pragma: no cover - compiled
    """Each residual's derivative by the nine intrinsics into ``out`` (n_res, 9):
    :func:`_project`'s ``parts``, times minus the normal for a curve point, minus itself for
    each of a fixed point's two pixel errors."""
    fx, fy = params9[0], params9[1]
    d = np.empty((2, 9))
    for p in range(view.shape[0]):
        X, Y = _curve_point(kind, radius, psi, fixed, p)
        x, y, r2, xd, yd = _distorted(params9, R, t, view[p], X, Y)
        d[:, :] = 0.0
        d[0, 0] = xd
        d[1, 1] = yd
        d[0, 2] = 1.0
        d[1, 3] = 1.0
        r4 = r2 * r2
        d[0, 4] = fx * x * r2
        d[1, 4] = fy * y * r2
        d[0, 5] = fx * x * r4
        d[1, 5] = fy * y * r4
        d[0, 8] = fx * x * (r4 * r2)
        d[1, 8] = fy * y * (r4 * r2)
        d[0, 6] = fx * 2 * x * y
        d[1, 6] = fy * (r2 + 2 * y * y)
        d[0, 7] = fx * (r2 + 2 * x * x)
        d[1, 7] = fy * 2 * x * y
        row = slot[p]
        if kind[p] == _POINT:
            for j in range(9):
                out[row, j] = -d[0, j]
                out[row + 1, j] = -d[1, j]
        else:
            for j in range(9):
                out[row, j] = -(d[0, j] * nrm[p, 0] + d[1, j] * nrm[p, 1])


class _Problem:
    """Residuals of every observation for the parameter vector (9 intrinsics + 6 per view).

    The projections run in compiled kernels (:func:`_curve_pixels`, :func:`_curve_residuals`)
    with :func:`_project`'s arithmetic, point by point, without the ``(P, 3, 3)`` copies of
    each point's pose that the array form needs (most of a 20-view calibration's time).
    """

    def __init__(self, data: _Data, n_views: int) -> None:
        self.d = data
        self.n_views = n_views
        self.curve = data.kind != _POINT
        self.is_point = ~self.curve
        # Residual layout: one per curve point, two per fixed point.
        nc = int(self.curve.sum())
        self.n_res = nc + 2 * int(self.is_point.sum())
        self.slot = np.empty(len(data.kind), dtype=np.int64)
        self.slot[self.curve] = np.arange(nc)
        self.slot[self.is_point] = nc + 2 * np.arange(int(self.is_point.sum()))
        self.step = np.where(data.kind == _CIRCLE, 1e-4, 1e-3)

    def unpack(self, x: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        poses = x[9:].reshape(self.n_views, 6)
        R = Rotation.from_rotvec(poses[:, :3]).as_matrix()
        return x[:9], R, poses[:, 3:]

    def _proj(self, x9: NDArray, R: NDArray, t: NDArray, psi: NDArray) -> NDArray:
        """Pixels ``(P, 2)`` of every observation's target point at ``psi``, the views'
        rotations ``R`` ``(V, 3, 3)`` and translations ``t`` ``(V, 3)``."""
        d = self.d
        out = np.empty((len(psi), 2))
        _curve_pixels(
            np.ascontiguousarray(x9, dtype=np.float64), np.ascontiguousarray(R),
            np.ascontiguousarray(t), d.view, d.kind, d.radius,
            np.ascontiguousarray(psi, dtype=np.float64), d.fixed, out,
        )  # fmt: skip
        return out

    def _residuals_along(self, x9: NDArray, R: NDArray, t: NDArray, nrm: NDArray) -> NDArray:
        """The residuals ``(n_res,)`` at the curve parameters as they are, each curve point's
        along its normal ``nrm`` ``(P, 2)`` (unit, fixed points' rows unused)."""
        d = self.d
        out = np.empty(self.n_res)
        _curve_residuals(
            np.ascontiguousarray(x9, dtype=np.float64), np.ascontiguousarray(R),
            np.ascontiguousarray(t), d.view, d.kind, d.radius,
            np.ascontiguousarray(d.psi, dtype=np.float64), d.fixed, d.obs, nrm, self.slot, out,
        )  # fmt: skip
        return out

    def _normals(self, x9: NDArray, R: NDArray, t: NDArray) -> NDArray:
        """The unit normal ``(P, 2)`` of each observation's curve image at its point (from
        the curve's tangent by a small step of its parameter; 0 for fixed points)."""
        p0 = self._proj(x9, R, t, self.d.psi)
        tan = self._proj(x9, R, t, self.d.psi + self.step) - p0
        nrm = np.column_stack([-tan[:, 1], tan[:, 0]])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        return nrm

    def update_psi(self, x: NDArray, iterations: int = 2) -> None:
        d = self.d
        x9, R, t = self.unpack(x)
        for _ in range(iterations):
            p0 = self._proj(x9, R, t, d.psi)
            p1 = self._proj(x9, R, t, d.psi + self.step)
            tan = (p1 - p0) / self.step[:, None]
            g = np.einsum("pi,pi->p", p0 - d.obs, tan)
            hh = np.einsum("pi,pi->p", tan, tan)
            upd = np.where(self.curve, -g / np.maximum(hh, 1e-300), 0.0)
            d.psi = d.psi + upd

    def residuals(self, x: NDArray, update: bool = True) -> NDArray:
        if update:
            self.update_psi(x)
        x9, R, t = self.unpack(x)
        nrm = self._normals(x9, R, t)
        return self._residuals_along(x9, R, t, nrm)

    def residual_views(self) -> NDArray:
        d = self.d
        return np.concatenate([d.view[self.curve], np.repeat(d.view[self.is_point], 2)])

    def jacobian(self, x: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """Forward differences, all views' pose columns perturbed together (block-sparse).

        The curve parameters stay at their optimum and the residual directions fixed: at the
        optimum the distance's derivative is the partial one (envelope theorem).
        """
        d = self.d
        x9, R, t = self.unpack(x)
        nrm = self._normals(x9, R, t)
        r0 = self._residuals_along(x9, R, t, nrm)
        views = self.residual_views()
        Ji = np.empty((self.n_res, 9))
        _intrinsics_jacobian(
            np.ascontiguousarray(x9, dtype=np.float64), np.ascontiguousarray(R),
            np.ascontiguousarray(t), d.view, d.kind, d.radius,
            np.ascontiguousarray(d.psi, dtype=np.float64), d.fixed, nrm, self.slot, Ji,
        )  # fmt: skip
        Jp = np.empty((self.n_res, 6))
        poses = x[9:].reshape(self.n_views, 6)
        for k in range(6):
            pp = poses.copy()
            hk = np.abs(pp[:, k]) * 1e-7 + 1e-7
            pp[:, k] += hk
            Rk = Rotation.from_rotvec(pp[:, :3]).as_matrix() if k < 3 else R
            Jp[:, k] = (self._residuals_along(x9, Rk, pp[:, 3:], nrm) - r0) / hk[views]
        return Ji, Jp, views

    def normal_equations(self, x: NDArray, r: NDArray, w: NDArray) -> tuple[NDArray, NDArray]:
        """``J^T W J`` and ``J^T W r`` assembled block by block (each view's pose touches only
        its own residuals), never forming the dense Jacobian."""
        Ji, Jp, views = self.jacobian(x)
        n = x.size
        A = np.zeros((n, n))
        g = np.zeros(n)
        wJi = Ji * w[:, None]
        A[:9, :9] = Ji.T @ wJi
        g[:9] = wJi.T @ r
        order = np.argsort(views, kind="stable")
        bounds = np.searchsorted(views[order], np.arange(self.n_views + 1))
        for v in range(self.n_views):
            idx = order[bounds[v] : bounds[v + 1]]
            sl = slice(9 + 6 * v, 15 + 6 * v)
            Jpv = Jp[idx]
            wv = w[idx]
            A[sl, sl] = Jpv.T @ (Jpv * wv[:, None])
            A[:9, sl] = wJi[idx].T @ Jpv
            A[sl, :9] = A[:9, sl].T
            g[sl] = Jpv.T @ (wv * r[idx])
        return A, g


def _initial_psi(data: _Data, K: NDArray, poses: NDArray) -> None:
    """Curve parameters from back-projecting each observation onto its view's plane."""
    Kinv = np.linalg.inv(K)
    R = Rotation.from_rotvec(poses[:, :3]).as_matrix()
    t = poses[:, 3:]
    rays = np.column_stack([data.obs, np.ones(len(data.obs))]) @ Kinv.T
    Rv, tv = R[data.view], t[data.view]
    # Target-frame ray: origin -R^T t, direction R^T ray.
    o = -np.einsum("pji,pj->pi", Rv, tv)
    dvec = np.einsum("pji,pj->pi", Rv, rays)
    s = -o[:, 2] / dvec[:, 2]
    X = o + s[:, None] * dvec
    data.psi = np.where(
        data.kind == _CIRCLE,
        np.arctan2(X[:, 1], X[:, 0]),
        np.where(data.kind == _XLINE, X[:, 0], np.where(data.kind == _YLINE, X[:, 1], 0.0)),
    )


def _gather(obs_list: list[TargetObservation], max_per_ring: int) -> _Data:
    view, kind, radius, uv, fixed = [], [], [], [], []
    for v, ob in enumerate(obs_list):
        if ob.kind == "concentric_circles" and ob.rings:
            for ring in ob.rings:
                pts = ring.edge_points_px
                if len(pts) > max_per_ring:
                    pts = pts[np.linspace(0, len(pts) - 1, max_per_ring).round().astype(int)]
                n = len(pts)
                view.append(np.full(n, v))
                kind.append(np.full(n, _CIRCLE))
                radius.append(np.full(n, ring.radius_mm))
                uv.append(pts)
                fixed.append(np.zeros((n, 3)))
            for ax in ob.axis_points:
                n = len(ax.points_px)
                view.append(np.full(n, v))
                kind.append(np.full(n, _XLINE if ax.axis == "x" else _YLINE))
                radius.append(np.zeros(n))
                uv.append(ax.points_px)
                fixed.append(np.zeros((n, 3)))
        else:
            n = len(ob.points_px)
            view.append(np.full(n, v))
            kind.append(np.full(n, _POINT))
            radius.append(np.zeros(n))
            uv.append(ob.points_px)
            fixed.append(ob.points_target)
    return _Data(
        np.concatenate(view).astype(int),
        np.concatenate(kind).astype(int),
        np.concatenate(radius).astype(float),
        np.concatenate(uv).astype(float),
        np.concatenate(fixed).astype(float),
        np.zeros(sum(len(a) for a in view)),
    )


@dataclass
class _Solution:
    x: NDArray
    success: bool
    message: str
    iterations: int


def _levenberg_marquardt(
    prob: _Problem, x0: NDArray, f_scale: float, free: NDArray, max_iter: int = 60
) -> _Solution:
    """Levenberg-Marquardt on the normal equations with a robust soft-L1 loss (IRLS weights).

    The normal matrix is small (9 + 6 per view), so this is far faster than a dense SVD of
    the Jacobian; columns are scaled by the diagonal (Marquardt's scaling).
    """

    def cost(r: NDArray) -> float:
        z = (r / f_scale) ** 2
        return float(np.sum(2.0 * (np.sqrt(1.0 + z) - 1.0)) * f_scale**2)

    x = x0.copy()
    r = prob.residuals(x)
    c = cost(r)
    lam = 1e-3
    for it in range(max_iter):
        w = 1.0 / np.sqrt(1.0 + (r / f_scale) ** 2)
        A, g = prob.normal_equations(x, r, w)
        dA = np.maximum(np.diag(A), 1e-300)
        improved = False
        for _ in range(12):
            try:
                dx = np.zeros_like(x)
                Af = (A + lam * np.diag(dA))[np.ix_(free, free)]
                dx[free] = -np.linalg.solve(Af, g[free])
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            x_new = x + dx
            r_new = prob.residuals(x_new)
            c_new = cost(r_new)
            if np.isfinite(c_new) and c_new <= c:
                rel = (c - c_new) / max(c, 1e-300)
                x, r, c = x_new, r_new, c_new
                lam = max(lam / 5.0, 1e-9)
                improved = True
                break
            prob.update_psi(x, iterations=3)
            lam *= 8.0
        if not improved:
            return _Solution(x, True, "no further decrease", it)
        step = np.abs(dx) / (np.abs(x) + 1e-6)
        if rel < 1e-12 or float(np.max(step)) < 1e-10:
            return _Solution(x, True, "converged", it)
    return _Solution(x, False, f"stopped after {max_iter} iterations", max_iter)


def _adjust(
    obs_list: list[TargetObservation],
    K0: NDArray,
    dist0: NDArray,
    poses0: NDArray,
    f_scale_px: float | None,
    max_per_ring: int,
    fixed: tuple[str, ...] = (),
) -> tuple[NDArray, NDArray, _Problem, _Solution]:
    """One robust adjustment; with ``f_scale_px=None`` the loss scale is 3 robust sigmas of
    the residuals of a first pass (so honest noise is weighted as least squares)."""
    data = _gather(obs_list, max_per_ring)
    _initial_psi(data, K0, poses0)
    prob = _Problem(data, len(obs_list))
    x0 = np.r_[K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2], dist0[:5], poses0.ravel()]
    prob.update_psi(x0, iterations=6)
    free = np.ones(x0.size, bool)
    free[[PARAM_NAMES.index(n) for n in fixed]] = False
    first_iter = 12 if f_scale_px is None else 60
    sol = _levenberg_marquardt(
        prob, x0, 1.0 if f_scale_px is None else f_scale_px, free, max_iter=first_iter
    )
    if f_scale_px is None:
        r = prob.residuals(sol.x)
        sigma = 1.4826 * float(np.median(np.abs(r - np.median(r))))
        sol = _levenberg_marquardt(prob, sol.x, max(3.0 * sigma, 0.02), free)
    prob.update_psi(sol.x, iterations=3)
    return sol.x, prob.residuals(sol.x, update=False), prob, sol


def adjustment_covariances(
    prob: _Problem, x: NDArray, res: NDArray, fixed: tuple[str, ...]
) -> tuple[NDArray, list[NDArray]]:
    """Covariances after an adjustment, from J^T J and the residual variance.

    Returns
    -------
    intrinsics : ndarray, shape (9, 9)
        :data:`PARAM_NAMES`, marginal over the views' poses (held terms: zero rows and
        columns).
    poses : list of ndarray, shape (6, 6)
        Each view's pose (rotation vector rad, translation mm) given the intrinsics: what
        its own features' noise leaves, through that view's geometry (distance, tilt, how
        much of the target it sees). The intrinsics' error moves the poses too, correlated
        between the views and through each view's geometry differently; that part is left
        out here (it is in ``intrinsics`` and what propagates from it).

    Raises
    ------
    numpy.linalg.LinAlgError
        The normal matrix is singular (the views do not determine every free parameter).
    """
    JtJ, _ = prob.normal_equations(x, res, np.ones(len(res)))
    sigma2 = float(np.sum(res**2) / max(len(res) - x.size, 1))
    free = np.ones(x.size, bool)
    free[[PARAM_NAMES.index(n) for n in fixed]] = False
    cov = np.zeros((x.size, x.size))
    cov[np.ix_(free, free)] = np.linalg.inv(JtJ[np.ix_(free, free)]) * sigma2
    blocks = [slice(9 + 6 * v, 15 + 6 * v) for v in range((x.size - 9) // 6)]
    return cov[:9, :9], [np.linalg.inv(JtJ[b, b]) * sigma2 for b in blocks]


def intrinsics_covariance(
    prob: _Problem, x: NDArray, res: NDArray, fixed: tuple[str, ...]
) -> NDArray:
    """Covariance ``(9, 9)`` of :data:`PARAM_NAMES` after an adjustment, marginal over the
    views' poses (see :func:`adjustment_covariances`)."""
    return adjustment_covariances(prob, x, res, fixed)[0]
