"""What the PLC service runs: the job interface, session sources and the pipeline jobs.

The service does not know how a check, a scan or a calibration is computed. It calls a
:class:`JobRunner`: three functions taking a :class:`JobContext` and returning a
:class:`JobOutcome` or raising :class:`JobError` with an :class:`ErrorCode`. The default
runner, :class:`PipelineJobs`, captures a session from a :class:`SessionSource` and runs the
stages of :mod:`scanner.app.stages`, the same functions the command line and the demo call.
Tests inject fake runners.

Jobs run on a worker thread. Cancellation is cooperative: the service sets
``ctx.cancel`` (watchdog, job timeout, shutdown) and a job calls
:meth:`JobContext.check_cancelled` between its stages, which raises :class:`JobCancelled`.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import shutil
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np

from metrology.ef_check import EFTolerances
from scanner.app import stages
from scanner.app.full_object import cell_with_part, full_object_scan_options
from scanner.app.plc.config import (
    CalibrationGate,
    CheckTolerances,
    PlcConfig,
    Recipe,
    SourceConfig,
)
from scanner.app.plc.registers import ErrorCode
from scanner.core.config import resolve_config
from scanner.core.fileio import InputError
from scanner.formats.calibration_file import CalibrationQuality, read_calibration
from scanner.formats.layout import JobLayout
from scanner.formats.meshes import read_mesh
from scanner.formats.scan_plan import ScanPlanFile, read_scan_plan
from scanner.virtual_cell.cell import CellConfig, load_cell

__all__ = [
    "FolderSource",
    "JobCancelled",
    "JobContext",
    "JobError",
    "JobOutcome",
    "JobRunner",
    "PipelineJobs",
    "SessionSource",
    "VirtualCellSource",
    "calibration_gate",
    "ef_tolerances",
    "install_calibration",
    "make_source",
]

log = logging.getLogger(__name__)

T = TypeVar("T")


class JobError(Exception):
    """A job that cannot finish, with the error code the PLC reads."""

    def __init__(self, code: ErrorCode, message: str) -> None:
        self.code = ErrorCode(code)
        self.message = message
        super().__init__(f"error {int(code)} ({self.code.name}): {message}")


class JobCancelled(Exception):
    """Raised by :meth:`JobContext.check_cancelled` once the service has cancelled the job."""


@dataclass
class JobContext:
    """Everything a job gets: who it is, where to write, and the cancellation flag."""

    job_id: int
    command: int
    parameter: int
    #: A fresh folder for this job's session, report and artefacts.
    work_dir: Path
    config: PlcConfig
    cancel: threading.Event = field(default_factory=threading.Event)
    #: Set by the job when it knows the session it processes (recorded in the history).
    session_path: Path | None = None

    def check_cancelled(self) -> None:
        """Raise :class:`JobCancelled` if the service has cancelled this job."""
        if self.cancel.is_set():
            raise JobCancelled(f"job {self.job_id} cancelled")


@dataclass(frozen=True)
class JobOutcome:
    """How a job that ran to its end came out.

    ``passed`` false with ``error`` NONE is a valid result out of tolerance (DONE without
    PASS); a non-NONE ``error`` makes the PLC see ERROR with that code (e.g. a calibration
    that failed its quality gate), with the figures still recorded.
    """

    passed: bool
    results_um: tuple[float | None, float | None, float | None] = (None, None, None)
    report_path: Path | None = None
    artefacts: tuple[Path, ...] = ()
    error: ErrorCode = ErrorCode.NONE
    message: str = ""
    not_proven: bool = False
    """Nothing failed, but a measurement's conformity is not proven (guarded acceptance)."""


class JobRunner(Protocol):
    """The three jobs the PLC can start (command 1, 2, 3)."""

    def recalibration_check(self, ctx: JobContext) -> JobOutcome: ...

    def scan(self, ctx: JobContext) -> JobOutcome: ...

    def full_calibration(self, ctx: JobContext) -> JobOutcome: ...


# --------------------------------------------------------------------------------------------
# Session sources


class SessionSource(Protocol):
    """Gives a job the session folder it processes."""

    def acquire(self, kind: str, ctx: JobContext, recipe: Recipe | None = None) -> Path: ...


def _session_kind(folder: Path) -> str | None:
    try:
        data = json.loads((folder / "session.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    kind = data.get("kind") if isinstance(data, dict) else None
    return kind if isinstance(kind, str) else None


@dataclass(frozen=True)
class FolderSource:
    """Session folders dropped by capture software into ``root``; the newest complete one wins.

    A folder is complete once its ``session.json`` exists (the capture writes it last); newest
    means the latest ``session.json`` modification time. Only sessions of the requested kind
    are considered.
    """

    root: Path

    def newest(self, kind: str) -> Path | None:
        """The newest complete session folder of ``kind``, or ``None``."""
        if not self.root.is_dir():
            return None
        best: tuple[float, str] | None = None
        best_path: Path | None = None
        for child in self.root.iterdir():
            marker = child / "session.json"
            try:
                mtime = marker.stat().st_mtime
            except OSError:
                continue
            if _session_kind(child) != kind:
                continue
            key = (mtime, child.name)
            if best is None or key > best:
                best, best_path = key, child
        return best_path

    def acquire(self, kind: str, ctx: JobContext, recipe: Recipe | None = None) -> Path:
        found = self.newest(kind)
        if found is None:
            raise JobError(ErrorCode.NO_SESSION, f"no complete {kind!r} session in {self.root}")
        return found


@dataclass(frozen=True)
class VirtualCellSource:
    """Each job captures a fresh session from the virtual cell (``scanner.virtual_cell``).

    The seed is ``seed`` plus the job id, so every job sees new noise and the run is
    reproducible from the history.
    """

    cell: str = "modern"
    seed: int = 0
    workers: int = 2

    def acquire(self, kind: str, ctx: JobContext, recipe: Recipe | None = None) -> Path:
        cell: str | CellConfig = recipe.cell if recipe is not None and recipe.cell else self.cell
        out = ctx.work_dir / "capture"
        sweep_paths = None
        if kind == "sweep" and recipe is not None and recipe.sweeps:
            planned, base_from_part = _planned_part(recipe.sweeps)
            part_cell = _call(load_cell, cell)
            cell = cell_with_part(part_cell, Path(recipe.nominal), base_from_part)
            sweep_paths = planned.base_from_flange
        _call(
            stages.simulate,
            cell,
            out,
            seed=self.seed + ctx.job_id,
            sessions=(kind,),
            workers=self.workers,
            sweep_paths=sweep_paths,
            check_cancelled=ctx.check_cancelled,
        )
        session = out / kind
        if not (session / "session.json").is_file():
            raise JobError(ErrorCode.NO_SESSION, f"the virtual cell wrote no {kind} session")
        return session


def make_source(config: SourceConfig) -> SessionSource:
    """The session source the config names."""
    if config.kind == "folder":
        return FolderSource(Path(config.folder))
    return VirtualCellSource(config.cell, config.seed)


# --------------------------------------------------------------------------------------------
# Calibration file management


def install_calibration(
    new_path: Path, current_path: Path, now: dt.datetime | None = None
) -> Path | None:
    """Make ``new_path`` the current calibration, keeping the old one with a timestamp.

    Returns
    -------
    Path or None
        Where the previous calibration now is (``calibration-YYYYMMDDTHHMMSS.json`` beside
        it), or ``None`` when there was none.
    """
    now = now or dt.datetime.now(dt.timezone.utc)
    current_path.parent.mkdir(parents=True, exist_ok=True)
    kept: Path | None = None
    if current_path.exists():
        stamp = now.strftime("%Y%m%dT%H%M%S")
        kept = current_path.with_name(f"{current_path.stem}-{stamp}{current_path.suffix}")
        n = 1
        while kept.exists():
            kept = current_path.with_name(f"{current_path.stem}-{stamp}-{n}{current_path.suffix}")
            n += 1
        shutil.copy2(current_path, kept)
    # Copy beside the target, then rename: the current file is never half-written.
    tmp = current_path.with_name(f".{current_path.name}.new")
    shutil.copyfile(new_path, tmp)
    os.replace(tmp, current_path)
    return kept


# --------------------------------------------------------------------------------------------
# The pipeline jobs


def _call(func: Callable[..., T], *args: Any, **kwargs: Any) -> T:
    """Call a stage, turning bad input into the job error the PLC reads."""
    try:
        return func(*args, **kwargs)
    except (JobError, JobCancelled):
        raise
    except (InputError, ValueError, FileNotFoundError) as exc:
        # The stages report bad input (too few frames, target not found...) as ValueError.
        raise JobError(ErrorCode.BAD_INPUT, " ".join(str(exc).split())) from exc


def _planned_part(folder: str) -> tuple[ScanPlanFile, np.ndarray]:
    """A recipe's scan plan and where it puts the part; a plan without a part is bad input."""
    planned = _call(read_scan_plan, Path(folder))
    if planned.base_from_part is None:
        raise JobError(ErrorCode.BAD_INPUT, f"{folder}: the plan does not place a part")
    return planned, planned.base_from_part


def _mm_to_um(value: float | None) -> float | None:
    return None if value is None else float(value) * 1000.0


def ef_tolerances(tol: CheckTolerances) -> EFTolerances:
    """The service's check limits (µm, as the PLC reads the results) for the EF check."""
    return EFTolerances(
        max_mean_abs_mm=tol.max_mean_abs_um / 1000.0,
        max_abs_mm=tol.max_abs_um / 1000.0,
        max_o_spread_mm=tol.max_o_spread_um / 1000.0,
    )


class PipelineJobs:
    """The real jobs: capture a session, then run the stages (:mod:`scanner.app.stages`).

    Each job writes its artefacts into its own folder under the names of
    :class:`~scanner.formats.layout.JobLayout`, as the demo does.

    Parameters
    ----------
    config : PlcConfig
        Tolerances, recipes, the calibration path.
    source : SessionSource, optional
        Where sessions come from; default from ``config.source``.
    """

    def __init__(self, config: PlcConfig, source: SessionSource | None = None) -> None:
        self.config = config
        self.source = source or make_source(config.source)

    @property
    def calibration_path(self) -> Path:
        return Path(self.config.storage.calibration)

    def _require_calibration(self) -> Path:
        path = self.calibration_path
        if not path.is_file():
            raise JobError(ErrorCode.NO_CALIBRATION, f"no calibration at {path}")
        return path

    def recalibration_check(self, ctx: JobContext) -> JobOutcome:
        """EF check and spread of O on a fresh ``check`` session, against the tolerances."""
        calibration = self._require_calibration()
        ctx.session_path = self.source.acquire("check", ctx)
        ctx.check_cancelled()
        job = JobLayout.of(ctx.work_dir)
        run = _call(
            stages.check,
            ctx.session_path,
            calibration,
            job.check,
            tolerances=ef_tolerances(self.config.check),
            check_cancelled=ctx.check_cancelled,
        )
        result = run.result
        results = (
            _mm_to_um(result.mean_abs_error_mm),
            _mm_to_um(result.max_abs_error_mm),
            _mm_to_um(result.o_spread_mm),
        )
        return JobOutcome(
            passed=result.passed,
            results_um=results,
            report_path=run.report_path or run.out_path,
            artefacts=(run.out_path,),
        )

    def scan(self, ctx: JobContext) -> JobOutcome:
        """Scan a sweep session and judge it by the recipe (recipe number in register 3).

        A recipe with a plan measures it; one with a nominal mesh inspects the cloud against
        it (scan-to-CAD). Results: with a nominal, the largest deviation (signed, of the points
        that are not outliers), the deviation RMS and the alignment RMS, µm, PASS when the
        inspection's verdict is pass and its pose is not ambiguous; with a plan only, the
        plan's first three measured values in µm, PASS when no measurement failed. With both,
        PASS needs both.
        """
        recipe = self.config.recipe(ctx.parameter)
        if recipe is None:
            known = ", ".join(str(r.number) for r in self.config.recipes) or "none"
            raise JobError(
                ErrorCode.UNKNOWN_RECIPE,
                f"expected a recipe number ({known}), got {ctx.parameter}",
            )
        calibration = self._require_calibration()
        plan = _call(resolve_config, recipe.plan, "plans") if recipe.plan else None
        spec = _call(resolve_config, recipe.inspect_spec, "inspect") if recipe.nominal else None
        options = None
        if recipe.sweeps:
            _, base_from_part = _planned_part(recipe.sweeps)
            options = full_object_scan_options(base_from_part, _call(read_mesh, recipe.nominal))
        ctx.session_path = self.source.acquire("sweep", ctx, recipe)
        ctx.check_cancelled()
        job = JobLayout.of(ctx.work_dir)
        _call(
            stages.scan,
            [ctx.session_path],
            calibration,
            job.cloud,
            options=options,
            check_cancelled=ctx.check_cancelled,
        )
        ctx.check_cancelled()
        outcomes = []
        if plan is not None:
            outcomes.append(self._measure(job, plan, calibration))
            ctx.check_cancelled()
        if spec is not None:
            outcomes.append(self._inspect(job, Path(recipe.nominal), spec))
        # The inspection's figures go to the registers when there is one; all artefacts stay.
        return replace(
            outcomes[-1],
            passed=all(o.passed for o in outcomes),
            not_proven=any(o.not_proven for o in outcomes)
            and not any(not o.passed and not o.not_proven for o in outcomes),
            artefacts=(job.cloud, *(a for o in outcomes for a in o.artefacts)),
            message="; ".join(o.message for o in outcomes if o.message),
        )

    def _measure(self, job: JobLayout, plan: Path, calibration: Path) -> JobOutcome:
        run = _call(stages.measure, job.cloud, plan, job.measure, calibration_path=calibration)
        report = run.result
        figures: list[float | None] = [
            None if r.actual is None else float(r.actual) * 1000.0 for r in report.rows[:3]
        ]
        figures += [None] * (3 - len(figures))
        return JobOutcome(
            passed=bool(report.passed),
            not_proven=report.verdict == "not proven",
            results_um=(figures[0], figures[1], figures[2]),
            report_path=run.files.html_path,
            artefacts=(run.files.json_path,),
            message=report.summary(),
        )

    def _inspect(self, job: JobLayout, nominal: Path, spec: Path) -> JobOutcome:
        run = _call(
            stages.inspect, job.cloud, nominal, job.inspection, deviations=job.deviations, spec=spec
        )
        result = run.result
        kept = result.deviation_mm[~result.outlier]
        largest = float(kept[np.argmax(np.abs(kept))]) if kept.size else None
        alignment = result.alignment
        message = f"inspection {result.verdict}, deviation rms {result.stats.rms:.4f} mm"
        if alignment.ambiguous:
            message += "; " + "; ".join(alignment.warnings)
        return JobOutcome(
            passed=result.verdict == "pass" and not alignment.ambiguous,
            results_um=(
                _mm_to_um(largest),
                _mm_to_um(result.stats.rms),
                _mm_to_um(alignment.rms_mm),
            ),
            report_path=run.report_path or run.out_path,
            artefacts=(run.out_path, job.deviations),
            message=message,
        )

    def _current_laser_origin(self) -> tuple[float, float, float] | None:
        """The laser's origin the installed calibration was given (the sensor's drawing): a
        recalibration keeps it, checked against its new light plane. One the installed
        calibration estimated from its own session is not carried over: the new session's
        estimate replaces it."""
        if not self.calibration_path.is_file():
            return None
        try:
            installed = read_calibration(self.calibration_path)
        except (InputError, ValueError):
            return None
        origin = installed.laser_origin_cam
        source = str(installed.quality.record.get("laser_origin_source", ""))
        if origin is None or source.startswith("estimated"):
            return None
        return (float(origin[0]), float(origin[1]), float(origin[2]))

    def full_calibration(self, ctx: JobContext) -> JobOutcome:
        """Calibrate from a fresh ``calibration`` session; install it only if it passes the gate.

        Results: intrinsics RMS is in pixels, so only result 1 is set: the light-plane RMS, µm.
        """
        ctx.session_path = self.source.acquire("calibration", ctx)
        ctx.check_cancelled()
        job = JobLayout.of(ctx.work_dir)
        run = _call(
            stages.calibrate,
            ctx.session_path,
            job.calibration,
            laser_origin_cam_mm=self._current_laser_origin(),
            laser_origin_strict=False,
            check_cancelled=ctx.check_cancelled,
        )
        ctx.check_cancelled()
        passed, reason, plane_um = calibration_gate(run.quality, self.config.calibration_gate)
        if run.result.calibration.light_plane is None:
            passed, reason = (
                False,
                (
                    "a camera-only calibration (the session has no laser images): the scanner "
                    "needs a light plane; the current calibration is kept"
                ),
            )
        results = (plane_um, None, None)
        if not passed:
            return JobOutcome(
                passed=False,
                results_um=results,
                artefacts=(run.calibration_path,),
                error=ErrorCode.QUALITY_GATE,
                message=reason,
            )
        kept = install_calibration(run.calibration_path, self.calibration_path)
        log.info("calibration installed at %s (previous kept as %s)", self.calibration_path, kept)
        return JobOutcome(
            passed=True,
            results_um=results,
            report_path=run.report_path or run.calibration_path,
            artefacts=(run.calibration_path,),
        )


def calibration_gate(
    quality: CalibrationQuality, gate: CalibrationGate
) -> tuple[bool, str, float | None]:
    """Judge a calibration's quality record; ``(passed, reason, light-plane RMS in µm)``.

    A figure missing from the record fails the gate (it cannot be judged).
    """
    plane_um = _mm_to_um(quality.light_plane_rms_mm)
    checks = (
        ("intrinsics RMS", quality.intrinsics_rms_px, gate.max_intrinsics_rms_px, "px"),
        ("light-plane RMS", plane_um, gate.max_light_plane_rms_um, "um"),
        ("hand-eye RMS", quality.hand_eye_rms_px, gate.max_hand_eye_rms_px, "px"),
    )
    for name, value, limit, unit in checks:
        if value is None:
            return False, f"{name} missing from the calibration's quality record", plane_um
        if value > limit:
            return False, f"{name} {value:.3g} {unit} over the limit {limit:g} {unit}", plane_um
    return True, "", plane_um
