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
"""

from __future__ import annotations

import contextlib
import csv
import glob
import hashlib
import io
import json
import logging
import os
import socket
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

from distributed import Client, Future, LocalCluster, get_worker

from metrology.plan import Plan, load_plan
from scanner import __version__
from scanner.app import stages
from scanner.core.config import resolve_config
from scanner.core.fileio import (
    InputError,
    check_outputs_apart,
    commit_together,
    write_json_atomic,
)
from scanner.core.tolerance import (
    STATUS_ERROR,
    ToleranceRow,
    spreadsheet_safe,
    verdict_of_statuses,
)
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

#: The columns of ``DIR/results.csv`` (interfaces.md §6).
RESULT_COLUMNS = tuple("session name unit nominal actual deviation lower upper status".split())
MANIFEST_FORMAT = "scanner-batch/1"
Verdict = Literal["pass", "fail", "not proven", "error", "absent"]


# --------------------------------------------------------------------------------------------
# what a batch is given and what each task returns


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
class ClusterInfo:
    """The Dask cluster a batch ran on."""

    scheduler: str
    dashboard: str | None
    workers: int
    threads: int
    local: bool


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
# the cluster


def local_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


@contextlib.contextmanager
def dask_client(
    scheduler: str | None,
    workers: int | None = None,
    dashboard_address: str = "127.0.0.1:8787",
    connect_timeout_s: float = 20.0,
) -> Iterator[tuple[Client, ClusterInfo]]:
    """A client of the scheduler at ``scheduler``, or of a local cluster of ``workers``
    processes with one thread each (default: one per core). The local cluster listens on
    127.0.0.1 only and is shut down on leaving."""
    cluster: LocalCluster | None = None
    if scheduler:
        try:
            client = Client(scheduler, timeout=connect_timeout_s)
        except (OSError, TimeoutError) as exc:
            raise OSError(
                f"{scheduler}: cannot reach the Dask scheduler ({_one_line(exc)})"
            ) from None
        try:
            client.wait_for_workers(1, timeout=connect_timeout_s)
        except (OSError, TimeoutError):
            client.close()
            raise OSError(
                f"{scheduler}: no Dask worker joined the scheduler within {connect_timeout_s:g} s"
            ) from None
    else:
        cluster = LocalCluster(
            n_workers=workers or local_cores(),
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=dashboard_address,
        )
        client = Client(cluster)
    try:
        nthreads = client.nthreads()
        services = client.scheduler_info().get("services", {})
        info = ClusterInfo(
            scheduler=str(client.scheduler.address),
            dashboard=client.dashboard_link if "dashboard" in services else None,
            workers=len(nthreads),
            threads=sum(nthreads.values()),
            local=cluster is not None,
        )
        yield client, info
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _load(client: Client, keys: set[str]) -> tuple[int, int] | None:
    """``(workers, running)``: workers in the cluster, and tasks of ``keys`` executing now
    (per worker at most its threads). None when the scheduler does not answer."""
    try:
        processing = client.processing()
        nthreads = client.nthreads()
    except (OSError, TimeoutError):  # pragma: no cover - the scheduler went away
        return None
    running = sum(
        min(sum(k in keys for k in ks), nthreads.get(w, 1)) for w, ks in processing.items()
    )
    return len(nthreads), running


# --------------------------------------------------------------------------------------------
# progress


@dataclass(frozen=True)
class BatchState:
    """Where a running batch is, for a progress display.

    ``done`` and ``failed`` count every session settled so far, ``reused`` ones (complete
    outputs of an earlier run) included; ``running``: tasks executing now (None: unknown).
    """

    total: int
    reused: int
    done: int
    failed: int
    running: int | None
    elapsed_s: float

    @property
    def seconds_left(self) -> float | None:
        """This run's throughput so far applied to the sessions left (None before the first)."""
        processed, left = self.done - self.reused, self.total - self.done
        return self.elapsed_s / processed * left if processed > 0 and left else None


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


def _outcome_of(future: Future, job: SessionJob) -> SessionOutcome:
    try:
        outcome = future.result()
    except Exception as exc:  # the worker died (KilledWorker) or the task was cancelled
        return _failed_outcome(job, f"task lost on the cluster: {_one_line(exc)}", 0.0, "")
    if not isinstance(outcome, SessionOutcome):  # pragma: no cover - a foreign task result
        return _failed_outcome(job, f"unexpected task result {type(outcome).__name__}", 0.0, "")
    return outcome


def _run_on_cluster(
    client: Client,
    jobs: Sequence[SessionJob],
    settled: dict[str, SessionOutcome],
    total: int,
    on_progress: Callable[[BatchState], None] | None,
    poll_s: float = 0.5,
    no_worker_timeout_s: float = 120.0,
) -> None:
    """Submit one task per job; add each outcome to ``settled`` as it arrives.

    Should the cluster lose every worker for ``no_worker_timeout_s``, the sessions left are
    recorded as failed rather than waited for forever.
    """
    t0 = last_worker = time.perf_counter()
    reused = len(settled)
    token = uuid.uuid4().hex[:8]
    futures = {
        client.submit(process_session, job, key=f"batch-{job.name}-{token}", pure=False): job
        for job in jobs
    }
    pending = set(futures)
    try:
        while pending:
            for f in [f for f in pending if f.done()]:
                pending.discard(f)
                outcome = _outcome_of(f, futures[f])
                settled[outcome.name] = outcome
            load = _load(client, {f.key for f in pending}) if pending else (1, 0)
            now = time.perf_counter()
            if load is None or load[0] > 0:
                last_worker = now
            elif now - last_worker > no_worker_timeout_s:
                reason = f"no Dask worker left in the cluster for {no_worker_timeout_s:g} s"
                log.warning("%s: %d session(s) not processed", reason, len(pending))
                client.cancel(list(pending))
                for f in pending:
                    settled[futures[f].name] = _failed_outcome(futures[f], reason, 0.0, "")
                pending.clear()
            if on_progress is not None:
                failed = sum(not o.ok for o in settled.values())
                running = None if load is None else load[1]
                on_progress(BatchState(total, reused, len(settled), failed, running, now - t0))
            if pending:
                time.sleep(poll_s)
    except BaseException:
        client.cancel(list(pending))
        raise


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
