"""Running one job: on a thread of the service, or in a worker process of its own.

``[jobs] worker = "process"`` (the default of ``configs/plc.toml``) runs each job in a fresh
``spawn``-ed process: it can be killed when the watchdog fires and the job does not reach its
next cancellation check within ``kill_after_s``, a crash in native code (OpenCV, Open3D) ends
the job and not the service, and a job computing in Python does not compete with the event
loop for the GIL (``benchmarks/bench_plc.py``, 50 clients polling status: once p99 467 ms with
a thread worker against ~ 6 ms idle; see docs/PLC.md for the runs).

``worker = "thread"`` runs the job in the service's own interpreter: it is what the tests use
with injected fake runners, and it is cheaper for jobs that spend their time in code that
releases the GIL. Cancellation is then cooperative only.

The child builds its runner from ``[jobs] runner`` (a name, so it can be imported there),
watches its parent and exits if the service dies, killing its process group with it (so neither
the job nor the worker pools its stages started outlive a SIGKILL of the service), and sends
back one message: the outcome, or the job error, or the error of a bug.

With ``worker = "thread"`` the pools are children of the service itself:
:func:`kill_new_children` ends those still running when the service stops. After a SIGKILL of
the service nothing in it runs any more; the pool workers must then notice by themselves (see
docs/PLC.md).
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import multiprocessing
import os
import signal
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from scanner.app.plc.config import BUILTIN_RUNNER, PlcConfig
from scanner.app.plc.jobs import (
    JobCancelled,
    JobContext,
    JobError,
    JobOutcome,
    JobRunner,
    PipelineJobs,
)
from scanner.app.plc.registers import ErrorCode

__all__ = [
    "WorkerError",
    "check_runner",
    "kill_job_processes",
    "kill_new_children",
    "load_runner",
    "new_cancel_event",
    "run_in_process",
    "run_in_thread",
]

log = logging.getLogger(__name__)

_MP = multiprocessing.get_context("spawn")
#: Job processes alive now (so that a stopping service can kill what did not stop).
_LIVE: set[multiprocessing.process.BaseProcess] = set()
_LIVE_LOCK = threading.Lock()


def kill_job_processes() -> int:
    """Kill every job process still running; return how many there were."""
    with _LIVE_LOCK:
        procs = [p for p in _LIVE if p.is_alive()]
    for proc in procs:
        log.warning("killing job process %s (pid %s)", proc.name, proc.pid)
        _kill_group(proc)
    for proc in procs:
        proc.join(5.0)
    return len(procs)


def kill_new_children(before: set[int]) -> int:
    """Kill the child processes of this process started by :mod:`multiprocessing` (the worker
    pools of jobs on threads) whose pid is not in ``before``; return how many there were."""
    procs = [p for p in multiprocessing.active_children() if p.pid not in before]
    for proc in procs:
        log.warning("killing job worker process %s (pid %s)", proc.name, proc.pid)
        proc.kill()
    for proc in procs:
        proc.join(5.0)
    return len(procs)


def child_pids() -> set[int]:
    """The pids of this process's :mod:`multiprocessing` children alive now."""
    return {p.pid for p in multiprocessing.active_children() if p.pid is not None}


def _kill_group(proc: multiprocessing.process.BaseProcess) -> None:
    """Kill a job process and the pool workers it started (its process group)."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)  # type: ignore[arg-type]
    except (AttributeError, ProcessLookupError, PermissionError, TypeError):
        proc.kill()


class WorkerError(Exception):
    """A job raised an unexpected exception in its worker process; ``str`` says which."""


def _split_runner(spec: str) -> tuple[str, str]:
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise ValueError(
            f"[jobs] runner: expected {BUILTIN_RUNNER!r} or 'package.module:factory', got {spec!r}"
        )
    return module_name, attr


def check_runner(spec: str) -> None:
    """Refuse a runner ``spec`` whose module cannot be found, without importing it.

    The service calls it when it starts, so a misspelt ``[jobs] runner`` is one line at start
    rather than an internal error at the first job (a job process imports the module itself).

    Raises
    ------
    ValueError
        ``"[jobs] runner: expected an importable module, got ..."``.
    """
    if spec == BUILTIN_RUNNER:
        return
    module_name, _ = _split_runner(spec)
    try:
        found = importlib.util.find_spec(module_name) is not None
        reason = f"no module named {module_name!r}"
    except (ImportError, ValueError) as exc:  # a parent package is missing or broken
        found, reason = False, str(exc)
    if not found:
        raise ValueError(f"[jobs] runner: expected an importable module, got {spec!r} ({reason})")


def load_runner(spec: str, config: PlcConfig) -> JobRunner:
    """Build the job runner ``spec``: ``"pipeline"`` (the real stages) or a plug-in's
    ``"package.module:factory"``, called with the config.

    Raises
    ------
    ValueError
        The module cannot be imported or does not define the factory.
    """
    if spec == BUILTIN_RUNNER:
        return PipelineJobs(config)
    module_name, attr = _split_runner(spec)
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(
            f"[jobs] runner: expected an importable module, got {spec!r} ({exc})"
        ) from None
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise ValueError(
            f"[jobs] runner: expected {module_name!r} to define the factory {attr!r}, got "
            f"{'nothing' if factory is None else type(factory).__name__} by that name"
        )
    return factory(config)


def new_cancel_event(worker: str) -> Any:
    """A cancellation flag that crosses into the job: a process-shared one for processes."""
    return _MP.Event() if worker == "process" else threading.Event()


def run_in_thread(runner: JobRunner, method: str, ctx: JobContext) -> JobOutcome:
    """Run the job here (the caller's thread)."""
    ctx.work_dir.mkdir(parents=True, exist_ok=True)
    return getattr(runner, method)(ctx)


def _exit_with_parent(parent: int) -> None:
    def watch() -> None:
        while True:
            time.sleep(0.5)
            if os.getppid() != parent:
                # The service died (SIGKILL): take the job's worker pools with us. The job is
                # the leader of its own process group (set in _child_main), they are in it.
                if hasattr(os, "killpg") and os.getpgrp() == os.getpid():
                    os.killpg(os.getpgrp(), signal.SIGKILL)
                os._exit(3)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _child_main(
    config: PlcConfig, method: str, ctx: JobContext, conn: Connection, parent: int, level: int
) -> None:
    _exit_with_parent(parent)
    # The job and the worker pools its stages start form one process group, so that a kill
    # reaches them all (no pool worker outlives a killed job).
    if hasattr(os, "setpgrp"):
        os.setpgrp()
    # The service decides when a job stops (it cancels, then kills): Ctrl-C on the terminal or
    # SIGTERM to the whole control group must not kill the job behind its back.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # Log like the service: same level, same format, to the same standard error.
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    message: tuple[Any, ...]
    try:
        runner = load_runner(config.jobs.runner, config)
        message = ("ok", run_in_thread(runner, method, ctx))
    except JobCancelled:
        message = ("cancelled",)
    except JobError as exc:
        message = ("job_error", int(exc.code), exc.message)
    except BaseException as exc:
        logging.getLogger(__name__).exception("job %d failed", ctx.job_id)
        message = ("error", f"{type(exc).__name__}: {exc}")
    session = None if ctx.session_path is None else str(ctx.session_path)
    try:
        conn.send((message, session))
    finally:
        conn.close()


def run_in_process(
    config: PlcConfig, method: str, ctx: JobContext, kill_after_s: float = 2.0
) -> JobOutcome:
    """Run the job in a new process and wait for it (call on a thread, it blocks).

    ``ctx.cancel`` must come from :func:`new_cancel_event` with ``"process"``. Once it is set,
    the child has ``kill_after_s`` to stop on its own before it is killed.

    Raises
    ------
    JobCancelled
        The job was cancelled (it stopped, or was killed).
    JobError
        The job's own error, or INTERNAL when the process died without an answer.
    WorkerError
        The job raised anything else.
    """
    receiver, sender = _MP.Pipe(duplex=False)
    proc = _MP.Process(
        target=_child_main,
        args=(config, method, ctx, sender, os.getpid(), logging.getLogger().getEffectiveLevel()),
        name=f"plc-job-{ctx.job_id}",
        # Not a daemon: a job's stages start worker pools of their own, which a daemonic
        # process may not. The service still never leaves it behind: the child watches its
        # parent, and the service kills the job's whole process group when it stops.
        daemon=False,
    )
    proc.start()
    with _LIVE_LOCK:
        _LIVE.add(proc)
    sender.close()
    reply: tuple[Any, ...] | None = None
    cancelled_at: float | None = None
    try:
        while reply is None:
            if receiver.poll(0.05):
                try:
                    reply = receiver.recv()
                except EOFError:  # the child died without answering
                    break
                continue
            if not proc.is_alive() and not receiver.poll(0):
                break
            if ctx.cancel.is_set():
                cancelled_at = cancelled_at or time.monotonic()
                if time.monotonic() - cancelled_at > kill_after_s:
                    log.warning("job %d did not stop: killing its process", ctx.job_id)
                    _kill_group(proc)
                    break
    finally:
        receiver.close()
        proc.join(5.0)
        if proc.is_alive():
            _kill_group(proc)
            proc.join(5.0)
        with _LIVE_LOCK:
            _LIVE.discard(proc)
    if reply is None:
        if ctx.cancel.is_set():
            raise JobCancelled(f"job {ctx.job_id} cancelled (worker process stopped)")
        raise JobError(
            ErrorCode.INTERNAL, f"worker process died without a result (exit code {proc.exitcode})"
        )
    message, session = reply
    if session is not None:
        ctx.session_path = Path(session)
    kind = message[0]
    if kind == "ok":
        return message[1]
    if kind == "cancelled":
        raise JobCancelled(f"job {ctx.job_id} cancelled")
    if kind == "job_error":
        raise JobError(ErrorCode(message[1]), message[2])
    raise WorkerError(message[1])
