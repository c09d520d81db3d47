"""Inspection plans: which features to fit where, and what to measure between them.

A plan is a TOML file (``configs/plans/*.toml``) loaded into frozen dataclasses and validated
once, at the edge; errors name the file, the line and the key::

    configs/plans/paper_sweep.toml, line 31, measurements[2].features: unknown feature
    'sphere_3' (expected one of sphere_1, sphere_2, plate, table)

Layout (all coordinates in the base frame, mm)::

    name = "sphere bar and plate"
    threshold_mm = 0.2                  # default RANSAC inlier distance of the fits
    decision_rule = "simple"            # or "guarded": pass only inside tolerance - U
    instrument = { probing_size_mm = 0.06, sphere_spacing_mm = 0.025 }  # verified PS, SD

    [[features]]
    name = "sphere_1"
    kind = "sphere"                     # plane | sphere | cylinder | circle | line
    region = { seed_mm = [650, -45, 45], radius_mm = 16 }   # or box_min_mm / box_max_mm
    nominal = { center_mm = [650, -45, 45], diameter_mm = 25.4 }
    # optional fit options: threshold_mm, min_points, min_zone, seed

    [[measurements]]
    name = "sphere spacing"
    type = "distance"                   # distance | diameter | flatness | form | angle
    features = ["sphere_1", "sphere_2"]
    nominal = 100.0
    tolerance = 0.1                     # symmetric, or upper = / lower = (deviations)

Distances by kinds: sphere/circle centres are points, so point-point is the centre distance;
point-plane the distance from the centre to the plane (signed along the plane's normal, which
follows the nominal normal when one is given); plane-plane the mean distance of each plane's
centroid from the other; point-line and point-cylinder the distance to the axis. A measurement
may also name one feature and a literal ``point_mm``. ``diameter`` takes a sphere, cylinder or
circle; ``flatness`` a plane; ``form`` any feature (range of its residuals: sphericity,
cylindricity, roundness, straightness); ``angle`` two of plane (normal), line, cylinder
(axis), in degrees, between 0 and 90 for planes and lines alike.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Literal, TypeVar

import numpy as np
from numpy.typing import NDArray

from scanner.core.config import load_config
from scanner.core.tolerance import DECISION_RULES, DecisionRule

__all__ = [
    "FEATURE_KINDS",
    "MEASUREMENT_TYPES",
    "FeatureSpec",
    "MeasurementSpec",
    "Nominal",
    "Plan",
    "Region",
    "load_plan",
]

FeatureKind = Literal["plane", "sphere", "cylinder", "circle", "line"]
MeasurementType = Literal["distance", "diameter", "flatness", "form", "angle"]
FEATURE_KINDS: tuple[str, ...] = ("plane", "sphere", "cylinder", "circle", "line")
MEASUREMENT_TYPES: tuple[str, ...] = ("distance", "diameter", "flatness", "form", "angle")

Vec3 = tuple[float, float, float]
T = TypeVar("T")

#: Kinds whose feature is a point for distances (their centre).
POINT_KINDS = ("sphere", "circle")
#: Kinds that carry a direction for angles (plane normal, line direction, cylinder axis).
DIRECTION_KINDS = ("plane", "line", "cylinder")
#: Kinds that have a diameter.
DIAMETER_KINDS = ("sphere", "cylinder", "circle")


#: No length a plan names is larger than this (mm): a workspace bound, not a tolerance.
LENGTH_LIMIT_MM = 1.0e5


def _finite(values: tuple[float, ...] | None, where: str) -> None:
    if values is not None and not all(math.isfinite(v) for v in values):
        raise ValueError(f"{where}: expected finite numbers, got {list(values)}")


def _plausible(value: float | None, where: str) -> None:
    """A finite value within :data:`LENGTH_LIMIT_MM` (angles too stay far below it)."""
    if value is not None and not (math.isfinite(value) and abs(value) <= LENGTH_LIMIT_MM):
        raise ValueError(
            f"{where}: expected a finite number within ±{LENGTH_LIMIT_MM:g}, got {value}"
        )


@dataclass(frozen=True)
class Region:
    """Where a feature's points are, in the base frame: an axis-aligned box
    (``box_min_mm``, ``box_max_mm``) or a ball (``seed_mm`` and ``radius_mm``)."""

    box_min_mm: Vec3 | None = None
    box_max_mm: Vec3 | None = None
    seed_mm: Vec3 | None = None
    radius_mm: float | None = None

    def __post_init__(self) -> None:
        box = self.box_min_mm is not None or self.box_max_mm is not None
        ball = self.seed_mm is not None or self.radius_mm is not None
        if box == ball:
            raise ValueError(
                "expected either box_min_mm and box_max_mm or seed_mm and radius_mm, "
                f"got {'both' if box else 'neither'}"
            )
        if box:
            if self.box_min_mm is None or self.box_max_mm is None:
                missing = "box_max_mm" if self.box_max_mm is None else "box_min_mm"
                raise ValueError(f"{missing}: missing required key (a box needs both)")
            _finite(self.box_min_mm, "box_min_mm")
            _finite(self.box_max_mm, "box_max_mm")
            if not all(lo < hi for lo, hi in zip(self.box_min_mm, self.box_max_mm)):
                raise ValueError(
                    f"box_max_mm: expected every coordinate above box_min_mm "
                    f"{list(self.box_min_mm)}, got {list(self.box_max_mm)}"
                )
        else:
            if self.seed_mm is None:
                raise ValueError("seed_mm: missing required key (a ball needs it)")
            if self.radius_mm is None:
                raise ValueError("radius_mm: missing required key (a ball needs it)")
            _finite(self.seed_mm, "seed_mm")
            if not (math.isfinite(self.radius_mm) and self.radius_mm > 0):
                raise ValueError(f"radius_mm: expected a positive number, got {self.radius_mm}")

    def select(self, points_base: NDArray) -> NDArray:
        """Boolean mask ``(N,)`` of the ``(N, 3)`` base-frame points inside the region."""
        p = np.asarray(points_base, dtype=np.float64)
        if self.seed_mm is not None:
            d = p - np.asarray(self.seed_mm)
            return np.einsum("ij,ij->i", d, d) <= float(self.radius_mm) ** 2  # type: ignore[arg-type]
        lo, hi = np.asarray(self.box_min_mm), np.asarray(self.box_max_mm)
        return np.all((p >= lo) & (p <= hi), axis=1)

    def describe(self) -> str:
        if self.seed_mm is not None:
            return f"ball r={self.radius_mm:g} mm at {list(self.seed_mm)}"
        return f"box {list(self.box_min_mm or ())} .. {list(self.box_max_mm or ())}"


@dataclass(frozen=True)
class Nominal:
    """Optional nominal geometry of a feature; it guides the fit (RANSAC radius range, the
    cylinder's starting axis, the sign of a plane's normal) and is reported beside it."""

    center_mm: Vec3 | None = None
    diameter_mm: float | None = None
    normal: Vec3 | None = None
    axis: Vec3 | None = None

    def __post_init__(self) -> None:
        _finite(self.center_mm, "center_mm")
        if self.diameter_mm is not None and not (
            math.isfinite(self.diameter_mm) and self.diameter_mm > 0
        ):
            raise ValueError(f"diameter_mm: expected a positive number, got {self.diameter_mm}")
        for key in ("normal", "axis"):
            v = getattr(self, key)
            if v is not None:
                _finite(v, f"{key}")
                if float(np.linalg.norm(v)) < 1e-9:
                    raise ValueError(f"{key}: expected a non-zero vector, got {list(v)}")


@dataclass(frozen=True)
class FeatureSpec:
    """One feature to fit: its name, kind, region, nominal and fit options."""

    name: str
    kind: FeatureKind
    region: Region
    nominal: Nominal = field(default_factory=Nominal)
    threshold_mm: float | None = None
    """RANSAC inlier distance; the plan's ``threshold_mm`` when omitted; 0 turns RANSAC off."""
    min_points: int = 20
    min_zone: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.name.strip():
            raise ValueError("name: expected a non-empty string")
        if self.threshold_mm is not None and not (
            math.isfinite(self.threshold_mm) and self.threshold_mm >= 0
        ):
            raise ValueError(f"threshold_mm: expected a number >= 0, got {self.threshold_mm}")
        if self.min_points < 3:
            raise ValueError(f"min_points: expected at least 3, got {self.min_points}")
        if self.nominal.diameter_mm is not None and self.kind not in DIAMETER_KINDS:
            raise ValueError(f"nominal.diameter_mm: a {self.kind} has no diameter")


@dataclass(frozen=True)
class MeasurementSpec:
    """One characteristic to report: what, between which features, nominal and tolerance.

    ``tolerance`` is symmetric (±); ``lower``/``upper`` give an asymmetric band as permitted
    deviations from nominal (``lower <= actual - nominal <= upper``); for ``flatness`` and
    ``form`` the nominal is 0 and ``tolerance`` means ``upper`` (a form error is never
    negative).
    """

    name: str
    type: MeasurementType
    features: tuple[str, ...]
    nominal: float | None = None
    tolerance: float | None = None
    lower: float | None = None
    upper: float | None = None
    point_mm: Vec3 | None = None
    method: Literal["lsq", "min_zone"] = "lsq"
    """For ``flatness`` and sphere ``form``: least-squares range or minimum zone."""

    def __post_init__(self) -> None:
        if not self.name.strip():
            raise ValueError("name: expected a non-empty string")
        n_ref = len(self.features) + (self.point_mm is not None)
        need = {"distance": 2, "angle": 2, "diameter": 1, "flatness": 1, "form": 1}[self.type]
        if n_ref != need or not self.features:
            got = f"{len(self.features)} feature(s)" + (" and point_mm" if self.point_mm else "")
            raise ValueError(
                f"features: a {self.type} takes {need} operand(s) "
                f"({'two features, or one and point_mm' if need == 2 else 'one feature'}), "
                f"got {got}"
            )
        _finite(self.point_mm, "point_mm")
        for key in ("nominal", "tolerance", "lower", "upper"):
            _plausible(getattr(self, key), key)
        if self.tolerance is not None and (self.lower is not None or self.upper is not None):
            raise ValueError("tolerance: expected either tolerance or lower/upper, got both")
        if self.tolerance is not None and not (self.tolerance >= 0):
            raise ValueError(f"tolerance: expected a number >= 0, got {self.tolerance}")
        if self.lower is not None and self.upper is not None and self.lower > self.upper:
            raise ValueError(f"upper: expected upper >= lower ({self.lower}), got {self.upper}")
        if self.type in ("flatness", "form") and self.nominal not in (None, 0.0):
            raise ValueError(f"nominal: a {self.type} has nominal 0, got {self.nominal}")

    @property
    def unit(self) -> str:
        return "deg" if self.type == "angle" else "mm"

    @property
    def nominal_value(self) -> float | None:
        return 0.0 if self.type in ("flatness", "form") else self.nominal

    @property
    def bounds(self) -> tuple[float | None, float | None]:
        """Permitted deviation ``(lower, upper)`` from nominal; None is unbounded."""
        if self.tolerance is not None:
            if self.type in ("flatness", "form"):
                return None, self.tolerance
            return -self.tolerance, self.tolerance
        return self.lower, self.upper


@dataclass(frozen=True)
class InstrumentSpec:
    """The sensor's own systematic errors as its verification measured them (VDI/VDE 2634-2
    acceptance, ``scanner acceptance``): the largest size error of a sphere (PS) and of a
    sphere spacing (SD), mm. They enter each diameter's and each centre distance's budget as
    type B contributions (rectangular, ``u = value / sqrt(3)``): the stripe's biases on
    curved surfaces that no single scan can show. None: not known (and named as missing)."""

    probing_size_mm: float | None = None
    sphere_spacing_mm: float | None = None

    def __post_init__(self) -> None:
        for key in ("probing_size_mm", "sphere_spacing_mm"):
            v = getattr(self, key)
            if v is not None and not (math.isfinite(v) and v >= 0):
                raise ValueError(f"instrument.{key}: expected a number >= 0, got {v}")


@dataclass(frozen=True)
class Plan:
    """An inspection plan: features to fit and measurements to report."""

    name: str
    features: tuple[FeatureSpec, ...]
    measurements: tuple[MeasurementSpec, ...] = ()
    description: str = ""
    cell: str = ""
    """The virtual or real cell the plan's coordinates belong to (informational)."""
    threshold_mm: float = 0.2
    decision_rule: DecisionRule = "simple"
    """How each measurement's status follows from its value, tolerance and uncertainty U
    (:data:`scanner.core.tolerance.DecisionRule`): ``simple`` or ``guarded`` acceptance."""
    instrument: InstrumentSpec = field(default_factory=InstrumentSpec)
    """The sensor's verified systematic errors, for the uncertainty budgets."""

    def __post_init__(self) -> None:
        if self.decision_rule not in DECISION_RULES:
            raise ValueError(
                f"decision_rule: expected one of {', '.join(DECISION_RULES)}, "
                f"got {self.decision_rule!r}"
            )
        if not self.features:
            raise ValueError("features: expected at least one [[features]] table")
        if not (math.isfinite(self.threshold_mm) and self.threshold_mm >= 0):
            raise ValueError(f"threshold_mm: expected a number >= 0, got {self.threshold_mm}")
        kinds: dict[str, str] = {}
        for i, f in enumerate(self.features):
            if f.name in kinds:
                raise ValueError(f"features[{i}].name: duplicate feature name {f.name!r}")
            kinds[f.name] = f.kind
        seen: set[str] = set()
        for i, m in enumerate(self.measurements):
            where = f"measurements[{i}]"
            if m.name in seen:
                raise ValueError(f"{where}.name: duplicate measurement name {m.name!r}")
            seen.add(m.name)
            for ref in m.features:
                if ref not in kinds:
                    raise ValueError(
                        f"{where}.features: unknown feature {ref!r} "
                        f"(expected one of {', '.join(kinds)})"
                    )
            _check_kinds(m, [kinds[r] for r in m.features], where)

    def feature(self, name: str) -> FeatureSpec:
        for f in self.features:
            if f.name == name:
                return f
        raise KeyError(name)

    def threshold_for(self, feature: FeatureSpec) -> float | None:
        """RANSAC threshold of a feature: its own, else the plan's; None when 0 (off)."""
        t = self.threshold_mm if feature.threshold_mm is None else feature.threshold_mm
        return t if t > 0 else None


def _check_kinds(m: MeasurementSpec, kinds: list[str], where: str) -> None:
    bad = None
    if m.type == "diameter" and kinds[0] not in DIAMETER_KINDS:
        bad = f"a diameter needs a sphere, cylinder or circle, got a {kinds[0]}"
    elif m.type == "flatness" and kinds[0] != "plane":
        bad = f"flatness needs a plane, got a {kinds[0]}"
    elif m.type == "form" and m.method == "min_zone" and kinds[0] not in ("plane", "sphere"):
        bad = f"minimum-zone form is available for planes and spheres, got a {kinds[0]}"
    elif m.type == "flatness" or m.type == "form":
        pass
    elif m.type == "angle":
        if m.point_mm is not None or any(k not in DIRECTION_KINDS for k in kinds):
            bad = f"an angle needs two of plane, line, cylinder, got {' and '.join(kinds)}"
    elif m.type == "distance":
        ops = kinds + (["point"] if m.point_mm is not None else [])
        pts = sum(k in (*POINT_KINDS, "point") for k in ops)
        if pts == 2 or (pts == 1 and any(k in ("plane", "line", "cylinder") for k in ops)):
            pass
        elif ops == ["plane", "plane"]:
            pass
        else:
            bad = (
                f"a distance is defined point-point, point-plane, point-line/cylinder or "
                f"plane-plane (sphere and circle centres are points), got {' and '.join(ops)}"
            )
    if m.method == "min_zone" and m.type not in ("flatness", "form"):
        bad = f"method min_zone applies to flatness and form, not {m.type}"
    if bad:
        raise ValueError(f"{where}.features: {bad}")


def load_plan(path: str | os.PathLike[str]) -> Plan:
    """Load and validate an inspection plan.

    Raises
    ------
    ConfigError
        ``"<file>, line <n>: <key>: <reason>"`` for any missing, unknown or wrong value, an
        unknown feature name in a measurement, or a measurement the kinds do not support.
    InputError
        The file is missing or not TOML.
    """
    return load_config(Plan, path)
