"""The public fits: plane, sphere, cylinder, 3-D circle and line of a point cloud.

Each checks its points, runs :func:`metrology.fits.robust.robust_fit` on the primitive's model
and, where asked, adds the minimum-zone form.
"""

from __future__ import annotations

from dataclasses import replace

from numpy.typing import ArrayLike

from metrology.fits.axial import CircleModel, CylinderModel
from metrology.fits.geometry import SeedLike, take
from metrology.fits.min_zone import min_zone_flatness, min_zone_sphericity
from metrology.fits.models import LineModel, PlaneModel, SphereModel
from metrology.fits.results import CircleFit, CylinderFit, LineFit, PlaneFit, SphereFit
from metrology.fits.robust import robust_fit
from scanner.core.conventions import check_points

__all__ = ["fit_circle", "fit_cylinder", "fit_line", "fit_plane", "fit_sphere"]


def fit_plane(
    points: ArrayLike, threshold_mm: float | None = None, *, min_zone: bool = False,
    seed: SeedLike = 0, max_iterations: int = 1000,
) -> PlaneFit:  # fmt: skip
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
        Seeds the RANSAC sampling and the subsamples (a fit is repeatable).
    max_iterations : int
        Most RANSAC hypotheses (fewer once the inlier ratio makes more needless).

    Returns
    -------
    PlaneFit
        Unit normal and offset (``normal . p + d = 0``), their standard deviations, residual
        RMS and range, or a failed fit (falsy) whose ``reason`` says why.
    """
    pts = check_points(points, min_count=0)
    fit = robust_fit(PlaneModel(), pts, threshold_mm, seed=seed, max_iterations=max_iterations)
    if min_zone and fit:
        fit = replace(fit, min_zone_mm=min_zone_flatness(take(pts, fit.inliers), fit.normal))
    return fit


def fit_sphere(
    points: ArrayLike, threshold_mm: float | None = None, *, min_zone: bool = False,
    seed: SeedLike = 0, max_iterations: int = 1000,
    radius_range_mm: tuple[float, float] | None = None,
) -> SphereFit:  # fmt: skip
    """Fit a sphere by orthogonal (radial) least squares, optionally after RANSAC.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points on the sphere, mm. N >= 4, not coplanar.
    threshold_mm, seed, max_iterations
        As for :func:`fit_plane`.
    min_zone : bool
        Also evaluate the minimum-zone sphericity (``min_zone_mm``).
    radius_range_mm : (float, float), optional
        Radii a RANSAC hypothesis may have (e.g. nominal +-20 %); without it, at most the
        cloud's extent, so that a plane is not taken for a huge sphere.

    Returns
    -------
    SphereFit
        Centre, radius, their standard deviations, residual RMS and range (the probing form
        error), or a failed fit (falsy) whose ``reason`` says why.
    """
    pts = check_points(points, min_count=0)
    model = SphereModel(radius_range_mm)
    fit = robust_fit(model, pts, threshold_mm, seed=seed, max_iterations=max_iterations)
    if min_zone and fit:
        mz = min_zone_sphericity(take(pts, fit.inliers), fit.center_mm)
        fit = replace(fit, min_zone_mm=mz)
    return fit


def fit_cylinder(
    points: ArrayLike, threshold_mm: float | None = None, *, seed: SeedLike = 0,
    max_iterations: int = 1000, radius_range_mm: tuple[float, float] | None = None,
    axis_hint: ArrayLike | None = None, start: CylinderFit | None = None,
) -> CylinderFit:  # fmt: skip
    """Fit a cylinder by orthogonal (radial) least squares, optionally after RANSAC.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points on the cylinder's surface, mm (a partial arc will do). N >= 6, not collinear.
    threshold_mm : float, optional
        RANSAC inlier distance (hypotheses from two points and their Open3D normals); without
        it every point is an inlier.
    seed, max_iterations, radius_range_mm
        As for :func:`fit_sphere`.
    axis_hint : array_like, shape (3,), optional
        Approximate axis direction (e.g. the nominal), tried besides the direction search.
    start : CylinderFit, optional
        An earlier fit of nearly the same points: the least squares start from it (and from
        ``axis_hint``, when given) instead of a search for the axis.

    Returns
    -------
    CylinderFit
        Axis, axis point, radius and their standard deviations, residual RMS and range, or a
        failed fit (falsy) whose ``reason`` says why.
    """
    pts = check_points(points, min_count=0)
    model = CylinderModel(radius_range_mm, axis_hint)
    return robust_fit(
        model, pts, threshold_mm, seed=seed, max_iterations=max_iterations, start=start
    )


def fit_circle(
    points: ArrayLike, threshold_mm: float | None = None, *, seed: SeedLike = 0,
    max_iterations: int = 1000, radius_range_mm: tuple[float, float] | None = None,
) -> CircleFit:  # fmt: skip
    """Fit a circle in 3-D by orthogonal least squares (3-D distance to the circle).

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points on or near the circle (an arc will do), mm. N >= 4, not collinear.
    threshold_mm : float, optional
        RANSAC inlier distance (3-D distance to the circle); without it every point is an
        inlier.
    seed, max_iterations, radius_range_mm
        As for :func:`fit_sphere`.

    Returns
    -------
    CircleFit
        Centre, normal, radius and their standard deviations, residual figures, or a failed
        fit (falsy) whose ``reason`` says why.
    """
    pts = check_points(points, min_count=0)
    model = CircleModel(radius_range_mm)
    return robust_fit(model, pts, threshold_mm, seed=seed, max_iterations=max_iterations)


def fit_line(
    points: ArrayLike, threshold_mm: float | None = None, *, seed: SeedLike = 0,
    max_iterations: int = 1000,
) -> LineFit:  # fmt: skip
    """Fit a 3-D line by orthogonal least squares (closed form), optionally after RANSAC.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Points along the line, mm. N >= 3, not all coincident.
    threshold_mm, seed, max_iterations
        As for :func:`fit_plane`.

    Returns
    -------
    LineFit
        Centroid, unit direction and their standard deviations, the distances' RMS and range,
        or a failed fit (falsy) whose ``reason`` says why.
    """
    pts = check_points(points, min_count=0)
    return robust_fit(LineModel(), pts, threshold_mm, seed=seed, max_iterations=max_iterations)
