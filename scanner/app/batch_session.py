"""One session of a batch: the job a Dask task is given, the outcome it returns, and the task
itself (:func:`process_session`, run on a worker: the stage layer's scan then measure into the
session's folder), with an outcome read back from complete outputs (a restart's reuse)."""

from __future__ import annotations

import csv
import json
import logging
import socket
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from distributed import get_worker

from scanner.app import stages
from scanner.core.tolerance import ToleranceRow, verdict_of_statuses
from scanner.formats.layout import JobLayout
from scanner.scanning.pipeline import ScanOptions

log = logging.getLogger(__name__)

#: The columns of ``DIR/results.csv`` (interfaces.md §6).
RESULT_COLUMNS = tuple("session name unit nominal actual deviation lower upper status".split())
Verdict = Literal["pass", "fail", "not proven", "error", "absent"]


# --------------------------------------------------------------------------------------------
# what each task is given and returns


@dataclass(frozen=True)
class SessionJob:
    """One task: scan ``session_dir`` and measure the cloud into ``layout.root``."""

    name: str
    session_dir: Path
    calibration: Path
    plan: Path
    layout: JobLayout
    options: ScanOptions
    plan_rows: tuple[ResultRow, ...]
    """The plan's measurements as ``error`` rows, for a session that could not be measured."""


@dataclass(frozen=True)
class ResultRow:
    """One measurement of one session, as text exactly as ``scanner measure`` wrote it."""

    name: str
    unit: str
    nominal: str
    actual: str
    deviation: str
    lower: str
    upper: str
    status: str

    @classmethod
    def from_tolerance_row(cls, row: ToleranceRow) -> ResultRow:
        """A row written the way :func:`metrology.report.write_rows_csv` writes it."""
        j = row.to_json()
        text = {k: "" if j[k] is None else str(j[k]) for k in RESULT_COLUMNS[1:]}
        return cls(**text)


@dataclass(frozen=True)
class SessionOutcome:
    """What became of one session.

    ``ok`` is False when the session could not be scanned or measured, or when a feature of
    the plan could not be fitted (``reason`` says which and why; its outputs are still
    written). ``reused``: complete outputs of an earlier run were kept.
    """

    name: str
    path: str
    ok: bool
    reason: str = ""
    rows: tuple[ResultRow, ...] = ()
    points: int | None = None
    seconds: float = 0.0
    worker: str = ""
    reused: bool = False

    @property
    def verdict(self) -> Verdict:
        return verdict_of(self.rows)


def verdict_of(rows: Sequence[ResultRow]) -> Verdict:
    """``absent`` without rows, else :func:`~scanner.core.tolerance.verdict_of_statuses`."""
    return verdict_of_statuses({r.status for r in rows}) if rows else "absent"


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    if isinstance(exc, ValueError | OSError) and text:
        return text
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


# --------------------------------------------------------------------------------------------
# the task (runs on a Dask worker)


def _read_rows(csv_path: Path) -> tuple[ResultRow, ...]:
    with open(csv_path, encoding="utf-8", newline="") as fh:
        return tuple(
            ResultRow(**{k: row[k] for k in RESULT_COLUMNS[1:]}) for row in csv.DictReader(fh)
        )


@dataclass(frozen=True)
class _StoredMeasure:
    """What a restart needs from a session's ``measure.json``: points and failed fits."""

    points: int | None
    failed_fits: tuple[str, ...]

    @classmethod
    def read(cls, path: Path) -> _StoredMeasure:
        data = json.loads(path.read_text(encoding="utf-8"))
        failed = tuple(
            f"feature {f['name']!r}: {f['fit'].get('reason', 'fit failed')}"
            for f in data.get("features", [])
            if not f.get("fit", {}).get("ok", True)
        )
        return cls(data.get("cloud", {}).get("n_points"), failed)


def _report_files(layout: JobLayout) -> tuple[Path, Path, Path]:
    return layout.measure, layout.measure.with_suffix(".csv"), layout.measure.with_suffix(".html")


def outputs_complete(layout: JobLayout) -> bool:
    """Whether a session folder holds the cloud and the whole measurement report."""
    return all(p.is_file() for p in (layout.cloud, *_report_files(layout)))


def stored_outcome(
    job: SessionJob, *, reused: bool, seconds: float = 0.0, worker: str = ""
) -> SessionOutcome:
    """A session's outcome read back from its complete outputs."""
    json_path, csv_path, _ = _report_files(job.layout)
    stored = _StoredMeasure.read(json_path)
    return SessionOutcome(
        name=job.name,
        path=str(job.session_dir),
        ok=not stored.failed_fits,
        reason="; ".join(stored.failed_fits),
        rows=_read_rows(csv_path),
        points=stored.points,
        seconds=seconds,
        worker=worker,
        reused=reused,
    )


def _failed_outcome(job: SessionJob, reason: str, seconds: float, worker: str) -> SessionOutcome:
    return SessionOutcome(
        name=job.name,
        path=str(job.session_dir),
        ok=False,
        reason=reason,
        rows=job.plan_rows,
        seconds=seconds,
        worker=worker,
    )


def process_session(job: SessionJob) -> SessionOutcome:
    """Scan and measure one session through the stage layer (a Dask task; never raises).

    The report files are removed first, so they are complete only once this run's are.
    """
    t0 = time.perf_counter()
    try:
        worker = str(get_worker().address)
    except ValueError:  # called outside a Dask worker
        worker = socket.gethostname()
    try:
        for stale in _report_files(job.layout):
            stale.unlink(missing_ok=True)
        stages.scan([job.session_dir], job.calibration, job.layout.cloud, options=job.options)
        stages.measure(job.layout.cloud, job.plan, job.layout.measure)
        return stored_outcome(job, reused=False, seconds=time.perf_counter() - t0, worker=worker)
    except Exception as exc:
        log.info("session %s failed: %s", job.name, _one_line(exc))
        return _failed_outcome(job, _one_line(exc), time.perf_counter() - t0, worker)
