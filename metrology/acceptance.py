"""Acceptance test of the scanner after VDI/VDE 2634 Part 2 (optical 3-D measuring systems).

From one scan of a sphere bar (two spheres of calibrated diameters at a calibrated centre
distance) and a flat plate, the four characteristics of the guideline:

``PF`` probing error, form
    Range of the radial residuals ``Rmax - Rmin`` of a least-squares sphere fit, per sphere.
``PS`` probing error, size
    Measured minus calibrated diameter, per sphere.
``SD`` sphere-spacing error
    Measured minus calibrated centre distance.
``F``  flatness measurement error
    Range of the signed plane residuals of a least-squares plane fit.

Each is compared with its maximum permissible error (MPE): ``PF <= MPE_PF``,
``|PS| <= MPE_PS``, ``|SD| <= MPE_SD``, ``F <= MPE_F``. As the guideline allows, a small
fraction of points (``outlier_fraction``, 0.3 % by default) with the largest residuals is
excluded before the final fit. The artefacts are first isolated in their regions by RANSAC
(the table, the bar and the plate's edges are not part of them).

The guideline's full test repeats the sphere-bar scan in several positions in the measuring
volume and takes the worst value: :func:`run_acceptance` evaluates one scan,
:func:`full_acceptance` combines the scans (each characteristic decided by its worst scan).

Specification (``configs/plans/acceptance_*.toml``)::

    name = "VDI/VDE 2634-2 acceptance"
    calibrated_distance_mm = 100.0
    [[spheres]]
    name = "sphere_1"
    region = { seed_mm = [650, -45, 45], radius_mm = 17 }
    calibrated_diameter_mm = 25.4
    [[spheres]]  ...
    [plate]
    region = { seed_mm = [700, 55, 12], radius_mm = 27 }
    [mpe]
    probing_form_mm = 0.1
    probing_size_mm = 0.05
    sphere_spacing_mm = 0.1
    flatness_mm = 0.1
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from metrology.fits import Fit, PlaneFit, SphereFit, fit_plane, fit_sphere
from metrology.measure import cloud_points
from metrology.plan import Region
from scanner.core.config import load_config
from scanner.core.tolerance import STATUS_ERROR, STATUS_FAIL, STATUS_PASS, RowCounts, ToleranceRow

__all__ = [
    "MPE",
    "AcceptanceResult",
    "AcceptanceSpec",
    "Characteristic",
    "FullAcceptance",
    "PlateArtefact",
    "SphereArtefact",
    "full_acceptance",
    "load_acceptance_spec",
    "run_acceptance",
]

log = logging.getLogger(__name__)

FORMAT = "scan-acceptance/1"
STANDARD = "VDI/VDE 2634 Part 2"


def _positive(value: float, key: str) -> None:
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{key}: expected a positive number, got {value}")


@dataclass(frozen=True)
class SphereArtefact:
    """One sphere of the bar: where it is and its calibrated diameter."""

    name: str
    region: Region
    calibrated_diameter_mm: float

    def __post_init__(self) -> None:
        _positive(self.calibrated_diameter_mm, "calibrated_diameter_mm")


@dataclass(frozen=True)
class PlateArtefact:
    """The flatness standard: where it is (the region should stay clear of its edges)."""

    region: Region
    name: str = "plate"
    calibrated_flatness_mm: float = 0.0
    """The plate's own calibrated form (reported, not subtracted)."""


@dataclass(frozen=True)
class MPE:
    """Maximum permissible errors, mm."""

    probing_form_mm: float
    probing_size_mm: float
    sphere_spacing_mm: float
    flatness_mm: float

    def __post_init__(self) -> None:
        for key in ("probing_form_mm", "probing_size_mm", "sphere_spacing_mm", "flatness_mm"):
            _positive(getattr(self, key), key)


@dataclass(frozen=True)
class AcceptanceSpec:
    """What the acceptance test measures and what it allows."""

    name: str
    spheres: tuple[SphereArtefact, ...]
    calibrated_distance_mm: float
    plate: PlateArtefact
    mpe: MPE
    description: str = ""
    cell: str = ""
    threshold_mm: float = 0.3
    """RANSAC inlier distance that isolates each artefact in its region."""
    outlier_fraction: float = 0.003
    """Share of points with the largest residuals excluded before the final fit (0.3 %)."""
    min_points: int = 100

    def __post_init__(self) -> None:
        if len(self.spheres) != 2:
            raise ValueError(
                f"spheres: expected 2 [[spheres]] tables (a sphere bar), got {len(self.spheres)}"
            )
        if self.spheres[0].name == self.spheres[1].name:
            raise ValueError(f"spheres[1].name: duplicate sphere name {self.spheres[1].name!r}")
        _positive(self.calibrated_distance_mm, "calibrated_distance_mm")
        _positive(self.threshold_mm, "threshold_mm")
        if not (0.0 <= self.outlier_fraction < 0.1):
            raise ValueError(
                f"outlier_fraction: expected 0 <= fraction < 0.1 (the guideline's 0.003), "
                f"got {self.outlier_fraction}"
            )
        if self.min_points < 10:
            raise ValueError(f"min_points: expected at least 10, got {self.min_points}")


def load_acceptance_spec(path: str | os.PathLike[str]) -> AcceptanceSpec:
    """Load and validate an acceptance specification (errors name file, line and key)."""
    return load_config(AcceptanceSpec, path)


@dataclass
class Characteristic:
    """One evaluated characteristic (PF, PS, SD or F) of one artefact."""

    symbol: str
    artefact: str
    value_mm: float | None
    mpe_mm: float
    row: ToleranceRow

    @property
    def passed(self) -> bool:
        return self.row.final_status == STATUS_PASS

    def to_json(self) -> dict[str, Any]:
        return {
            "symbol": self.symbol,
            "artefact": self.artefact,
            "value_mm": self.value_mm,
            "mpe_mm": self.mpe_mm,
            "status": self.row.final_status,
            "note": self.row.note,
        }


class _Judged(RowCounts):
    """What one scan's result and a full test share: the characteristics and their verdict."""

    characteristics: list[Characteristic]

    @property
    def rows(self) -> list[ToleranceRow]:
        return [c.row for c in self.characteristics]

    def worst(self, symbol: str) -> float | None:
        """The decisive value of a characteristic: the largest PF or F, the PS or SD of the
        largest magnitude; None if it could not be evaluated."""
        vals = [c.value_mm for c in self.characteristics if c.symbol == symbol]
        if not vals or any(v is None for v in vals):
            return None
        return max(vals, key=lambda v: abs(v))  # type: ignore[arg-type, return-value]

    def summary(self) -> str:
        parts = []
        for sym in ("PF", "PS", "SD", "F"):
            v = self.worst(sym)
            parts.append(f"{sym} {'n/a' if v is None else f'{v * 1000:+.1f} µm'}")
        return (
            f"{'PASS' if self.passed else 'FAIL'}: {self.n_passed} passed, {self.n_failed} "
            f"failed ({', '.join(parts)})"
        )

    def _verdict_json(
        self, spec: AcceptanceSpec, spec_path: str | None, created: datetime
    ) -> dict[str, Any]:
        """The JSON's head: format, verdict, specification and decisive values."""
        return {
            "format": FORMAT,
            "standard": STANDARD,
            "created_utc": created.astimezone(timezone.utc).isoformat(timespec="seconds"),
            "result": "pass" if self.passed else "fail",
            "summary": {"passed": self.n_passed, "failed": self.n_failed, "line": self.summary()},
            "spec": _spec_json(spec, spec_path),
            "values_mm": {sym: self.worst(sym) for sym in ("PF", "PS", "SD", "F")},
        }


def _spec_json(spec: AcceptanceSpec, spec_path: str | None) -> dict[str, Any]:
    mpe = spec.mpe
    return {
        "name": spec.name,
        "path": spec_path,
        "cell": spec.cell,
        "calibrated_distance_mm": spec.calibrated_distance_mm,
        "calibrated_diameters_mm": {s.name: s.calibrated_diameter_mm for s in spec.spheres},
        "outlier_fraction": spec.outlier_fraction,
        "mpe_mm": {
            "PF": mpe.probing_form_mm,
            "PS": mpe.probing_size_mm,
            "SD": mpe.sphere_spacing_mm,
            "F": mpe.flatness_mm,
        },
    }


@dataclass
class AcceptanceResult(_Judged):
    """Characteristics, fits and the per-point deviations of one acceptance scan."""

    spec: AcceptanceSpec
    characteristics: list[Characteristic]
    fits: dict[str, Fit]
    points_base: NDArray
    deviations_mm: NDArray
    n_excluded: dict[str, int]
    cloud_path: str | None = None
    spec_path: str | None = None
    provenance: dict[str, Any] = field(default_factory=dict)
    created: datetime = field(default_factory=lambda: datetime.now(timezone.utc))
    seconds: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return self._verdict_json(self.spec, self.spec_path, self.created) | {
            "characteristics": [c.to_json() for c in self.characteristics],
            "rows": [r.to_json() for r in self.rows],
            "fits": {name: f.to_json() for name, f in self.fits.items()},
            "excluded_points": self.n_excluded,
            "cloud": {
                "path": self.cloud_path,
                "n_points": len(self.points_base),
                "provenance": self.provenance,
            },
            "seconds": round(self.seconds, 3),
        }


@dataclass
class FullAcceptance(_Judged):
    """The guideline's full test: the sphere bar and plate scanned in several positions.

    ``characteristics`` holds each characteristic's decisive row, from the scan where it is
    worst (a scan where it could not be evaluated decides it), its note naming that scan
    (counted from 1); ``decided_by[i]`` is that scan's index into ``scans`` (from 0, the
    JSON's ``scan_index``).
    """

    scans: list[AcceptanceResult]
    characteristics: list[Characteristic]
    decided_by: list[int]
    created: datetime = field(default_factory=lambda: datetime.now(timezone.utc))

    @property
    def spec(self) -> AcceptanceSpec:
        return self.scans[0].spec

    @property
    def seconds(self) -> float:
        return sum(r.seconds for r in self.scans)

    def to_json(self) -> dict[str, Any]:
        return self._verdict_json(self.spec, self.scans[0].spec_path, self.created) | {
            "characteristics": [
                c.to_json() | {"scan_index": k, "cloud": self.scans[k].cloud_path}
                for c, k in zip(self.characteristics, self.decided_by)
            ],
            "rows": [r.to_json() for r in self.rows],
            "scans": [r.to_json() for r in self.scans],
            "seconds": round(self.seconds, 3),
        }


def _severity(c: Characteristic) -> float:
    """How strongly a scan's row of a characteristic decides it: an error above all."""
    return math.inf if c.value_mm is None else abs(c.value_mm)


def full_acceptance(scans: Sequence[AcceptanceResult]) -> FullAcceptance:
    """Combine the scans of one acceptance test (positions of the sphere bar and plate).

    Parameters
    ----------
    scans : sequence of AcceptanceResult
        One per scan, all judged against the same specification.

    Returns
    -------
    FullAcceptance
        Each characteristic (PF and PS per sphere, SD, F) from the scan where its value has
        the largest magnitude; a scan where it could not be evaluated decides it (error).

    Raises
    ------
    ValueError
        No scans, or scans judged against different specifications.
    """
    if not scans:
        raise ValueError("scans: expected at least one acceptance scan, got none")
    for k, r in enumerate(scans[1:], 1):
        if r.spec != scans[0].spec:
            raise ValueError(
                f"scans[{k}]: expected the specification of scans[0] ({scans[0].spec.name!r}), "
                f"got {r.spec.name!r}"
            )
    chars, decided = [], []
    for i in range(len(scans[0].characteristics)):
        k = max(range(len(scans)), key=lambda j: _severity(scans[j].characteristics[i]))
        c = scans[k].characteristics[i]
        cloud = Path(scans[k].cloud_path).name if scans[k].cloud_path else "points in memory"
        note = f"scan {k + 1} of {len(scans)}, {cloud}" + (f": {c.row.note}" if c.row.note else "")
        chars.append(replace(c, row=replace(c.row, note=note)))
        decided.append(k)
    return FullAcceptance(scans=list(scans), characteristics=chars, decided_by=decided)


def _trim_and_refit(
    points: NDArray, first: Fit, fraction: float, refit: Any
) -> tuple[Fit, NDArray, int]:
    """Drop the ``fraction`` of inliers with the largest |residual| and fit again without
    RANSAC. Returns the fit, the kept mask over ``points`` and the number dropped."""
    mask = first.inliers.copy()
    n_drop = math.floor(fraction * int(mask.sum()))
    if n_drop > 0:
        inl = np.flatnonzero(mask)
        worst = np.argsort(np.abs(first.residuals_mm))[-n_drop:]
        mask[inl[worst]] = False
    fit = refit(points[mask])
    return fit, mask, n_drop


def _fit_region(
    points: NDArray,
    region: Region,
    spec: AcceptanceSpec,
    failed: Callable[..., Fit],
    fit: Callable[..., Fit],
    **kwargs: Any,
) -> tuple[Fit, int]:
    """Fit an artefact to its region's points, then drop the spec's outlier fraction and refit.

    Returns the fit (its ``inliers`` a mask over ``points``) and how many points were
    dropped; a region with fewer than ``spec.min_points`` gives ``failed(reason=...)``.
    """
    if len(points) < spec.min_points:
        reason = (
            f"too few points in the region: expected at least {spec.min_points}, "
            f"got {len(points)} ({region.describe()})"
        )
        return failed(reason=reason), 0
    first = fit(points, spec.threshold_mm, **kwargs)
    if not first:
        return first, 0
    refit, mask, n_drop = _trim_and_refit(points, first, spec.outlier_fraction, fit)
    return (_with_mask(refit, mask) if refit else refit), n_drop


def run_acceptance(
    cloud: str | os.PathLike[str] | ArrayLike,
    spec: AcceptanceSpec | str | os.PathLike[str],
    *,
    provenance: dict[str, Any] | None = None,
) -> AcceptanceResult:
    """Evaluate PF, PS, SD and F on one scan of the sphere bar and the plate.

    Parameters
    ----------
    cloud : path or array_like, shape (N, 3)
        The scan, base frame, mm.
    spec : AcceptanceSpec or path
        Regions, calibrated values and MPEs.

    Returns
    -------
    AcceptanceResult
        A characteristic whose artefact cannot be fitted is reported with status ``error``
        (it fails the test) and the reason; nothing raises for it.
    """
    t0 = time.perf_counter()
    spec_path = None
    if not isinstance(spec, AcceptanceSpec):
        spec_path = str(spec)
        spec = load_acceptance_spec(spec)
    points, prov, cloud_path = cloud_points(cloud, provenance)
    mpe = spec.mpe
    deviations = np.full(len(points), np.nan)
    fits: dict[str, Fit] = {}
    excluded: dict[str, int] = {}
    chars: list[Characteristic] = []

    def place(name: str, idx: NDArray, fit: Fit) -> None:
        fits[name] = fit
        if fit and fit.inliers.size == idx.size:
            deviations[idx[fit.inliers]] = fit.residuals_mm

    # Spheres: PF and PS
    for s in spec.spheres:
        idx = np.flatnonzero(s.region.select(points))
        r_nom = s.calibrated_diameter_mm / 2
        fit, excluded[s.name] = _fit_region(
            points[idx], s.region, spec, SphereFit, fit_sphere,
            radius_range_mm=(0.75 * r_nom, 1.25 * r_nom),
        )  # fmt: skip
        if fit and fit.n_inliers < spec.min_points:
            fit = SphereFit(
                reason=f"too few sphere points: expected {spec.min_points}, got {fit.n_inliers}"
            )
        place(s.name, idx, fit)
        pf = float(fit.range_mm) if fit else None
        ps = 2 * float(fit.radius_mm) - s.calibrated_diameter_mm if fit else None  # type: ignore[attr-defined]
        note = "" if fit else f"sphere fit failed: {fit.reason}"
        chars.append(
            Characteristic("PF", s.name, pf, mpe.probing_form_mm, ToleranceRow(
                f"PF probing error, form — {s.name}", 0.0, pf, None, mpe.probing_form_mm,
                status=None if fit else STATUS_ERROR,
                note=note or f"Rmax - Rmin of {fit.n_inliers} points, RMS {fit.rms_mm * 1000:.1f} µm",
            ))
        )  # fmt: skip
        diameter = 2 * float(fit.radius_mm) if fit else None  # type: ignore[attr-defined]
        chars.append(
            Characteristic("PS", s.name, ps, mpe.probing_size_mm, ToleranceRow(
                f"PS probing error, size — {s.name} diameter", s.calibrated_diameter_mm,
                diameter, -mpe.probing_size_mm, mpe.probing_size_mm,
                status=None if fit else STATUS_ERROR,
                note=note or "measured minus calibrated diameter",
            ))
        )  # fmt: skip

    # Sphere spacing: SD
    a, b = (fits[s.name] for s in spec.spheres)
    if a and b:
        dist = float(np.linalg.norm(a.center_mm - b.center_mm))  # type: ignore[attr-defined]
        sd: float | None = dist - spec.calibrated_distance_mm
        note = "measured minus calibrated centre distance"
        status = None
    else:
        dist, sd, status = None, None, STATUS_ERROR  # type: ignore[assignment]
        note = "a sphere fit failed"
    chars.append(
        Characteristic("SD", f"{spec.spheres[0].name}-{spec.spheres[1].name}", sd,
                       mpe.sphere_spacing_mm, ToleranceRow(
            "SD sphere-spacing error", spec.calibrated_distance_mm, dist,
            -mpe.sphere_spacing_mm, mpe.sphere_spacing_mm, status=status, note=note,
        ))
    )  # fmt: skip

    # Plate: F
    plate = spec.plate
    idx = np.flatnonzero(plate.region.select(points))
    pfit, excluded[plate.name] = _fit_region(points[idx], plate.region, spec, PlaneFit, fit_plane)
    place(plate.name, idx, pfit)
    f_val = float(pfit.range_mm) if pfit else None
    chars.append(
        Characteristic("F", plate.name, f_val, mpe.flatness_mm, ToleranceRow(
            f"F flatness measurement error — {plate.name}", 0.0, f_val, None, mpe.flatness_mm,
            status=None if pfit else STATUS_ERROR,
            note=(f"range of plane residuals of {pfit.n_inliers} points, RMS "
                  f"{pfit.rms_mm * 1000:.1f} µm") if pfit else f"plane fit failed: {pfit.reason}",
        ))
    )  # fmt: skip
    result = AcceptanceResult(
        spec=spec,
        characteristics=chars,
        fits=fits,
        points_base=points,
        deviations_mm=deviations,
        n_excluded=excluded,
        cloud_path=cloud_path,
        spec_path=spec_path,
        provenance=prov,
        seconds=time.perf_counter() - t0,
    )
    for c in chars:
        if c.row.final_status in (STATUS_FAIL, STATUS_ERROR):
            log.info("acceptance: %s %s %s", c.symbol, c.artefact, c.row.final_status)
    return result


def _with_mask(fit: Fit, mask: NDArray) -> Fit:
    """The refit's inlier mask expressed over the whole region (it was fitted on a subset)."""
    import dataclasses

    full = mask.copy()
    full[mask] = fit.inliers
    return dataclasses.replace(fit, inliers=full)
