"""Geometric least squares for the iterative fits (sphere, cylinder, circle).

:func:`solve_lsq` minimises ``sum fun(x, points)^2`` with :func:`scipy.optimize.least_squares`
and analytic Jacobians. Clouds of more than :data:`LSQ_SUBSAMPLE` points are solved on a
subsample first and finished by a few Gauss-Newton steps on all points, which keeps a fit on a
million points well under a second.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from metrology.fits.geometry import subsample

__all__ = ["LSQ_SUBSAMPLE", "Residuals", "gauss_newton_polish", "solve_lsq"]

log = logging.getLogger(__name__)

#: Least squares converges on at most this many points before the final pass on all of them.
LSQ_SUBSAMPLE = 50_000

#: ``fun(x, points)`` or ``jac(x, points)``: residuals (M,) or their Jacobian (M, p) for
#: parameters ``x`` (p,) and points (N, 3).
Residuals = Callable[[NDArray, NDArray], NDArray]


def gauss_newton_polish(
    fun: Residuals, jac: Residuals, x: NDArray, pts: NDArray, max_steps: int = 3
) -> NDArray | None:
    """Gauss-Newton steps on all points from a nearly converged ``x`` (p,).

    Returns
    -------
    ndarray, shape (p,), or None
        The polished parameters; None if a step fails to lower the cost (the caller then runs
        the full least squares).
    """
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


def solve_lsq(
    fun: Residuals, jac: Residuals, x0: NDArray, pts: NDArray, rng: np.random.Generator
) -> NDArray:
    """Minimise ``sum fun(x, pts)^2`` with :func:`scipy.optimize.least_squares` (Levenberg-
    Marquardt) from ``x0`` (p,); returns ``x`` (p,).

    A cloud ``pts`` (N, 3) of more than :data:`LSQ_SUBSAMPLE` points is solved on a random
    subsample (drawn from ``rng``) first; from there (within about
    ``sigma / sqrt(LSQ_SUBSAMPLE)`` of the optimum) Gauss-Newton steps on all points converge
    quadratically, at a fraction of the cost of a full solver run. If a step does not lower the
    cost, ``least_squares`` runs on all points instead.
    """
    x = np.asarray(x0, dtype=np.float64)
    if len(pts) > LSQ_SUBSAMPLE:
        sub = pts[subsample(len(pts), LSQ_SUBSAMPLE, rng)]
        x = least_squares(fun, x, jac=jac, args=(sub,), method="lm", xtol=1e-12, ftol=1e-12).x
        polished = gauss_newton_polish(fun, jac, x, pts)
        if polished is not None:
            return polished
        log.debug("Gauss-Newton polish did not converge; full least squares")
    sol = least_squares(fun, x, jac=jac, args=(pts,), method="lm", xtol=1e-13, ftol=1e-12)
    log.debug("least squares on %d points: %d evaluations", len(pts), sol.nfev)
    return sol.x
