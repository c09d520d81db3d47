"""Small geometric helpers the fits share: frames, scatter matrices, closed-form and algebraic
estimates, distances and covariances.

Every function takes and returns float64 numpy arrays; point sets are ``(N, 3)`` in mm.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "DEGENERACY_RATIO",
    "SeedLike",
    "circle_distance",
    "circle_from_3",
    "circle_scores",
    "covariance",
    "cylinder_from_normals",
    "degenerate_rank",
    "extent",
    "fibonacci_hemisphere",
    "frame_std",
    "orient",
    "perp_basis",
    "residual_stats",
    "rng_from",
    "rownorm",
    "scatter_eig",
    "sphere_algebraic",
    "subsample",
    "take",
]

#: Relative size of the smallest singular value below which a point set counts as degenerate.
DEGENERACY_RATIO = 1e-6

SeedLike = int | np.random.Generator | None


def rng_from(seed: SeedLike) -> np.random.Generator:
    """The generator itself, or a new one seeded with ``seed``."""
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


def orient(v: NDArray) -> NDArray:
    """Unit vector of ``v`` (shape (3,)) with its largest-magnitude component positive."""
    v = v / np.linalg.norm(v)
    return -v if v[np.argmax(np.abs(v))] < 0 else v


def perp_basis(n: NDArray) -> tuple[NDArray, NDArray]:
    """Unit ``u, v`` (each shape (3,)) with ``(u, v, n)`` right-handed and orthonormal."""
    helper = np.eye(3)[np.argmin(np.abs(n))]
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def scatter_eig(points: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Centroid (3,), eigenvalues (3,) ascending and eigenvectors (3, 3) as columns of the
    scatter matrix of ``(N, 3)`` points."""
    c = points.mean(axis=0)
    x = points - c
    w, v = np.linalg.eigh(x.T @ x)
    return c, np.maximum(w, 0.0), v


def degenerate_rank(points: NDArray) -> int:
    """Numerical rank of the centred ``(N, 3)`` point set: 0 coincident, 1 collinear,
    2 coplanar, 3."""
    _, w, _ = scatter_eig(points)
    s = np.sqrt(w)
    if s[2] <= 1e-12 * max(1.0, float(np.abs(points).max())):
        return 0
    return int(1 + (s[1] > DEGENERACY_RATIO * s[2]) + (s[0] > DEGENERACY_RATIO * s[2]))


def rownorm(a: NDArray) -> NDArray:
    """Euclidean norm (N,) of each row of an ``(N, 3)`` array (faster than ``linalg.norm``)."""
    return np.sqrt(np.einsum("ij,ij->i", a, a))


def extent(points: NDArray) -> float:
    """Largest side of the bounding box of ``(N, 3)`` points (from at most ~100k of them:
    only a scale is needed)."""
    step = max(1, len(points) // 100_000)
    return float(np.ptp(points[::step], axis=0).max())


def take(points: NDArray, mask: NDArray) -> NDArray:
    """``points[mask]`` (mask shape (N,)) without the copy when every point is selected."""
    return points if mask.all() else points[mask]


def subsample(n: int, k: int, rng: np.random.Generator) -> NDArray:
    """Sorted indices (min(n, k),) of a random subset of ``range(n)``; all of them (drawing
    nothing from ``rng``) when ``n <= k``."""
    return np.arange(n) if n <= k else np.sort(rng.choice(n, size=k, replace=False))


def residual_stats(res: NDArray) -> tuple[float, float]:
    """RMS and range (max - min) of residuals of shape (M,)."""
    return float(np.sqrt(np.mean(res**2))), float(res.max() - res.min())


def covariance(jac: NDArray, res: NDArray) -> NDArray:
    """``sigma^2 (J^T J)^-1`` (p, p) with ``sigma^2 = sum r^2 / (m - p)`` for a Jacobian of shape
    (m, p) and residuals (m,); all NaN when no degree of freedom is left (``m <= p``) or
    ``J^T J`` is singular."""
    m, p = jac.shape
    if m <= p:
        return np.full((p, p), np.nan)
    sigma2 = float(res @ res) / (m - p)
    jtj = jac.T @ jac
    try:
        return sigma2 * np.linalg.inv(jtj)
    except np.linalg.LinAlgError:
        return np.full((p, p), np.nan)


def frame_std(basis: NDArray, cov: NDArray) -> NDArray:
    """Standard deviations (3,) of ``basis @ x`` for ``x`` of covariance ``cov`` (2, 2), with
    ``basis`` (3, 2) the in-plane unit vectors as columns."""
    return np.sqrt(np.maximum(np.diag(basis @ cov @ basis.T), 0))


def sphere_algebraic(p: NDArray) -> tuple[NDArray, float] | None:
    """Kasa fit of ``(N, 3)`` points: ``|p|^2 = 2 c . p + (r^2 - |c|^2)`` by linear least
    squares on centred data. Centre (3,) and radius, or None."""
    c0 = p.mean(axis=0)
    x = p - c0
    a = np.column_stack([2 * x, np.ones(len(x))])
    b = np.einsum("ij,ij->i", x, x)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    r2 = sol[3] + sol[:3] @ sol[:3]
    if not np.all(np.isfinite(sol)) or r2 <= 0:
        return None
    return c0 + sol[:3], float(np.sqrt(r2))


def circle_scores(x: NDArray, y: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Kasa circle fits of ``(M, D)`` coordinate columns (D candidate projections of M
    points): centres ``cx, cy``, radii and geometric RMS, each of shape (D,)."""
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


def circle_distance(p: NDArray, c: NDArray, n: NDArray, r: float) -> NDArray:
    """Unsigned 3-D distance (N,) of ``(N, 3)`` points from the circle of centre ``c`` (3,),
    unit normal ``n`` (3,) and radius ``r``."""
    q = p - c
    w = q @ n
    rho = rownorm(q - np.outer(w, n)) - r
    return np.hypot(w, rho)


def circle_from_3(a: NDArray, b: NDArray, c: NDArray) -> tuple[NDArray, NDArray, float] | None:
    """Centre (3,), unit normal (3,) and radius of the circle through three points (each (3,)),
    or None for (nearly) collinear points."""
    ab, ac = b - a, c - a
    n = np.cross(ab, ac)
    nn2 = n @ n
    if nn2 <= 1e-18 * (ab @ ab) * (ac @ ac) or nn2 == 0:
        return None
    centre = a + (np.cross(n, ab) * (ac @ ac) + np.cross(ac, n) * (ab @ ab)) / (2 * nn2)
    return centre, n / math.sqrt(nn2), float(np.linalg.norm(a - centre))


def cylinder_from_normals(
    p1: NDArray, n1: NDArray, p2: NDArray, n2: NDArray
) -> tuple[NDArray, NDArray, float] | None:
    """Unit axis (3,), axis point (3,) and radius from two surface points and their unit
    normals (each (3,)), or None when the normals are (nearly) parallel."""
    a = np.cross(n1, n2)
    an = np.linalg.norm(a)
    if an < 1e-3:
        return None
    a /= an
    u, v = perp_basis(a)
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


def fibonacci_hemisphere(n: int) -> NDArray:
    """``n`` unit vectors (n, 3) spread evenly over the upper hemisphere (z > 0)."""
    i = np.arange(n) + 0.5
    z = i / n  # uniform in z on (0, 1]: uniform on the hemisphere
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    r = np.sqrt(1 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
