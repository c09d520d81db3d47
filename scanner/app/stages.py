"""The stage layer: each stage of the job run on files, once, for every caller.

The command line, the demo, the PLC jobs and the batch runner call these functions and never
chain the libraries themselves. A stage

- takes paths (sessions, calibration, cloud, plan) and the paths it is to write,
- reads and checks its inputs once, refusing bad input with a one-line :class:`InputError`
  before any expensive work, and refusing an output that would replace an input,
- writes all its artefacts together or none (:func:`commit_together`): a failed run leaves
  what was there before,
- records its provenance (program version, time, inputs with their digests) in what it
  writes, and
- returns a typed result holding the library's result and the paths written.

The names of a job folder's artefacts are declared in :class:`scanner.formats.layout.JobLayout`.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Generic, Literal, TypeVar, overload

import numpy as np
from numpy.typing import NDArray

from calibration.pipeline import CalibrationResult, calibrate_session
from calibration.report import write_calibration_report
from metrology.acceptance import (
    AcceptanceResult,
    FullAcceptance,
    full_acceptance,
    load_acceptance_spec,
    run_acceptance,
)
from metrology.coverage_map import write_coverage_map
from metrology.ef_check import EFCheckResult, EFTolerances, run_ef_check
from metrology.ef_report import write_ef_report
from metrology.inspect.inspect import inspect_cloud
from metrology.inspect.report import write_inspection_report
from metrology.inspect.result import InspectionResult, write_deviations
from metrology.inspect.spec import load_inspection_spec
from metrology.measure import MeasurementReport, measure_cloud
from metrology.plan import load_plan
from metrology.report import write_acceptance_report, write_measurement_report
from metrology.uncertainty import attach_uncertainties, measurement_uncertainties
from scanner import __version__
from scanner.core.config import resolve_config
from scanner.core.fileio import (
    InputError,
    check_outputs_apart,
    commit_together,
    write_json_atomic,
)
from scanner.formats.calibration_file import (
    CalibrationQuality,
    read_calibration,
    write_calibration,
)
from scanner.formats.clouds import FORMATS, read_points
from scanner.formats.layout import report_beside
from scanner.formats.meshes import read_mesh
from scanner.formats.scan_plan import write_scan_plan
from scanner.formats.session import read_session
from scanner.scanning.coverage import SensorGeometry
from scanner.scanning.geometry import scan_geometry_of
from scanner.scanning.pipeline import ScanOptions, ScanResult, check_scan_inputs, scan_session
from scanner.scanning.planning import PlanConfig, SweepPlan, place_on_table, plan_sweeps
from scanner.virtual_cell.cell import CellConfig, load_cell
from scanner.virtual_cell.simulate import simulate_cell
from scanner.virtual_cell.truth import CellTruth

log = logging.getLogger(__name__)

__all__ = [
    "CalibrateRun",
    "CheckRun",
    "InspectRun",
    "Judged",
    "PlanRun",
    "ReportFiles",
    "ScanRun",
    "StageClock",
    "acceptance",
    "calibrate",
    "check",
    "inspect",
    "measure",
    "plan_scan",
    "provenance",
    "scan",
    "simulate",
]


# --------------------------------------------------------------------------------------------
# provenance


def _digest(*paths: Path) -> str | None:
    """SHA-256 of the files' bytes in turn (``None`` when one is missing)."""
    h = hashlib.sha256()
    for path in paths:
        if not path.is_file():
            return None
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def provenance(stage: str, inputs: dict[str, Path | None]) -> dict[str, Any]:
    """What produced an artefact: the stage, the program's version, when, and from what.

    Files are recorded with their SHA-256; a session folder with that of its ``session.json``
    and ``frames.csv`` (its images are named there, with their poses).
    """
    record: dict[str, Any] = {}
    for name, path in inputs.items():
        if path is None:
            continue
        p = Path(path).resolve()
        files = (p / "session.json", p / "frames.csv") if p.is_dir() else (p,)
        record[name] = {"path": str(p), "sha256": _digest(*files)}
    return {
        "stage": stage,
        "scanner_version": __version__,
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "inputs": record,
    }


def _require_suffix(path: Path, suffixes: Sequence[str], what: str) -> None:
    if path.suffix.lower() not in suffixes:
        raise InputError(
            path,
            f"{what}: expected a {', '.join(suffixes)} file name, got {path.suffix or 'none'!r}",
        )


# --------------------------------------------------------------------------------------------
# simulate


def simulate(
    cell: str | CellConfig,
    out_dir: Path,
    *,
    seed: int = 0,
    target: str | None = None,
    sweep_frames: int | None = None,
    sessions: tuple[str, ...] = ("calibration", "check", "sweep"),
    workers: int = 2,
    progress: bool = False,
    sweep_paths: Sequence[NDArray] | None = None,
    check_cancelled: Callable[[], None] | None = None,
) -> CellTruth:
    """Capture sessions from the virtual cell into ``out_dir/<kind>/``, with their truth.

    ``sweep_paths`` (flange poses of each planned sweep) replaces the cell's own sweep;
    ``check_cancelled`` is called before the first frame and after each (``simulate_cell``).
    """
    if seed < 0:
        raise ValueError(f"--seed: expected >= 0, got {seed}")
    return simulate_cell(
        cell,
        out_dir,
        seed=seed,
        target=target,
        sweep_frames=sweep_frames,
        sessions=sessions,
        workers=workers,
        progress=progress,
        sweep_paths=sweep_paths,
        check_cancelled=check_cancelled,
    )


# --------------------------------------------------------------------------------------------
# plan-scan


@dataclass(frozen=True)
class PlanRun:
    """Sweeps planned for a part: the plan and the files written into the plan folder.

    ``plan.json`` and ``sweeps.csv`` (``scan-plan/1``), ``coverage.npz`` (the surface samples
    in the part's frame, which are visible from above and which sweep measures each) and
    ``coverage.png`` (the map).
    """

    plan: SweepPlan
    base_from_part: NDArray
    plan_path: Path
    sweeps_path: Path
    samples_path: Path
    map_path: Path


def plan_scan(
    part_path: Path,
    out_dir: Path,
    *,
    cell: str | CellConfig | None = None,
    calibration_path: Path | None = None,
    part_at_mm: tuple[float, float, float] | None = None,
    part_yaw_deg: float = 0.0,
    config: PlanConfig | None = None,
    rotation: str = "quaternion_wxyz",
) -> PlanRun:
    """Plan the sweeps that cover a part (``scanner plan-scan``).

    The sensor is a virtual cell's (``cell``) or a calibration file's (``calibration_path``,
    which must hold the laser origin). The part stands on the table with the middle of its
    footprint at ``part_at_mm`` (default: the cell's sweep centre on its table).
    """
    part_path, out_dir = Path(part_path), Path(out_dir)
    if (cell is None) == (calibration_path is None):
        raise ValueError("plan-scan: expected either a cell or a calibration file, not both")
    names = ("plan.json", "sweeps.csv", "coverage.npz", "coverage.png")
    inputs = [part_path, *([calibration_path] if calibration_path is not None else [])]
    check_outputs_apart(inputs, [out_dir / n for n in names])
    part = read_mesh(part_path)
    if calibration_path is not None:
        calibration = read_calibration(calibration_path)
        calibration.require_light_plane(calibration_path, "planning")
        try:
            sensor = SensorGeometry.from_calibration(calibration)
        except ValueError as exc:
            raise InputError(calibration_path, str(exc)) from None
        source = {"calibration": str(calibration_path)}
        if part_at_mm is None:
            raise ValueError("--part-at: expected where the part stands (x,y,z mm, base frame)")
    else:
        cell_config = load_cell(cell)
        sensor = cell_config.sensor_geometry()
        source = {"cell": cell_config.name}
        if part_at_mm is None:
            sw = cell_config.sweep
            part_at_mm = (sw.center_mm[0], sw.center_mm[1], sw.table_z_mm)
    config = config or PlanConfig()
    base_from_part = place_on_table(part, part_at_mm, part_yaw_deg)
    plan = plan_sweeps(sensor, part.transformed(base_from_part), config)
    part_from_base = np.linalg.inv(base_from_part)
    record = {
        "part": {"path": str(part_path), "base_from_part": base_from_part.tolist()},
        "sensor": source,
        "coverage": {
            "predicted": plan.coverage,
            "target": plan.target_coverage,
            "reached": bool(plan),
            "reason": plan.reason,
            "visible_share_of_surface": plan.visible_share,
            "samples": len(plan.points_base),
            "limits": {
                "max_view_incidence_deg": config.limits.max_view_incidence_deg,
                "max_laser_incidence_deg": config.limits.max_laser_incidence_deg,
                "depth_range_mm": list(config.limits.depth_range_mm),
                "image_margin_px": config.limits.image_margin_px,
            },
        },
        "candidates": plan.candidates,
        "reachable_candidates": plan.reachable,
        "frames": plan.frames,
        "sweeps": [
            {
                "index": k,
                "frames": sw.frames,
                "length_mm": sw.length_mm,
                "step_mm": sw.step_mm,
                "direction": sw.direction.tolist(),
                "base_from_cam_start": sw.base_from_cam_start.tolist(),
                "gain": gain,
            }
            for k, (sw, gain) in enumerate(zip(plan.sweeps, plan.gains))
        ],
        "provenance": provenance("plan-scan", {"part": part_path, "calibration": calibration_path}),
    }
    points_part = plan.points_base @ part_from_base[:3, :3].T + part_from_base[:3, 3]
    normals_part = plan.normals_base @ part_from_base[:3, :3].T
    paths = [out_dir / n for n in names]
    with commit_together() as staged:
        folder = staged(paths[0]).parent
        staged(paths[1])
        write_scan_plan(
            folder,
            [sw.base_from_flange(sensor.flange_from_cam) for sw in plan.sweeps],
            record,
            rotation,
        )
        np.savez_compressed(
            staged(paths[2]),
            points_part=points_part,
            normals_part=normals_part,
            visible=plan.visible,
            measured_by=plan.measured_by,
        )
        write_coverage_map(
            staged(paths[3]),
            part,
            points_part,
            plan.visible,
            plan.measured_by,
            f"{part_path.name}: {len(plan.sweeps)} sweeps, {plan.frames} profiles, predicted "
            f"coverage {100 * plan.coverage:.1f} % of the surface visible from above",
        )
    return PlanRun(plan, base_from_part, *paths)


# --------------------------------------------------------------------------------------------
# calibrate


@dataclass(frozen=True)
class CalibrateRun:
    """A calibration written: the library's result and the files."""

    result: CalibrationResult
    calibration_path: Path
    report_path: Path | None

    @property
    def quality(self) -> CalibrationQuality:
        return self.result.calibration.quality


def calibrate(
    session_dir: Path,
    out: Path,
    *,
    report: Path | Literal["beside"] | None = "beside",
    method: Literal["default", "paper"] = "default",
    refine_intrinsics: bool = False,
    laser_origin_cam_mm: tuple[float, float, float] | None = None,
    laser_origin_strict: bool = True,
    progress: bool = False,
    on_stage: Callable[[str], None] | None = None,
    check_cancelled: Callable[[], None] | None = None,
) -> CalibrateRun:
    """Calibrate from a ``calibration`` session and write the calibration file and its report.

    Parameters
    ----------
    session_dir : path
        The calibration session folder.
    out : path
        The calibration file to write (JSON).
    report : path, None or "beside"
        The HTML report: beside ``out`` (same name, ``.html``) by default, ``None`` for none.
    laser_origin_cam_mm : tuple of float, optional
        The laser fan's apex in the camera frame (mm) from the sensor's drawing: written as
        ``laser_origin_cam``; it must lie on the calibrated light plane (within 5 mm).
    laser_origin_strict : bool
        An origin off the new plane is an error (``True``, a user's input) or left out with a
        warning (``False``: the PLC carrying the installed calibration's origin over).
    check_cancelled : callable, optional
        Called between the calibration's stages and images (``calibrate_session``).
    """
    out = Path(out)
    _require_suffix(out, (".json",), "--out")
    report_path = report_beside(out) if report == "beside" else report
    outputs = [out] + ([report_path] if report_path is not None else [])
    check_outputs_apart([session_dir], outputs)
    if laser_origin_cam_mm is not None and not all(math.isfinite(v) for v in laser_origin_cam_mm):
        raise ValueError(f"--laser-origin-mm: expected finite numbers, got {laser_origin_cam_mm}")
    session = read_session(session_dir)
    result = calibrate_session(
        session,
        method=method,
        progress=progress,
        refine_intrinsics=refine_intrinsics,
        on_stage=on_stage,
        check_cancelled=check_cancelled,
    )
    record = dict(result.calibration.quality.record)
    record["provenance"] = provenance("calibrate", {"session": Path(session_dir)})
    if result.calibration.laser_origin_cam is not None:
        record["laser_origin_source"] = "estimated from the laser frames' shadow edges"
    calibration = replace(
        result.calibration, quality=replace(result.calibration.quality, record=record)
    )
    if laser_origin_cam_mm is not None:
        origin = np.asarray(laser_origin_cam_mm, dtype=np.float64)
        if calibration.light_plane is None:
            raise ValueError("--laser-origin-mm: the session gave no light plane to put it on")
        off = abs(float(calibration.light_plane.signed_distance(origin)))
        if off <= 5.0:
            record["laser_origin_source"] = "given (--laser-origin-mm, the sensor's drawing)"
            cov = calibration.covariance  # the estimate's origin covariance is not the drawing's
            calibration = replace(
                calibration,
                laser_origin_cam=origin,
                quality=replace(calibration.quality, record=record),
                covariance=cov if cov is None else replace(cov, laser_origin_mm2=None),
            )
        elif laser_origin_strict:
            raise ValueError(
                f"--laser-origin-mm: expected a point on the calibrated light plane, got one "
                f"{off:.1f} mm off it (camera frame, mm?)"
            )
        else:
            log.warning(
                "laser origin %s left out: %.1f mm off the new light plane", origin.tolist(), off
            )
    result = replace(result, calibration=calibration)
    with commit_together() as staged:
        write_calibration(staged(out), calibration)
        if report_path is not None:
            staged_report = staged(report_path)
            write_calibration_report(result, staged_report.parent, staged_report.name)
    return CalibrateRun(result, out, report_path)


# --------------------------------------------------------------------------------------------
# check


@dataclass(frozen=True)
class CheckRun:
    """An EF check written: the result and the files."""

    result: EFCheckResult
    out_path: Path
    report_path: Path | None


def check(
    session_dir: Path,
    calibration_path: Path,
    out: Path,
    *,
    report: Path | Literal["beside"] | None = "beside",
    mode: Literal["fast", "precise"] = "precise",
    tolerances: EFTolerances | None = None,
    progress: bool = False,
    check_cancelled: Callable[[], None] | None = None,
) -> CheckRun:
    """The paper's EF check on a ``check`` session; writes the result JSON and its report.

    ``check_cancelled`` is called after each laser frame's measurement (``run_ef_check``).
    """
    out = Path(out)
    _require_suffix(out, (".json",), "--out")
    report_path = report_beside(out) if report == "beside" else report
    outputs = [out] + ([report_path] if report_path is not None else [])
    check_outputs_apart([session_dir, calibration_path], outputs)
    calibration = read_calibration(calibration_path)
    calibration.require_light_plane(calibration_path, "the EF check")
    session = read_session(session_dir)
    result = run_ef_check(
        session,
        calibration,
        progress=progress,
        mode=mode,
        calibration_source=str(Path(calibration_path).resolve()),
        tolerances=tolerances,
        check_cancelled=check_cancelled,
    )
    data = result.to_json()
    data["provenance"] = provenance(
        "check", {"session": Path(session_dir), "calibration": Path(calibration_path)}
    )
    with commit_together() as staged:
        write_json_atomic(staged(out), data)
        if report_path is not None:
            write_ef_report(result, staged(report_path))
    return CheckRun(result, out, report_path)


# --------------------------------------------------------------------------------------------
# scan


@dataclass(frozen=True)
class ScanRun:
    """A cloud written: the scan's result (counts, timings, corrections) and the file."""

    result: ScanResult
    out_path: Path


def scan(
    session_dirs: Sequence[Path],
    calibration_path: Path,
    out: Path,
    *,
    options: ScanOptions | None = None,
    work_dir: Path | None = None,
    progress: bool = False,
    check_cancelled: Callable[[], None] | None = None,
) -> ScanRun:
    """Sweep sessions to one base-frame cloud, written atomically (``.ply``, ``.pcd``, ``.e57``).

    Everything that can be refused (file names, calibration, sessions, image sizes) is
    refused before any image is decoded. ``check_cancelled`` is called between chunks of
    frames and between the later steps: what it raises stops the scan (a PLC job's
    cancellation).
    """
    out = Path(out)
    if out.suffix.lower() not in FORMATS:
        raise InputError(
            out, f"expected a {', '.join(FORMATS)} file name, got {out.suffix or 'none'!r}"
        )
    if not session_dirs:
        raise ValueError("sessions: expected at least one sweep session, got none")
    check_outputs_apart([*session_dirs, calibration_path], [out])
    calibration = read_calibration(calibration_path)
    calibration.require_light_plane(calibration_path, "scanning")
    options = options or ScanOptions()
    if options.laser_origin_mm is None and calibration.laser_origin_cam is not None:
        # The calibration's laser origin gives each point's illumination angle.
        options = replace(options, laser_origin_mm=tuple(calibration.laser_origin_cam.tolist()))
    sessions = [read_session(s, check_images=True) for s in session_dirs]
    check_scan_inputs(sessions, calibration)
    result = scan_session(
        sessions,
        calibration,
        options,
        out_path=out,
        work_dir=work_dir,
        progress=progress,
        calibration_path=Path(calibration_path),
        check_cancelled=check_cancelled,
    )
    return ScanRun(result, out)


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


# --------------------------------------------------------------------------------------------
# timing, for the callers that report time per stage


@dataclass
class StageClock:
    """Seconds per stage name, for a job's summary."""

    seconds: dict[str, float] = field(default_factory=dict)

    def run(self, name: str, fn: Callable[[], Any]) -> Any:
        t0 = time.perf_counter()
        try:
            return fn()
        finally:
            self.seconds[name] = time.perf_counter() - t0
