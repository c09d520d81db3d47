"""Minimum-zone (Chebyshev) form: flatness and sphericity by linear programming.

The minimum zone is the smallest possible range of the residuals over all planes (flatness)
or all centres (sphericity); it is never more than the least-squares range. Both are solved by
:func:`scipy.optimize.linprog`, linearised about a starting plane or centre (the least-squares
one) and re-linearised until the zone stops shrinking.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linprog

from metrology.fits.geometry import perp_basis, rownorm, scatter_eig, sphere_algebraic
from scanner.core.conventions import check_points

__all__ = ["min_zone_flatness", "min_zone_sphericity"]


def _min_range_lp(a: NDArray, b: NDArray, bound: float) -> tuple[NDArray, float] | None:
    """``delta`` (k,), ``|delta_i| <= bound``, minimising ``max(b - a delta) - min(b - a delta)``
    for ``a`` (m, k) and ``b`` (m,); returns ``delta`` and that range, or None if the LP fails."""
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
    """Indices of the ``k`` smallest and ``k`` largest of ``values`` (N,): where the zone's
    bounding points are likely to be."""
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
        _, _, evec = scatter_eig(pts)
        n = evec[:, 0]
    else:
        n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    best = float(np.ptp(x @ n))
    for _ in range(6):
        u, v = perp_basis(n)
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
        init = sphere_algebraic(pts)
        if init is None:
            raise ValueError("points: expected points on a sphere, got a degenerate set")
        c = init[0]
    else:
        c = np.asarray(center, dtype=np.float64).reshape(3)
    rho = rownorm(pts - c)
    best = float(np.ptp(rho))
    step = max(best, 1e-9)
    for _ in range(30):
        q = pts - c
        rho = rownorm(q)
        unit = q / rho[:, None]
        active = _active_set_candidates(rho, 200)
        res = _min_range_lp(unit[active], rho[active], step)
        if res is None:
            break
        delta = res[0]
        c_new = c + delta
        zone = float(np.ptp(rownorm(pts - c_new)))
        if zone < best * (1 - 1e-12):
            best, c = zone, c_new
            if np.linalg.norm(delta) < 1e-10:
                break
        else:
            step *= 0.3
            if step < 1e-9:
                break
    return best
