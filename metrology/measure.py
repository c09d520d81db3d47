"""Run an inspection plan on a point cloud: fit each feature in its region, then evaluate the
measurements against their nominals and tolerances.

``measure_cloud(cloud, plan)`` returns a :class:`MeasurementReport`: the fits, the table of
Nominal / Actual / Deviation / Tolerance / Status rows, and per-point deviations for the
pictures. :mod:`metrology.report` writes it as JSON, CSV and a self-contained HTML page.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from metrology.budget import Uncertainty
from metrology.fits import (
    CircleFit,
    CylinderFit,
    Fit,
    LineFit,
    PlaneFit,
    SphereFit,
    fit_circle,
    fit_cylinder,
    fit_line,
    fit_plane,
    fit_sphere,
)
from metrology.plan import FeatureSpec, MeasurementSpec, Plan, load_plan
from scanner.core.conventions import check_points
from scanner.core.tolerance import STATUS_ERROR, RowCounts, ToleranceRow
from scanner.formats.clouds import read_points

__all__ = [
    "FeatureResult",
    "MeasurementReport",
    "MeasurementResult",
    "evaluate_measurement",
    "fit_feature",
    "measure_cloud",
]

log = logging.getLogger(__name__)

FORMAT = "scan-measurement/1"

#: RANSAC hypotheses for a feature with a nominal diameter must have a radius within this
#: fraction of the nominal radius.
NOMINAL_RADIUS_SLACK = 0.25


# --------------------------------------------------------------------------------------------
# Clouds
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------


@dataclass
class FeatureResult:
    """One feature's fit: the spec, the points its region held, and the fit (falsy if failed)."""

    spec: FeatureSpec
    fit: Fit
    region_indices: NDArray
    """Indices into the cloud of the points inside the region, ``(M,)``."""
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return bool(self.fit)

    @property
    def inlier_indices(self) -> NDArray:
        """Cloud indices of the points the fit used."""
        if not self.fit or self.fit.inliers.size != self.region_indices.size:
            return np.zeros(0, dtype=np.int64)
        return self.region_indices[self.fit.inliers]

    def to_json(self) -> dict[str, Any]:
        nominal = {k: v for k, v in dataclasses.asdict(self.spec.nominal).items() if v is not None}
        return {
            "name": self.spec.name,
            "kind": self.spec.kind,
            "region": self.spec.region.describe(),
            "nominal": nominal,
            "n_region_points": int(self.region_indices.size),
            "seconds": round(self.seconds, 4),
            "fit": self.fit.to_json(),
        }


@dataclass
class MeasurementResult:
    """One measurement: its spec and the table row (actual None when it could not be made)."""

    spec: MeasurementSpec
    row: ToleranceRow
    uncertainty: Uncertainty | None = None
    """``u``, ``U`` and the budget (:mod:`metrology.uncertainty`), when evaluated."""

    def to_json(self) -> dict[str, Any]:
        out = {"type": self.spec.type, "features": list(self.spec.features)}
        if self.spec.point_mm is not None:
            out["point_mm"] = list(self.spec.point_mm)
        out.update(self.row.to_json())
        if self.uncertainty is not None:
            out["uncertainty"] = self.uncertainty.to_json()
        return out


@dataclass
class MeasurementReport(RowCounts):
    """Everything a measurement run produced; ``to_json`` is the machine-readable twin of the
    HTML report."""

    plan: Plan
    features: list[FeatureResult]
    measurements: list[MeasurementResult]
    points_base: NDArray
    """The cloud, ``(N, 3)``, mm."""
    deviations_mm: NDArray
    """Per-point signed deviation from the feature that used the point, NaN elsewhere, ``(N,)``."""
    cloud_path: str | None = None
    plan_path: str | None = None
    provenance: dict[str, Any] = field(default_factory=dict)
    created: datetime = field(default_factory=lambda: datetime.now(timezone.utc))
    seconds: float = 0.0

    @property
    def rows(self) -> list[ToleranceRow]:
        return [m.row for m in self.measurements]

    def summary(self) -> str:
        """One line: ``PASS: 9 passed, 0 failed (plan 'x', 1234567 points)``."""
        extra = f", {self.n_not_proven} not proven" if self.n_not_proven else ""
        extra += f", {self.n_not_judged} not judged" if self.n_not_judged else ""
        failed_fits = [f.spec.name for f in self.features if not f.ok]
        fits = f"; failed fits: {', '.join(failed_fits)}" if failed_fits else ""
        return (
            f"{self.verdict.upper()}: {self.n_passed} passed, {self.n_failed} "
            f"failed{extra} (plan {self.plan.name!r}, {len(self.points_base)} points){fits}"
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "created_utc": self.created.astimezone(timezone.utc).isoformat(timespec="seconds"),
            "result": self.verdict,
            "summary": {
                "passed": self.n_passed,
                "failed": self.n_failed,
                "not_proven": self.n_not_proven,
                "not_judged": self.n_not_judged,
                "line": self.summary(),
            },
            "plan": {
                "name": self.plan.name,
                "path": self.plan_path,
                "cell": self.plan.cell,
                "description": self.plan.description,
                "decision_rule": self.plan.decision_rule,
            },
            "cloud": {
                "path": self.cloud_path,
                "n_points": len(self.points_base),
                "provenance": self.provenance,
            },
            "seconds": round(self.seconds, 3),
            "measurements": [m.to_json() for m in self.measurements],
            "features": [f.to_json() for f in self.features],
        }


# --------------------------------------------------------------------------------------------
# Fitting a feature
# --------------------------------------------------------------------------------------------


def _failed(kind: str, reason: str) -> Fit:
    cls = {
        "plane": PlaneFit,
        "sphere": SphereFit,
        "cylinder": CylinderFit,
        "circle": CircleFit,
        "line": LineFit,
    }[kind]
    return cls(reason=reason)


def _flip_plane(fit: PlaneFit) -> PlaneFit:
    return dataclasses.replace(
        fit,
        normal=-fit.normal,
        d_mm=-fit.d_mm,
        residuals_mm=-fit.residuals_mm,
    )


def fit_feature(
    spec: FeatureSpec, points_base: NDArray, threshold_mm: float | None, start: Fit | None = None
) -> Fit:
    """Fit one feature to the ``(M, 3)`` points of its region, guided by its nominal.

    A nominal diameter bounds the RANSAC radii (±25 %), a nominal axis seeds the cylinder,
    a nominal normal orients the plane's normal (and so the sign of its deviations). ``start``,
    an earlier fit of nearly the same points, starts a cylinder's least squares instead of
    its search for an axis (refits of moved points, :mod:`metrology.uncertainty`).
    """
    n = len(points_base)
    if n < spec.min_points:
        return _failed(
            spec.kind,
            f"too few points in the region: expected at least {spec.min_points}, got {n} "
            f"({spec.region.describe()})",
        )
    nom = spec.nominal
    radius_range = None
    if nom.diameter_mm is not None and threshold_mm is not None:
        r = nom.diameter_mm / 2
        radius_range = (r * (1 - NOMINAL_RADIUS_SLACK), r * (1 + NOMINAL_RADIUS_SLACK))
    kw: dict[str, Any] = {"seed": spec.seed}
    if spec.kind == "plane":
        fit: Fit = fit_plane(points_base, threshold_mm, min_zone=spec.min_zone, **kw)
        if fit and nom.normal is not None and float(fit.normal @ np.asarray(nom.normal)) < 0:
            fit = _flip_plane(fit)  # type: ignore[arg-type]
    elif spec.kind == "sphere":
        fit = fit_sphere(
            points_base, threshold_mm, min_zone=spec.min_zone, radius_range_mm=radius_range, **kw
        )
    elif spec.kind == "cylinder":
        fit = fit_cylinder(
            points_base,
            threshold_mm,
            radius_range_mm=radius_range,
            axis_hint=nom.axis,
            start=start if isinstance(start, CylinderFit) else None,
            **kw,
        )
    elif spec.kind == "circle":
        fit = fit_circle(points_base, threshold_mm, radius_range_mm=radius_range, **kw)
    else:
        fit = fit_line(points_base, threshold_mm, **kw)
    if fit and fit.n_inliers < spec.min_points:
        return _failed(
            spec.kind,
            f"too few inliers: expected at least {spec.min_points}, got {fit.n_inliers}",
        )
    return fit


# --------------------------------------------------------------------------------------------
# Measurements
# --------------------------------------------------------------------------------------------


def _point_of(fit: Fit) -> NDArray:
    return fit.center_mm  # type: ignore[attr-defined]


def _direction_of(fit: Fit) -> NDArray:
    if isinstance(fit, PlaneFit):
        return fit.normal
    if isinstance(fit, CylinderFit):
        return fit.axis
    return fit.direction  # type: ignore[attr-defined]


def _axis_distance(point: NDArray, origin: NDArray, direction: NDArray) -> float:
    q = point - origin
    return float(np.linalg.norm(q - (q @ direction) * direction))


def _distance(operands: list[Fit | NDArray]) -> tuple[float, str]:
    a, b = operands
    if isinstance(a, PlaneFit) and isinstance(b, PlaneFit):
        d1 = abs(float(a.signed_distance(b.centroid_mm[None])[0]))
        d2 = abs(float(b.signed_distance(a.centroid_mm[None])[0]))
        ang = math.degrees(math.acos(min(1.0, abs(float(a.normal @ b.normal)))))
        return 0.5 * (d1 + d2), f"mean of centroid distances; planes {ang:.3f} deg apart"
    # put the point operand first
    if not (isinstance(a, np.ndarray) or isinstance(a, SphereFit | CircleFit)):
        a, b = b, a
    pa = a if isinstance(a, np.ndarray) else _point_of(a)
    if isinstance(b, np.ndarray) or isinstance(b, SphereFit | CircleFit):
        pb = b if isinstance(b, np.ndarray) else _point_of(b)
        return float(np.linalg.norm(pa - pb)), "centre to centre"
    if isinstance(b, PlaneFit):
        return float(b.signed_distance(pa[None])[0]), "signed, along the plane normal"
    if isinstance(b, CylinderFit):
        return _axis_distance(pa, b.point_mm, b.axis), "to the cylinder axis"
    if isinstance(b, LineFit):
        return _axis_distance(pa, b.point_mm, b.direction), "to the line"
    raise ValueError(f"distance: unsupported operands {type(a).__name__}, {type(b).__name__}")


def _angle_deg(a: Fit, b: Fit) -> float:
    c = abs(float(_direction_of(a) @ _direction_of(b)))
    c = min(1.0, c)
    if isinstance(a, PlaneFit) != isinstance(b, PlaneFit):
        return math.degrees(math.asin(c))  # line (or axis) against a plane
    return math.degrees(math.acos(c))


def evaluate_measurement(spec: MeasurementSpec, fits: dict[str, Fit]) -> ToleranceRow:
    """The table row of one measurement from the fitted features (by name)."""
    lower, upper = spec.bounds
    row = {
        "name": spec.name,
        "nominal": spec.nominal_value,
        "lower": lower,
        "upper": upper,
        "unit": spec.unit,
    }
    used = [fits[name] for name in spec.features]
    failed = [name for name, f in zip(spec.features, used) if not f]
    if failed:
        return ToleranceRow(
            **row, actual=None, status=STATUS_ERROR, note=f"fit failed: {', '.join(failed)}"
        )
    note = ""
    if spec.type == "distance":
        operands: list[Fit | NDArray] = list(used)
        if spec.point_mm is not None:
            operands.append(np.asarray(spec.point_mm, dtype=np.float64))
        value, note = _distance(operands)
    elif spec.type == "diameter":
        value = 2.0 * float(used[0].radius_mm)  # type: ignore[attr-defined]
    elif spec.type in ("flatness", "form"):
        fit = used[0]
        if spec.method == "min_zone":
            if fit.min_zone_mm is None:  # measure_cloud turns min_zone on for these features
                raise ValueError(
                    f"{spec.name}: minimum-zone form needs the fit option min_zone = true on "
                    f"feature {spec.features[0]!r}"
                )
            value = fit.min_zone_mm
            note = "minimum zone"
        else:
            value = float(fit.range_mm)
            note = "range of least-squares residuals"
        note += f", RMS {fit.rms_mm * 1000:.1f} µm"
    elif spec.type == "angle":
        value = _angle_deg(used[0], used[1])
    else:  # pragma: no cover - the plan validates types
        raise ValueError(f"type: unknown measurement type {spec.type!r}")
    return ToleranceRow(**row, actual=float(value), note=note)


# --------------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------------


def _plan_needs_min_zone(plan: Plan) -> set[str]:
    return {m.features[0] for m in plan.measurements if m.method == "min_zone" and m.features}


def cloud_points(
    cloud: str | os.PathLike[str] | ArrayLike, provenance: dict[str, Any] | None = None
) -> tuple[NDArray, dict[str, Any], str | None]:
    """``(points, provenance, path)`` of a cloud given as a file or as ``(N, 3)`` points.

    ``provenance`` (where the cloud came from), when given, overrides the file's own record.
    """
    cloud_path = None
    prov: dict[str, Any] = {}
    if isinstance(cloud, str | os.PathLike):
        cloud_path = str(cloud)
        points, prov = read_points(cloud)
    else:
        points = check_points(cloud, min_count=1, name="cloud")
    if provenance:
        prov = dict(provenance)
    return points, prov, cloud_path


def measure_cloud(
    cloud: str | os.PathLike[str] | ArrayLike,
    plan: Plan | str | os.PathLike[str],
    *,
    provenance: dict[str, Any] | None = None,
) -> MeasurementReport:
    """Fit every feature of ``plan`` in ``cloud`` and evaluate its measurements.

    Parameters
    ----------
    cloud : path or array_like, shape (N, 3)
        A cloud file (see :func:`scanner.formats.clouds.read_points`) or base-frame points, mm.
    plan : Plan or path
        An inspection plan or its TOML file.
    provenance : dict, optional
        Where the cloud came from (overrides the record read from the file).

    Returns
    -------
    MeasurementReport
        Never raises for a feature that cannot be fitted: its measurements are reported with
        status ``error`` and the reason.

    Raises
    ------
    InputError, ConfigError
        Unreadable cloud or plan.
    """
    t0 = time.perf_counter()
    plan_path = None
    if not isinstance(plan, Plan):
        plan_path = str(plan)
        plan = load_plan(plan)
    points, prov, cloud_path = cloud_points(cloud, provenance)
    min_zone_features = _plan_needs_min_zone(plan)
    deviations = np.full(len(points), np.nan)
    features: list[FeatureResult] = []
    for spec in plan.features:
        t1 = time.perf_counter()
        if spec.name in min_zone_features and not spec.min_zone:
            spec = dataclasses.replace(spec, min_zone=True)
        idx = np.flatnonzero(spec.region.select(points))
        fit = fit_feature(spec, points[idx], plan.threshold_for(spec))
        result = FeatureResult(spec, fit, idx, time.perf_counter() - t1)
        if fit:
            used = result.inlier_indices
            deviations[used] = fit.residuals_mm
            log.info(
                "%s: %s fit on %d of %d region points, RMS %.4f mm",
                spec.name, spec.kind, fit.n_inliers, idx.size, fit.rms_mm,
            )  # fmt: skip
        else:
            log.warning("%s: %s fit failed: %s", spec.name, spec.kind, fit.reason)
        features.append(result)
    fits = {f.spec.name: f.fit for f in features}
    measurements = [
        MeasurementResult(
            m, dataclasses.replace(evaluate_measurement(m, fits), rule=plan.decision_rule)
        )
        for m in plan.measurements
    ]
    return MeasurementReport(
        plan=plan,
        features=features,
        measurements=measurements,
        points_base=points,
        deviations_mm=deviations,
        cloud_path=cloud_path,
        plan_path=plan_path,
        provenance=prov,
        seconds=time.perf_counter() - t0,
    )
