"""The Dask side of a batch: a client of a scheduler or of a local cluster (:func:`dask_client`),
and the sessions' tasks run on it (:func:`_run_on_cluster`), each outcome taken as it arrives,
with where the batch is (:class:`BatchState`) for a progress display."""

from __future__ import annotations

import contextlib
import logging
import os
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

from distributed import Client, Future, LocalCluster

from scanner.app.batch_session import (
    SessionJob,
    SessionOutcome,
    _failed_outcome,
    _one_line,
    process_session,
)

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# the cluster


@dataclass(frozen=True)
class ClusterInfo:
    """The Dask cluster a batch ran on."""

    scheduler: str
    dashboard: str | None
    workers: int
    threads: int
    local: bool


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
# the tasks on the cluster


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
