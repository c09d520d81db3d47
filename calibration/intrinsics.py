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
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from calibration.detection.conics import fit_line
from calibration.detection.observations import TargetObservation
from scanner.core.conventions import make_transform

log = logging.getLogger(__name__)

__all__ = ["PARAM_NAMES", "IntrinsicsResult", "PaperEstimate", "calibrate_intrinsics"]

PARAM_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


@dataclass
class PaperEstimate:
    """One variant of the paper's closed-form intrinsics (zero skew, no distortion).

    ``ok`` False with ``reason`` when the linear system is degenerate or gives a negative
    alpha^2 / beta^2.
    """

    variant: str
    ok: bool
    reason: str = ""
    K: NDArray = field(default_factory=lambda: np.eye(3))
    vanishing_points: list[tuple[NDArray, NDArray]] = field(default_factory=list)

    def __bool__(self) -> bool:
        return bool(self.ok)


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
    """

    K: NDArray
    dist: NDArray
    image_size: tuple[int, int]
    method: str
    view_indices: list[int] = field(default_factory=list)
    cam_from_target: list[NDArray] = field(default_factory=list)
    rms_px: float = float("nan")
    per_view_rms_px: NDArray = field(default_factory=lambda: np.zeros(0))
    std: dict[str, float] = field(default_factory=dict)
    correlation: NDArray = field(default_factory=lambda: np.eye(len(PARAM_NAMES)))
    warnings: list[str] = field(default_factory=list)
    rejected: list[tuple[int, str]] = field(default_factory=list)
    paper: dict[str, PaperEstimate] = field(default_factory=dict)
    n_residuals: int = 0

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


MIN_VIEWS = 4

# Curve kinds of the adjustment's observations.
_CIRCLE, _XLINE, _YLINE, _POINT = 0, 1, 2, 3


# --------------------------------------------------------------------------------------------
# The paper's closed form (Section III.A)


def _to_xy(p: NDArray) -> NDArray:
    return np.asarray(p[:2], dtype=np.float64) / p[2]


def paper_intrinsics(
    vanishing_points: list[tuple[NDArray, NDArray]], variant: str = "diameter_ends"
) -> PaperEstimate:
    """Equations (4)-(6): K from the vanishing points (p, q) of n >= 4 views.

    Differences of consecutive views' equation (4) give ``H phi = g`` with
    ``phi = (u0, v0 alpha^2 / beta^2, alpha^2 / beta^2)``; then ``v0 = phi[1] / phi[2]`` (the
    paper prints ``y'/x'``, a typo: ``y' = v0 z'``) and ``alpha^2`` from (4) averaged over the
    views, ``beta^2 = alpha^2 / z'``.
    """
    vps = [(np.asarray(p, float), np.asarray(q, float)) for p, q in vanishing_points]
    finite = [
        (p, q)
        for p, q in vps
        if abs(p[2]) > 1e-12 * np.linalg.norm(p) and abs(q[2]) > 1e-12 * np.linalg.norm(q)
    ]
    if len(finite) < MIN_VIEWS:
        return PaperEstimate(
            variant,
            False,
            f"expected >= {MIN_VIEWS} views with finite vanishing points, got {len(finite)}",
            vanishing_points=vps,
        )
    pq = np.array([np.r_[_to_xy(p), _to_xy(q)] for p, q in finite])  # up, vp, uq, vq
    su = pq[:, 0] + pq[:, 2]
    sv = pq[:, 1] + pq[:, 3]
    pu = pq[:, 0] * pq[:, 2]
    pv = pq[:, 1] * pq[:, 3]
    H = np.column_stack([-np.diff(su), -np.diff(sv), np.diff(pv)])
    g = -np.diff(pu)
    if np.linalg.matrix_rank(H, tol=1e-9 * max(np.abs(H).max(), 1.0)) < 3:
        return PaperEstimate(
            variant, False, "H is rank deficient: views too alike", vanishing_points=vps
        )
    phi, *_ = np.linalg.lstsq(H, g, rcond=None)
    u0, yp, zp = (float(v) for v in phi)
    if zp <= 0:
        return PaperEstimate(
            variant,
            False,
            f"alpha^2/beta^2 = {zp:.3g} <= 0: inconsistent views",
            vanishing_points=vps,
        )
    v0 = yp / zp
    a2 = -np.mean((u0 - pq[:, 0]) * (u0 - pq[:, 2]) + zp * (v0 - pq[:, 1]) * (v0 - pq[:, 3]))
    if a2 <= 0:
        return PaperEstimate(
            variant, False, f"alpha^2 = {a2:.3g} <= 0: inconsistent views", vanishing_points=vps
        )
    alpha = float(np.sqrt(a2))
    beta = float(np.sqrt(a2 / zp))
    K = np.array([[alpha, 0.0, u0], [0.0, beta, v0], [0.0, 0.0, 1.0]])
    return PaperEstimate(variant, True, "", K, vps)


def _axis_vanishing_point(obs: TargetObservation, axis: str) -> NDArray | None:
    """Vanishing point of one diameter from every ring's ends: 1-D projective fit ``s -> t``."""
    col = 0 if axis == "x" else 1
    other = 1 - col
    sel = np.abs(obs.points_target[:, other]) < 1e-9
    s = obs.points_target[sel, col]
    pts = obs.points_px[sel]
    if len(s) < 4 or obs.center_px is None:
        return None
    o = np.asarray(obs.center_px, float)
    line = fit_line(pts)
    d = np.array([-line[1], line[0]])
    far = pts[np.argmax(s)]
    if float((far - o) @ d) < 0:
        d = -d
    t = (pts - o) @ d
    # t (c s + 1) = a s + b
    A = np.column_stack([s, np.ones_like(s), -s * t])
    (a, b, c), *_ = np.linalg.lstsq(A, t, rcond=None)
    base = o + b * 0.0
    return np.array([c * base[0] + a * d[0], c * base[1] + a * d[1], c])


def _paper_variants(obs_list: list[TargetObservation]) -> dict[str, PaperEstimate]:
    ends, rings = [], []
    for ob in obs_list:
        vp = ob.vanishing_points
        if "p" in vp and "q" in vp:
            ends.append((vp["p"], vp["q"]))
        px, qy = _axis_vanishing_point(ob, "x"), _axis_vanishing_point(ob, "y")
        if px is not None and qy is not None:
            rings.append((px, qy))
    return {
        "diameter_ends": paper_intrinsics(ends, "diameter_ends"),
        "all_rings": paper_intrinsics(rings, "all_rings"),
    }


# --------------------------------------------------------------------------------------------
# The adjustment


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


def _curve_points(kind: NDArray, radius: NDArray, psi: NDArray, fixed: NDArray) -> NDArray:
    pts = fixed.copy()
    c = kind == _CIRCLE
    pts[c, 0] = radius[c] * np.cos(psi[c])
    pts[c, 1] = radius[c] * np.sin(psi[c])
    xl = kind == _XLINE
    pts[xl, 0] = psi[xl]
    pts[xl, 1] = 0.0
    yl = kind == _YLINE
    pts[yl, 0] = 0.0
    pts[yl, 1] = psi[yl]
    pts[c | xl | yl, 2] = 0.0
    return pts


class _Problem:
    """Residuals of every observation for the parameter vector (9 intrinsics + 6 per view)."""

    def __init__(self, data: _Data, n_views: int) -> None:
        self.d = data
        self.n_views = n_views
        self.curve = data.kind != _POINT
        self.is_point = ~self.curve
        # Residual layout: one per curve point, two per fixed point.
        self.n_res = int(self.curve.sum() + 2 * self.is_point.sum())
        self.step = np.where(data.kind == _CIRCLE, 1e-4, 1e-3)

    def unpack(self, x: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        poses = x[9:].reshape(self.n_views, 6)
        R = Rotation.from_rotvec(poses[:, :3]).as_matrix()
        return x[:9], R, poses[:, 3:]

    def _proj(self, x9: NDArray, Rp: NDArray, tp: NDArray, psi: NDArray) -> NDArray:
        d = self.d
        return _project(x9, Rp, tp, _curve_points(d.kind, d.radius, psi, d.fixed))

    def update_psi(self, x: NDArray, iterations: int = 2) -> None:
        d = self.d
        x9, R, t = self.unpack(x)
        Rp, tp = R[d.view], t[d.view]
        for _ in range(iterations):
            p0 = self._proj(x9, Rp, tp, d.psi)
            p1 = self._proj(x9, Rp, tp, d.psi + self.step)
            tan = (p1 - p0) / self.step[:, None]
            g = np.einsum("pi,pi->p", p0 - d.obs, tan)
            hh = np.einsum("pi,pi->p", tan, tan)
            upd = np.where(self.curve, -g / np.maximum(hh, 1e-300), 0.0)
            d.psi = d.psi + upd

    def residuals(self, x: NDArray, update: bool = True) -> NDArray:
        d = self.d
        if update:
            self.update_psi(x)
        x9, R, t = self.unpack(x)
        Rp, tp = R[d.view], t[d.view]
        p0 = self._proj(x9, Rp, tp, d.psi)
        diff = d.obs - p0
        out = np.empty(self.n_res)
        nc = int(self.curve.sum())
        if nc:
            pc = self._proj(x9, Rp, tp, d.psi + self.step)
            tan = pc - p0
            nrm = np.column_stack([-tan[:, 1], tan[:, 0]])
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
            out[:nc] = np.einsum("pi,pi->p", diff, nrm)[self.curve]
        if self.is_point.any():
            out[nc:] = diff[self.is_point].ravel()
        return out

    def residual_views(self) -> NDArray:
        d = self.d
        return np.concatenate([d.view[self.curve], np.repeat(d.view[self.is_point], 2)])

    def jacobian(self, x: NDArray) -> NDArray:
        """Forward differences, all views' pose columns perturbed together (block-sparse).

        The curve parameters stay at their optimum and the residual directions fixed: at the
        optimum the distance's derivative is the partial one (envelope theorem).
        """
        d = self.d
        pts = _curve_points(d.kind, d.radius, d.psi, d.fixed)
        x9, R, t = self.unpack(x)
        p0 = _project(x9, R[d.view], t[d.view], pts)
        pc = _project(
            x9, R[d.view], t[d.view], _curve_points(d.kind, d.radius, d.psi + self.step, d.fixed)
        )
        tan = pc - p0
        nrm = np.column_stack([-tan[:, 1], tan[:, 0]])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        curve, point = self.curve, self.is_point

        def res(x9_: NDArray, R_: NDArray, t_: NDArray) -> NDArray:
            diff = d.obs - _project(x9_, R_[d.view], t_[d.view], pts)
            return np.concatenate(
                [np.einsum("pi,pi->p", diff[curve], nrm[curve]), diff[point].ravel()]
            )

        r0 = res(x9, R, t)
        views = self.residual_views()
        _, D = _project(x9, R[d.view], t[d.view], pts, parts=True)
        nc = int(curve.sum())
        Ji = np.empty((self.n_res, 9))
        Ji[:nc] = -np.einsum("pij,pi->pj", D[curve], nrm[curve])
        Ji[nc:] = -D[point].reshape(-1, 9)
        Jp = np.empty((self.n_res, 6))
        poses = x[9:].reshape(self.n_views, 6)
        for k in range(6):
            pp = poses.copy()
            hk = np.abs(pp[:, k]) * 1e-7 + 1e-7
            pp[:, k] += hk
            Rk = Rotation.from_rotvec(pp[:, :3]).as_matrix() if k < 3 else R
            Jp[:, k] = (res(x9, Rk, pp[:, 3:]) - r0) / hk[views]
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


def calibrate_intrinsics(
    observations: list[TargetObservation],
    image_size: tuple[int, int],
    method: Literal["default", "paper"] = "default",
    target: object | None = None,
    f_scale_px: float | None = None,
    max_points_per_ring: int = 200,
    fixed: tuple[str, ...] = (),
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
    x, res, prob, sol = _adjust(obs, K0, dist0, poses, f_scale_px, max_points_per_ring, fixed)

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
        K1 = np.array([[x[0], 0, x[2]], [0, x[1], x[3]], [0, 0, 1.0]])
        x, res, prob, sol = _adjust(obs, K1, x[4:9], poses, f_scale_px, max_points_per_ring, fixed)

    views = prob.residual_views()
    per_view = np.array([np.sqrt(np.mean(res[views == v] ** 2)) for v in range(len(obs))])
    K = np.array([[x[0], 0, x[2]], [0, x[1], x[3]], [0, 0, 1.0]])
    dist = x[4:9].copy()
    poses = x[9:].reshape(-1, 6)
    cam_from_target = [make_transform(Rotation.from_rotvec(p[:3]), p[3:]) for p in poses]

    # -- uncertainty
    JtJ, _ = prob.normal_equations(x, res, np.ones(len(res)))
    dof = max(len(res) - x.size, 1)
    sigma2 = float(np.sum(res**2) / dof)
    std: dict[str, float] = {}
    corr = np.full((9, 9), np.nan)
    try:
        free = np.ones(x.size, bool)
        free[[PARAM_NAMES.index(n) for n in fixed]] = False
        cov = np.zeros((x.size, x.size))
        cov[np.ix_(free, free)] = np.linalg.inv(JtJ[np.ix_(free, free)]) * sigma2
        c9 = cov[:9, :9]
        sd = np.sqrt(np.maximum(np.diag(c9), 0))
        std = {n: float(v) for n, v in zip(PARAM_NAMES, sd)}
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = c9 / np.outer(sd, sd)
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
        rms_px=float(np.sqrt(np.mean(res**2))),
        per_view_rms_px=per_view,
        std=std,
        correlation=corr,
        warnings=warnings,
        rejected=sorted(rejected),
        paper=paper,
        n_residuals=len(res),
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
    )
