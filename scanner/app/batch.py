"""Batch reprocessing of stored sweep sessions on Dask (``scanner batch``, interfaces.md §6).

Each session is one Dask task that runs the stage layer, :func:`scanner.app.stages.scan` then
:func:`scanner.app.stages.measure`, into ``DIR/<session name>/`` (the artefact names of
:class:`~scanner.formats.layout.JobLayout`), so its numbers are those of ``scanner scan``
followed by ``scanner measure`` on that session alone. Inside a task the scan runs in the
worker's own process (``ScanOptions(workers=1)``): the cluster, not the scan, spreads the work
over the cores.

A session's outputs are complete when ``measure.json``, ``.csv`` and ``.html`` are there: they
are written together (:func:`scanner.core.fileio.commit_together`) after the cloud, and
removed before a session is processed again, so a batch stopped half-way and started again
skips exactly the sessions that finished. ``DIR/batch.json`` records the calibration, plan and
stripe mode the folder was made with; a restart with other inputs is refused unless
``redo`` is given.

The runner writes ``DIR/results.csv`` (every session's ``measure.csv`` rows, the session's name
first; a session that could not be measured gets ``error`` rows) and ``DIR/summary.json``;
``scanner batch --compare`` adds ``DIR/compare.csv``.

One session's task is in :mod:`scanner.app.batch_session`, the Dask client and the run of the
tasks on it in :mod:`scanner.app.batch_cluster`; this module checks the inputs, runs the batch
and writes its files.
"""

from __future__ import annotations

import csv
import glob
import hashlib
import io
import json
import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

from metrology.plan import Plan, load_plan
from scanner import __version__
from scanner.app.batch_cluster import BatchState, ClusterInfo, _run_on_cluster, dask_client
from scanner.app.batch_session import (
    RESULT_COLUMNS,
    ResultRow,
    SessionJob,
    SessionOutcome,
    Verdict,
    _report_files,
    outputs_complete,
    process_session,
    stored_outcome,
    verdict_of,
)
from scanner.core.config import resolve_config
from scanner.core.fileio import (
    InputError,
    check_outputs_apart,
    commit_together,
    write_json_atomic,
)
from scanner.core.tolerance import STATUS_ERROR, ToleranceRow, spreadsheet_safe
from scanner.formats.calibration_file import read_calibration
from scanner.formats.layout import JobLayout
from scanner.scanning.pipeline import ScanOptions

__all__ = [
    "RESULT_COLUMNS",
    "BatchRequest",
    "BatchRun",
    "BatchState",
    "BatchSummary",
    "ClusterInfo",
    "FailedSession",
    "ResultRow",
    "SessionJob",
    "SessionOutcome",
    "Verdict",
    "dask_client",
    "expand_sessions",
    "outputs_complete",
    "process_session",
    "run_batch",
    "verdict_of",
]

log = logging.getLogger(__name__)

MANIFEST_FORMAT = "scanner-batch/1"


# --------------------------------------------------------------------------------------------
# what a batch is given and what it writes


@dataclass(frozen=True)
class BatchRequest:
    """What ``scanner batch`` was asked to do.

    Attributes
    ----------
    sessions : sequence of str or path
        Sweep session folders, or globs (see :func:`expand_sessions`).
    calibration, plan : path; str or path
        The calibration file; the inspection plan (a TOML path or a ``configs/plans`` name).
    out_dir : path
        ``DIR``: one folder per session, ``results.csv``, ``summary.json``.
    scheduler : str, optional
        Address of a running Dask scheduler (``tcp://host:8786``); None: a local cluster.
    workers : int, optional
        Worker processes of the local cluster (default: this machine's cores).
    mode : {"fast", "precise"}
        Stripe estimator (``scanner scan --mode``; fast by default, as there).
    redo : bool
        Process every session again, even those whose outputs are complete.
    dashboard_address : str
        Where the local cluster serves its dashboard (a busy port falls back to a free one).
    """

    sessions: Sequence[str | os.PathLike[str]]
    calibration: Path
    plan: str | Path
    out_dir: Path
    scheduler: str | None = None
    workers: int | None = None
    mode: str = "fast"
    redo: bool = False
    dashboard_address: str = "127.0.0.1:8787"


@dataclass(frozen=True)
class FailedSession:
    session: str
    reason: str


@dataclass(frozen=True)
class SessionRecord:
    """One session's line in ``summary.json``."""

    session: str
    path: str
    status: Literal["ok", "failed"]
    verdict: Verdict
    reused: bool
    seconds: float
    points: int | None
    worker: str


@dataclass(frozen=True)
class BatchSummary:
    """``DIR/summary.json``: counts, failures with their reasons, timing and inputs."""

    sessions: int
    ok: int
    failed: tuple[FailedSession, ...]
    passed: int
    out_of_tolerance: tuple[str, ...]
    processed: int
    reused: int
    seconds: float
    task_seconds: float
    calibration: str
    plan: str
    mode: str
    cluster: ClusterInfo | None
    scanner_version: str
    created_utc: str
    per_session: tuple[SessionRecord, ...]
    not_proven: tuple[str, ...] = ()
    """Sessions whose measurements passed none failing but some not proven (guarded rule)."""

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class BatchRun:
    """A finished batch: the summary, every session's outcome and the files written."""

    summary: BatchSummary
    outcomes: tuple[SessionOutcome, ...]
    results_path: Path
    summary_path: Path


# --------------------------------------------------------------------------------------------
# inputs


def expand_sessions(items: Sequence[str | os.PathLike[str]]) -> list[Path]:
    """Session folders from the command line: paths as given, globs expanded (sorted).

    Raises
    ------
    InputError
        A path that is not a folder, or a pattern that matches no folder.
    """
    if not items:
        raise ValueError("sessions: expected at least one sweep session folder, got none")
    out: list[Path] = []
    for item in items:
        p = Path(item)
        text = str(item)
        if not p.exists() and any(c in text for c in "*?["):
            matches = [Path(m) for m in sorted(glob.glob(text)) if Path(m).is_dir()]
            if not matches:
                raise InputError(p, "no session folder matches this pattern")
            out += matches
        elif not p.exists():
            raise InputError(p, "session folder not found")
        elif not p.is_dir():
            raise InputError(p, "not a folder (expected a sweep session folder)")
        else:
            out.append(p)
    return out


def _unique_names(sessions: Sequence[Path]) -> list[str]:
    seen: dict[str, Path] = {}
    for s in sessions:
        name = s.resolve().name
        if name in seen and seen[name].resolve() == s.resolve():
            raise InputError(s, "session given twice")
        if name in seen:
            raise InputError(
                s,
                f"two sessions are named {name!r} (the other is {seen[name]}); their outputs "
                "would share one folder: rename one",
            )
        seen[name] = s
    return list(seen)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass(frozen=True)
class BatchManifest:
    """``DIR/batch.json``: the inputs every session of the folder was processed with."""

    calibration_sha256: str
    plan_sha256: str
    mode: str
    format: str = MANIFEST_FORMAT

    @classmethod
    def read(cls, path: Path) -> BatchManifest | None:
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            return cls(**{k: data[k] for k in ("calibration_sha256", "plan_sha256", "mode")})
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def differs_from(self, other: BatchManifest) -> str:
        """What ``other`` was made with differently (empty: the same)."""
        what = [
            name
            for name, a, b in (
                ("calibration", self.calibration_sha256, other.calibration_sha256),
                ("plan", self.plan_sha256, other.plan_sha256),
                ("stripe mode", self.mode, other.mode),
            )
            if a != b
        ]
        return " and ".join(what)


def _plan_rows(plan: Plan) -> tuple[ResultRow, ...]:
    rows = []
    for m in plan.measurements:
        lower, upper = m.bounds
        row = ToleranceRow(
            m.name, m.nominal_value, None, lower, upper, unit=m.unit, status=STATUS_ERROR
        )
        rows.append(ResultRow.from_tolerance_row(row))
    return tuple(rows)


@dataclass(frozen=True)
class _Prepared:
    jobs: tuple[SessionJob, ...]
    manifest: BatchManifest
    calibration: Path
    plan: Path


def prepare(request: BatchRequest) -> _Prepared:
    """Check every input before any work (one-line :class:`InputError`), build the jobs."""
    sessions = [s.resolve() for s in expand_sessions(request.sessions)]
    names = _unique_names(sessions)
    calibration = Path(request.calibration).resolve()
    read_calibration(calibration).require_light_plane(calibration, "scanning")
    plan_path = resolve_config(request.plan, "plans").resolve()
    plan = load_plan(plan_path)
    out_dir = Path(request.out_dir).resolve()
    layouts = [JobLayout.of(out_dir / n) for n in names]
    check_outputs_apart(
        [*sessions, calibration, plan_path],
        [out_dir / "results.csv", *(lay.cloud for lay in layouts)],
    )
    options = ScanOptions(mode=request.mode, workers=1)
    rows = _plan_rows(plan)
    jobs = tuple(
        SessionJob(n, s, calibration, plan_path, lay, options, rows)
        for n, s, lay in zip(names, sessions, layouts)
    )
    manifest = BatchManifest(_sha256(calibration), _sha256(plan_path), request.mode)
    return _Prepared(jobs, manifest, calibration, plan_path)


def _check_manifest(path: Path, manifest: BatchManifest, redo: bool) -> None:
    """Refuse to mix the results of other inputs into a folder (unless all are redone)."""
    before = BatchManifest.read(path) if path.is_file() else None
    if before is not None and not redo and (diff := before.differs_from(manifest)):
        raise InputError(
            path,
            f"this folder was made with another {diff}: pass --redo to process every "
            "session again, or choose another --out",
        )


def _record_manifest(path: Path, manifest: BatchManifest, redo: Sequence[SessionJob]) -> None:
    """Mark the sessions to redo incomplete, then record the inputs: a redo stopped half-way
    cannot leave sessions of the old inputs looking done under the new record."""
    for job in redo:
        for stale in _report_files(job.layout):
            stale.unlink(missing_ok=True)
    write_json_atomic(path, asdict(manifest))


# --------------------------------------------------------------------------------------------
# results and summary


def _rows_csv(outcomes: Sequence[SessionOutcome]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(RESULT_COLUMNS)
    for o in outcomes:
        for r in o.rows:
            # The row's cells are measure.csv's text, already safe; the session's name is ours.
            writer.writerow(
                [spreadsheet_safe(o.name), *(getattr(r, c) for c in RESULT_COLUMNS[1:])]
            )
    return buf.getvalue()


def _summary(
    outcomes: Sequence[SessionOutcome],
    prepared: _Prepared,
    mode: str,
    cluster: ClusterInfo | None,
    seconds: float,
) -> BatchSummary:
    return BatchSummary(
        sessions=len(outcomes),
        ok=sum(o.ok for o in outcomes),
        failed=tuple(FailedSession(o.name, o.reason) for o in outcomes if not o.ok),
        passed=sum(o.verdict == "pass" for o in outcomes),
        out_of_tolerance=tuple(o.name for o in outcomes if o.verdict == "fail"),
        not_proven=tuple(o.name for o in outcomes if o.verdict == "not proven"),
        processed=sum(not o.reused for o in outcomes),
        reused=sum(o.reused for o in outcomes),
        seconds=round(seconds, 3),
        task_seconds=round(sum(o.seconds for o in outcomes if not o.reused), 3),
        calibration=str(prepared.calibration),
        plan=str(prepared.plan),
        mode=mode,
        cluster=cluster,
        scanner_version=__version__,
        created_utc=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        per_session=tuple(
            SessionRecord(
                o.name,
                o.path,
                "ok" if o.ok else "failed",
                o.verdict,
                o.reused,
                round(o.seconds, 3),
                o.points,
                o.worker,
            )
            for o in outcomes
        ),
    )


# --------------------------------------------------------------------------------------------
# the run


def run_batch(
    request: BatchRequest,
    *,
    on_cluster: Callable[[ClusterInfo], None] | None = None,
    on_progress: Callable[[BatchState], None] | None = None,
) -> BatchRun:
    """Scan and measure every session of ``request`` on Dask; write the batch's files.

    Parameters
    ----------
    request : BatchRequest
    on_cluster : callable, optional
        Called with the cluster's description once it is up (to print its dashboard).
    on_progress : callable, optional
        Called about twice a second while sessions run, with where the batch is.

    Raises
    ------
    InputError
        Bad input, before any session is processed: a missing session folder, two sessions
        of the same name, an unreadable calibration or plan, outputs that would replace an
        input, or a folder made with other inputs (without ``redo``).
    OSError
        The scheduler cannot be reached.
    """
    t0 = time.perf_counter()
    if request.workers is not None and request.workers < 1:
        raise ValueError(f"--workers: expected >= 1, got {request.workers}")
    if request.scheduler and request.workers is not None:
        raise ValueError("--workers: sizes the local cluster; it cannot go with --scheduler")
    prepared = prepare(request)
    out_dir = Path(request.out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    manifest_path = out_dir / "batch.json"
    _check_manifest(manifest_path, prepared.manifest, request.redo)

    settled: dict[str, SessionOutcome] = {}
    todo: list[SessionJob] = []
    for job in prepared.jobs:
        if not request.redo and outputs_complete(job.layout):
            try:
                settled[job.name] = stored_outcome(job, reused=True)
                continue
            except (OSError, ValueError, KeyError, TypeError) as exc:
                log.info("%s: outputs unreadable, processing again (%s)", job.name, exc)
        todo.append(job)
    log.info("%d sessions, %d to process, %d reused", len(prepared.jobs), len(todo), len(settled))

    cluster: ClusterInfo | None = None
    if todo:
        with dask_client(request.scheduler, request.workers, request.dashboard_address) as (
            client,
            cluster,
        ):
            if on_cluster is not None:
                on_cluster(cluster)
            _record_manifest(manifest_path, prepared.manifest, todo if request.redo else ())
            _run_on_cluster(client, todo, settled, len(prepared.jobs), on_progress)

    else:
        _record_manifest(manifest_path, prepared.manifest, ())
    outcomes = tuple(settled[j.name] for j in prepared.jobs)
    summary = _summary(outcomes, prepared, request.mode, cluster, time.perf_counter() - t0)
    results_path, summary_path = out_dir / "results.csv", out_dir / "summary.json"
    with commit_together() as staged:
        staged(results_path).write_text(_rows_csv(outcomes), encoding="utf-8")
        write_json_atomic(staged(summary_path), summary.to_json())
    return BatchRun(summary, outcomes, results_path, summary_path)
