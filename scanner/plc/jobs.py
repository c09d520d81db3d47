"""What the PLC service runs: the job interface, session sources and the pipeline jobs.

The service does not know how a check, a scan or a calibration is computed. It calls a
:class:`JobRunner`: three functions taking a :class:`JobContext` and returning a
:class:`JobOutcome` or raising :class:`JobError` with an :class:`ErrorCode`. The default
runner, :class:`PipelineJobs`, captures a session from a :class:`SessionSource` and calls the
pipeline (imported lazily, so the service starts even while a stage is missing, and a missing
stage is a recorded job error rather than a crash). Tests inject fake runners.

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from scanner.fileio import InputError
from scanner.plc.config import CheckTolerances, PlcConfig, Recipe, SourceConfig
from scanner.plc.registers import ErrorCode

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
    "install_calibration",
    "make_source",
]

log = logging.getLogger(__name__)


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
    """Each job captures a fresh session from the virtual cell (``scanner.virtual_cell``)."""

    cell: str = "default"
    seed: int = 0

    def acquire(self, kind: str, ctx: JobContext, recipe: Recipe | None = None) -> Path:
        try:
            from scanner.virtual_cell import simulate_cell
        except ImportError as exc:
            raise JobError(ErrorCode.INTERNAL, f"virtual cell not available: {exc}") from None
        out = ctx.work_dir / "session"
        kwargs: dict[str, Any] = {"kind": kind, "seed": self.seed + ctx.job_id}
        if recipe is not None and recipe.object:
            kwargs["object"] = recipe.object
        result = _call(simulate_cell, self.cell, out, **kwargs)
        path = Path(getattr(result, "session_path", None) or getattr(result, "path", None) or out)
        return path


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


def _call(func: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """Call a pipeline function, turning bad input into the job error the PLC reads."""
    try:
        return func(*args, **kwargs)
    except (JobError, JobCancelled):
        raise
    except InputError as exc:
        raise JobError(ErrorCode.BAD_INPUT, str(exc)) from exc
    except FileNotFoundError as exc:
        raise JobError(ErrorCode.BAD_INPUT, str(exc)) from exc


def _mm_to_um(value: Any) -> float | None:
    return None if value is None else float(value) * 1000.0


def check_passed(results_um: tuple[float | None, ...], tol: CheckTolerances) -> bool:
    """Whether the three check figures (µm) are all known and within ``tol``."""
    limits = (tol.max_mean_abs_um, tol.max_abs_um, tol.max_o_spread_um)
    return all(v is not None and abs(v) <= lim for v, lim in zip(results_um, limits))


class PipelineJobs:
    """The real jobs: capture a session, then call the pipeline stages.

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
        from metrology.ef_check import run_ef_check

        out = ctx.work_dir / "ef_check.json"
        result = _call(run_ef_check, ctx.session_path, calibration, out)
        results = (
            _mm_to_um(getattr(result, "mean_abs_error_mm", None)),
            _mm_to_um(getattr(result, "max_abs_error_mm", None)),
            _mm_to_um(getattr(result, "o_spread_mm", None)),
        )
        report = getattr(result, "report_path", None)
        return JobOutcome(
            passed=check_passed(results, self.config.check),
            results_um=results,
            report_path=Path(report) if report else out,
            artefacts=(out,),
        )

    def scan(self, ctx: JobContext) -> JobOutcome:
        """Scan the object of the recipe in register 3 and measure its inspection plan."""
        recipe = self.config.recipe(ctx.parameter)
        if recipe is None:
            known = ", ".join(str(r.number) for r in self.config.recipes) or "none"
            raise JobError(
                ErrorCode.UNKNOWN_RECIPE,
                f"expected a recipe number ({known}), got {ctx.parameter}",
            )
        calibration = self._require_calibration()
        ctx.session_path = self.source.acquire("sweep", ctx, recipe)
        ctx.check_cancelled()
        from scanner.scanning.pipeline import scan_session

        cloud = ctx.work_dir / "cloud.ply"
        _call(scan_session, ctx.session_path, calibration, cloud)
        ctx.check_cancelled()
        from metrology.measure import measure_cloud

        report = ctx.work_dir / "measurement.json"
        result = _call(measure_cloud, cloud, recipe.plan, report)
        figures = list(getattr(result, "results_um", ()) or ())[:3]
        figures += [None] * (3 - len(figures))
        passed = bool(getattr(result, "passed", False))
        report_path = getattr(result, "report_path", None)
        return JobOutcome(
            passed=passed,
            results_um=(figures[0], figures[1], figures[2]),
            report_path=Path(report_path) if report_path else report,
            artefacts=(cloud, report),
        )

    def full_calibration(self, ctx: JobContext) -> JobOutcome:
        """Calibrate from a fresh ``calibration`` session; install it only if it passes."""
        ctx.session_path = self.source.acquire("calibration", ctx)
        ctx.check_cancelled()
        from calibration.pipeline import calibrate_session

        new = ctx.work_dir / "calibration.json"
        result = _call(calibrate_session, ctx.session_path, new)
        ctx.check_cancelled()
        passed = bool(getattr(result, "passed", True))
        report_path = getattr(result, "report_path", None)
        report = Path(report_path) if report_path else None
        if not passed:
            reason = getattr(result, "reason", "") or "quality gate failed"
            return JobOutcome(
                passed=False,
                report_path=report,
                artefacts=(new,),
                error=ErrorCode.QUALITY_GATE,
                message=str(reason),
            )
        kept = install_calibration(new, self.calibration_path)
        log.info("calibration installed at %s (previous kept as %s)", self.calibration_path, kept)
        return JobOutcome(passed=True, report_path=report, artefacts=(new,))
