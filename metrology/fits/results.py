"""Result dataclasses of the fits: parameters, their standard deviations and residual figures.

A fit that could not succeed is falsy and says why in ``reason``; its numbers are NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from metrology.fits.geometry import circle_distance, rownorm

__all__ = ["CircleFit", "CylinderFit", "Fit", "LineFit", "PlaneFit", "SphereFit"]


def _nan3() -> NDArray:
    return np.full(3, np.nan)


def _empty_mask() -> NDArray:
    return np.zeros(0, dtype=bool)


def _empty() -> NDArray:
    return np.zeros(0)


def _radial_deviation(points: ArrayLike, origin: NDArray, direction: NDArray, r: float) -> NDArray:
    """Distance (N,) of ``(N, 3)`` points from the line through ``origin`` along the unit
    ``direction`` (each (3,)), minus ``r``."""
    q = np.asarray(points, dtype=np.float64) - origin
    return rownorm(q - np.outer(q @ direction, direction)) - r


class _Round:
    """The diameter of a fit with a radius (sphere, cylinder, circle)."""

    radius_mm: float  # the dataclass field of the subclass

    @property
    def diameter_mm(self) -> float:
        """Twice the radius, mm."""
        return 2.0 * self.radius_mm


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
    #: The parameters :meth:`to_json` writes, in order (names of fields or properties).
    _json_fields: ClassVar[str] = ""

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

    def _params_json(self) -> dict[str, Any]:
        """The subclass's ``_json_fields`` in order: arrays as lists, numbers as floats."""
        out: dict[str, Any] = {}
        for name in self._json_fields.split():
            value = getattr(self, name)
            out[name] = value.tolist() if isinstance(value, np.ndarray) else float(value)
        return out

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

    Attributes
    ----------
    normal, normal_std : ndarray, shape (3,)
        Unit normal (largest-magnitude component positive) and its components' standard
        deviations.
    d_mm, d_std_mm : float
        Offset and its standard deviation, mm.
    centroid_mm : ndarray, shape (3,)
        The inliers' centroid, mm.
    """

    normal: NDArray = field(default_factory=_nan3)
    d_mm: float = math.nan
    centroid_mm: NDArray = field(default_factory=_nan3)
    normal_std: NDArray = field(default_factory=_nan3)
    d_std_mm: float = math.nan
    kind: str = "plane"
    _json_fields: ClassVar[str] = "normal d_mm centroid_mm normal_std d_std_mm"

    def signed_distance(self, points: ArrayLike) -> NDArray:
        """Signed distance of ``(N, 3)`` points from the plane, positive on the normal's side."""
        return np.asarray(points, dtype=np.float64) @ self.normal + self.d_mm


@dataclass(frozen=True, kw_only=True, eq=False)
class SphereFit(Fit, _Round):
    """Sphere of centre ``center_mm`` and radius ``radius_mm``; ``cov`` over (cx, cy, cz, r).

    Attributes
    ----------
    center_mm, center_std_mm : ndarray, shape (3,)
        Centre and the standard deviations of its coordinates, mm.
    radius_mm, radius_std_mm : float
        Radius and its standard deviation, mm (``diameter_mm`` is twice the radius).
    """

    center_mm: NDArray = field(default_factory=_nan3)
    radius_mm: float = math.nan
    center_std_mm: NDArray = field(default_factory=_nan3)
    radius_std_mm: float = math.nan
    kind: str = "sphere"
    _json_fields: ClassVar[str] = "center_mm radius_mm diameter_mm center_std_mm radius_std_mm"

    def signed_distance(self, points: ArrayLike) -> NDArray:
        """Radial deviation ``|p - c| - r`` of ``(N, 3)`` points, positive outside."""
        p = np.asarray(points, dtype=np.float64)
        return rownorm(p - self.center_mm) - self.radius_mm


@dataclass(frozen=True, kw_only=True, eq=False)
class CylinderFit(Fit, _Round):
    """Cylinder of unit ``axis`` through ``point_mm`` (the axis point nearest the inliers'
    centroid) and radius ``radius_mm``.

    ``cov`` is over (axis tilt about ``u``, about ``v`` [rad], axis shift along ``u``, along
    ``v`` [mm], radius [mm]) with ``u, v`` perpendicular to the axis.

    Attributes
    ----------
    axis, axis_std : ndarray, shape (3,)
        Unit axis (largest-magnitude component positive) and its components' standard
        deviations.
    point_mm, point_std_mm : ndarray, shape (3,)
        Axis point and the standard deviations of its coordinates, mm.
    radius_mm, radius_std_mm : float
        Radius and its standard deviation, mm (``diameter_mm`` is twice the radius).
    """

    axis: NDArray = field(default_factory=_nan3)
    point_mm: NDArray = field(default_factory=_nan3)
    radius_mm: float = math.nan
    axis_std: NDArray = field(default_factory=_nan3)
    point_std_mm: NDArray = field(default_factory=_nan3)
    radius_std_mm: float = math.nan
    kind: str = "cylinder"
    _json_fields: ClassVar[str] = (
        "axis point_mm radius_mm diameter_mm axis_std point_std_mm radius_std_mm"
    )

    def signed_distance(self, points: ArrayLike) -> NDArray:
        """Radial deviation of ``(N, 3)`` points from the cylinder surface, positive outside."""
        return _radial_deviation(points, self.point_mm, self.axis, self.radius_mm)


@dataclass(frozen=True, kw_only=True, eq=False)
class CircleFit(Fit, _Round):
    """Circle in 3-D: centre, unit normal of its plane and radius.

    ``residuals_mm`` are the in-plane radial deviations (roundness); ``out_of_plane_mm`` the
    distances from the circle's plane; ``rms_mm`` is over the full 3-D distances to the circle.
    ``cov`` is over (normal tilt about ``u``, about ``v`` [rad], centre x, y, z [mm], radius).

    Attributes
    ----------
    center_mm, normal : ndarray, shape (3,)
        Centre (mm) and unit normal (largest-magnitude component positive).
    center_std_mm, normal_std : ndarray, shape (3,)
        Their components' standard deviations.
    radius_mm, radius_std_mm : float
        Radius and its standard deviation, mm (``diameter_mm`` is twice the radius).
    out_of_plane_mm : ndarray, shape (M,)
        Signed distances of the M inliers from the circle's plane, mm.
    """

    center_mm: NDArray = field(default_factory=_nan3)
    normal: NDArray = field(default_factory=_nan3)
    radius_mm: float = math.nan
    center_std_mm: NDArray = field(default_factory=_nan3)
    normal_std: NDArray = field(default_factory=_nan3)
    radius_std_mm: float = math.nan
    out_of_plane_mm: NDArray = field(default_factory=_empty)
    kind: str = "circle"
    _json_fields: ClassVar[str] = (
        "center_mm normal radius_mm diameter_mm center_std_mm normal_std radius_std_mm"
    )

    def signed_distance(self, points: ArrayLike) -> NDArray:
        """In-plane radial deviation of ``(N, 3)`` points, positive outside the circle."""
        return _radial_deviation(points, self.center_mm, self.normal, self.radius_mm)

    def distance(self, points: ArrayLike) -> NDArray:
        """Unsigned 3-D distance of ``(N, 3)`` points from the circle."""
        return circle_distance(
            np.asarray(points, dtype=np.float64), self.center_mm, self.normal, self.radius_mm
        )


@dataclass(frozen=True, kw_only=True, eq=False)
class LineFit(Fit):
    """Line through ``point_mm`` (the inliers' centroid) along unit ``direction``.

    ``residuals_mm`` are the (unsigned) distances from the line; ``cov`` is over (offset along
    ``u``, slope along ``u``, offset along ``v``, slope along ``v``) in a frame whose third axis
    is the direction.

    Attributes
    ----------
    point_mm, point_std_mm : ndarray, shape (3,)
        Point on the line and the standard deviations of its coordinates, mm.
    direction, direction_std : ndarray, shape (3,)
        Unit direction (largest-magnitude component positive) and its components' standard
        deviations.
    """

    point_mm: NDArray = field(default_factory=_nan3)
    direction: NDArray = field(default_factory=_nan3)
    point_std_mm: NDArray = field(default_factory=_nan3)
    direction_std: NDArray = field(default_factory=_nan3)
    kind: str = "line"
    _json_fields: ClassVar[str] = "point_mm direction point_std_mm direction_std"

    def signed_distance(self, points: ArrayLike) -> NDArray:
        """Distance of ``(N, 3)`` points from the line (never negative)."""
        return _radial_deviation(points, self.point_mm, self.direction, 0.0)
