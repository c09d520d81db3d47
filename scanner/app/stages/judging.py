"""Judging clouds: an inspection plan's features measured (``scanner measure``), the acceptance
test against the spec's MPEs (``scanner acceptance``), and the scan-to-CAD inspection against
a nominal mesh (``scanner inspect``)."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, Literal, TypeVar, overload

import numpy as np
from numpy.typing import NDArray

from metrology.acceptance import (
    AcceptanceResult,
    FullAcceptance,
    full_acceptance,
    load_acceptance_spec,
    run_acceptance,
)
from metrology.inspect.inspect import inspect_cloud
from metrology.inspect.report import write_inspection_report
from metrology.inspect.result import InspectionResult, write_deviations
from metrology.inspect.spec import load_inspection_spec
from metrology.measure import MeasurementReport, measure_cloud
from metrology.plan import load_plan
from metrology.report import write_acceptance_report, write_measurement_report
from metrology.uncertainty import attach_uncertainties, measurement_uncertainties
from scanner.app.stages.common import _require_suffix, provenance
from scanner.core.config import resolve_config
from scanner.core.fileio import InputError, check_outputs_apart, commit_together, write_json_atomic
from scanner.formats.clouds import read_points
from scanner.formats.layout import report_beside
from scanner.formats.meshes import read_mesh
from scanner.scanning.geometry import scan_geometry_of

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# measure and acceptance


def _cloud_with_provenance(
    cloud_path: Path, calibration_path: Path | None
) -> tuple[Any, dict[str, Any]]:
    points, cloud_provenance = read_points(cloud_path)
    if calibration_path is not None:
        if not Path(calibration_path).is_file():
            raise InputError(calibration_path, "calibration file not found")
        cloud_provenance = {
            **cloud_provenance,
            "calibration": str(Path(calibration_path).resolve()),
        }
    return points, cloud_provenance


@dataclass(frozen=True)
class ReportFiles:
    """The three files of a judged cloud: JSON (for machines), CSV (the table), HTML."""

    json_path: Path
    csv_path: Path
    html_path: Path

    @classmethod
    def beside(cls, out: Path) -> ReportFiles:
        _require_suffix(out, (".json",), "--out (the .csv and .html go beside it)")
        return cls(out, out.with_suffix(".csv"), out.with_suffix(".html"))


#: One cloud's result, and the result written (one cloud's, or several clouds' combined).
J = TypeVar("J", MeasurementReport, AcceptanceResult)
R = TypeVar("R", MeasurementReport, AcceptanceResult, FullAcceptance)


def _the_one(results: list[J]) -> J:
    return results[0]


def _judge_clouds(
    stage: str,
    cloud_paths: Sequence[Path],
    config: str | Path,
    out: Path,
    calibration_path: Path | None,
    judge: Callable[[NDArray, Path, dict[str, Any]], J],
    combine: Callable[[list[J]], R],
    write: Callable[[R, Path], object],
) -> tuple[R, ReportFiles]:
    """Judge clouds against a plan or spec (``configs/plans`` name or path); write the files:
    ``judge(points, config_path, provenance)`` gives one cloud's result, ``combine`` the one
    written (:func:`_the_one` for one cloud), ``write(result, out_json)`` the JSON, CSV and
    HTML. Every cloud is checked (there, given once, not an output) before any is read."""
    files = ReportFiles.beside(Path(out))
    config_path = resolve_config(config, "plans")
    clouds = [Path(c) for c in cloud_paths]
    for k, c in enumerate(clouds):
        if not c.is_file():
            raise InputError(c, "point cloud not found")
        if any(os.path.samefile(c, earlier) for earlier in clouds[:k]):
            raise InputError(c, "given twice: expected each scan once")
    inputs = [*clouds, config_path, *([calibration_path] if calibration_path else [])]
    check_outputs_apart(inputs, [files.json_path, files.csv_path, files.html_path])
    results = []
    for c in clouds:
        points, cloud_provenance = _cloud_with_provenance(c, calibration_path)
        cloud_provenance["stage"] = provenance(stage, {"cloud": c, "plan": config_path})
        one = judge(points, config_path, cloud_provenance)
        one.cloud_path = str(c)
        results.append(one)
    result = combine(results)
    with commit_together() as staged:
        write(result, staged(files.json_path))
    return result, files


def _measure_with_uncertainty(
    cloud_path: Path, calibration_path: Path | None
) -> Callable[[NDArray, Path, dict[str, Any]], MeasurementReport]:
    """The measurement of a cloud with each value's uncertainty: from the calibration's
    covariance, the robot's repeatability and the stripe noise where the cloud's stops are
    known (:func:`scanner.scanning.geometry.scan_geometry_of`), the noise alone otherwise."""

    def judge(
        points: NDArray, plan_path: Path, cloud_provenance: dict[str, Any]
    ) -> MeasurementReport:
        report = measure_cloud(points, load_plan(plan_path), provenance=cloud_provenance)
        report.plan_path = str(plan_path)
        geometry, why = scan_geometry_of(cloud_path, calibration_path)
        if geometry is not None and len(geometry.frame_index) != len(points):
            geometry, why = None, "the cloud's stops do not match its points"
        if geometry is None:
            log.warning("uncertainty without the calibration and robot shares: %s", why)
        t0 = time.perf_counter()
        try:
            uncertainties = measurement_uncertainties(
                report, geometry, not_included=() if geometry is not None else (why,)
            )
        except (ValueError, np.linalg.LinAlgError) as exc:
            # the measurement stands without it (and a guarded rule cannot prove conformity)
            log.warning("no uncertainty evaluated: %s", exc)
            uncertainties = [None] * len(report.measurements)
        report = attach_uncertainties(report, uncertainties)
        report.seconds += time.perf_counter() - t0
        return report

    return judge


def _accept(points: NDArray, spec_path: Path, cloud_provenance: dict[str, Any]) -> AcceptanceResult:
    result = run_acceptance(points, load_acceptance_spec(spec_path), provenance=cloud_provenance)
    result.spec_path = str(spec_path)
    return result


@dataclass(frozen=True)
class Judged(Generic[R]):
    """A judged cloud written: the result (measurement report or acceptance) and its files."""

    result: R
    files: ReportFiles


def measure(
    cloud_path: Path, plan: str | Path, out: Path, *, calibration_path: Path | None = None
) -> Judged[MeasurementReport]:
    """Fit an inspection plan's features in a cloud; write ``out`` (JSON) with CSV and HTML.

    ``plan`` is a TOML path or the name of a shipped plan (``configs/plans``).
    """
    judge = _measure_with_uncertainty(Path(cloud_path), calibration_path)
    report, files = _judge_clouds(
        "measure", [cloud_path], plan, out, calibration_path, judge, _the_one,
        write_measurement_report,
    )  # fmt: skip
    return Judged(report, files)


@overload
def acceptance(
    cloud_path: Path, spec: str | Path, out: Path, *, calibration_path: Path | None = None
) -> Judged[AcceptanceResult]: ...
@overload
def acceptance(
    cloud_path: Sequence[Path], spec: str | Path, out: Path, *, calibration_path: Path | None = None
) -> Judged[FullAcceptance]: ...
def acceptance(
    cloud_path: Path | Sequence[Path],
    spec: str | Path,
    out: Path,
    *,
    calibration_path: Path | None = None,
) -> Judged[AcceptanceResult] | Judged[FullAcceptance]:
    """PF, PS, SD and F of scans of a sphere bar and a plate against the spec's MPEs.

    One path: that scan's :class:`AcceptanceResult`. A sequence, the guideline's full test
    (the bar and plate in several positions): a :class:`FullAcceptance`, each characteristic
    decided by its worst scan. Bad input (see :func:`_judge_clouds`) raises
    :class:`InputError` before anything is written; an empty sequence ``ValueError``."""
    if isinstance(cloud_path, (str, os.PathLike)):
        result, files = _judge_clouds(
            "acceptance", [Path(cloud_path)], spec, out, calibration_path, _accept, _the_one,
            write_acceptance_report,
        )  # fmt: skip
        return Judged(result, files)
    if not cloud_path:
        raise ValueError("cloud_path: expected at least one acceptance scan, got none")
    full, files = _judge_clouds(
        "acceptance", cloud_path, spec, out, calibration_path, _accept, full_acceptance,
        write_acceptance_report,
    )  # fmt: skip
    return Judged(full, files)


# --------------------------------------------------------------------------------------------
# scan-to-CAD inspection


@dataclass(frozen=True)
class InspectRun:
    """A cloud inspected against its nominal mesh: the result and the files written."""

    result: InspectionResult
    out_path: Path
    deviations_path: Path | None
    report_path: Path | None


def inspect(
    cloud_path: Path,
    nominal_path: Path,
    out: Path,
    *,
    deviations: Path | None = None,
    spec: str | Path = "default",
    report: Path | Literal["beside"] | None = "beside",
) -> InspectRun:
    """Align a cloud to its nominal mesh and judge each point's deviation (contract section 5).

    Parameters
    ----------
    cloud_path : path
        The scan (PLY, PCD, E57 or a point list), any frame, mm.
    nominal_path : path
        The nominal mesh (STL, PLY, OBJ), the part's frame, mm.
    out : path
        ``RESULT.json`` (``scan-inspection/1``).
    deviations : path, optional
        ``DEV.ply``: every point in the nominal's frame with ``deviation_mm`` and ``outlier``.
    spec : str or path
        Inspection spec (bands, regions, sections, alignment): a TOML path or the name of one
        in ``configs/inspect`` (``default``: +-0.1 mm).
    report : path, None or "beside"
        The HTML report: beside ``out`` by default, ``None`` for none.
    """
    out = Path(out)
    _require_suffix(out, (".json",), "--out")
    if deviations is not None:
        _require_suffix(Path(deviations), (".ply",), "--deviations")
    report_path = report_beside(out) if report == "beside" else report
    spec_path = resolve_config(spec, "inspect")
    outputs = [out, *(p for p in (deviations, report_path) if p is not None)]
    check_outputs_apart([cloud_path, nominal_path, spec_path], outputs)
    inspection_spec = load_inspection_spec(spec_path)
    nominal = read_mesh(nominal_path)
    points_cloud, _ = read_points(cloud_path)
    geometry, why = scan_geometry_of(cloud_path)  # the calibration's share, where known
    result = inspect_cloud(
        points_cloud, nominal, inspection_spec, geometry=geometry, geometry_missing=why
    )
    result.nominal_path = str(nominal_path)
    result.cloud_path = str(cloud_path)
    result.spec_path = str(spec_path)
    result.provenance = provenance(
        "inspect", {"cloud": Path(cloud_path), "nominal": Path(nominal_path), "spec": spec_path}
    )
    with commit_together() as staged:
        write_json_atomic(staged(out), result.to_json())
        if deviations is not None:
            write_deviations(staged(Path(deviations)), result)
        if report_path is not None:
            write_inspection_report(result, staged(report_path))
    return InspectRun(result, out, deviations, report_path)
