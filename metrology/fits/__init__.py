"""Geometric fits of plane, sphere, cylinder, 3-D circle and line to point clouds.

Each fit runs in two steps (:func:`metrology.fits.robust.robust_fit`, one loop for all):

1. **Robust detection** (optional, when ``threshold_mm`` is given): MSAC, a RANSAC variant that
   scores a hypothesis by its truncated squared distances, on a seeded random subsample of at
   most :data:`RANSAC_SUBSAMPLE` points, with the iteration count adapted to the inlier ratio.
   The best model's inliers are then taken from the full cloud (for a big cloud, after the
   whole robust fit has run on the subsample), alternating with the least squares until the
   inlier set is stable. The inlier band is the threshold, widened to ``BAND_SIGMAS``
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

Modules
-------
``primitives``  the public ``fit_*`` functions
``robust``      the robust loop (:func:`robust_fit`, MSAC :func:`ransac`) and the ``Model`` base
``models``      plane, line and sphere models
``axial``       cylinder and circle models
``lsq``         least squares on large clouds (subsample, then Gauss-Newton on all points)
``results``     the result dataclasses
``min_zone``    minimum-zone flatness and sphericity
``geometry``    shared geometric helpers
"""

from metrology.fits.lsq import LSQ_SUBSAMPLE
from metrology.fits.min_zone import min_zone_flatness, min_zone_sphericity
from metrology.fits.primitives import fit_circle, fit_cylinder, fit_line, fit_plane, fit_sphere
from metrology.fits.results import CircleFit, CylinderFit, Fit, LineFit, PlaneFit, SphereFit
from metrology.fits.robust import RANSAC_SUBSAMPLE

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
