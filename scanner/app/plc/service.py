"""The PLC service: the register bank, the handshake, jobs on a worker thread, the watchdog.

:class:`PlcService` is the :class:`~scanner.app.plc.modbus.RegisterBank` behind the Modbus server
and implements the handshake of ``shared/spec/interfaces.md`` section 4:

* A write touching register 0 or 1 whose command is not 0 and whose sequence number is
  neither 0 nor the one last accepted (register 101) is a *new command*. While BUSY it is
  refused with exception 6 and changes nothing; an unknown command (register 0 outside 0..4)
  is refused with exception 3 and changes nothing. Otherwise the write is stored, the job is
  inserted in the history (so it can never be lost), BUSY is set, DONE, RESULT_VALID, PASS
  and ERROR are cleared, results read invalid, 101 acknowledges the number and 111-112 hold
  the job id -- all before the answer to that write is sent.
* A write repeating the sequence number last accepted is stored and executes nothing, so a
  PLC retry never runs a job twice. The last accepted number survives a restart (it is read
  back from the history).
* When the job ends, results (105-110) are written first, then the status: DONE with
  RESULT_VALID (and PASS when it passed), or ERROR with the code in 102. Both happen in one
  event-loop step, so no reader ever sees one without the other.

Jobs run on a daemon worker thread so reads, the heartbeat (104, every second) and the
watchdog keep going. The watchdog cancels a job when the PLC heartbeat (register 2) has not
changed for ``heartbeat_timeout_s`` (error 5) or the job runs longer than ``job_timeout_s``
(error 9); cancellation is cooperative (:meth:`JobContext.check_cancelled`), so BUSY stays set
until the job reaches its next check. On stop (SIGTERM), a running job is cancelled and, if it
does not stop within ``shutdown_grace_s``, recorded ``interrupted`` (error 7); a job found
``running`` in the history at start (the service was killed) is recorded the same way.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scanner.app.plc.config import PlcConfig, check_host
from scanner.app.plc.history import JobHistory, JobRecord
from scanner.app.plc.jobs import JobCancelled, JobContext, JobError, JobOutcome, JobRunner
from scanner.app.plc.modbus import ExceptionCode, ModbusException
from scanner.app.plc.registers import (
    PLC_FIRST,
    PLC_LAST,
    SCANNER_FIRST,
    SCANNER_LAST,
    WORD_ORDER_PROBE,
    Command,
    ErrorCode,
    Reg,
    State,
    Status,
    int32_to_words,
    micrometres_to_int32,
    uint32_to_words,
)
from scanner.app.plc.server import ModbusTcpServer
from scanner.app.plc.worker import (
    WorkerError,
    check_runner,
    child_pids,
    kill_job_processes,
    kill_new_children,
    load_runner,
    new_cancel_event,
    run_in_process,
    run_in_thread,
)
from scanner.core.fileio import InputError

__all__ = ["PlcService", "load_runner", "serve"]

# load_runner lives in scanner.app.plc.worker; re-exported for callers of the service.

log = logging.getLogger(__name__)

_JOB_COMMANDS = {
    Command.CHECK: "recalibration_check",
    Command.SCAN: "scan",
    Command.CALIBRATE: "full_calibration",
}


@dataclass
class _RunningJob:
    ctx: JobContext
    started: float
    cancel_reason: ErrorCode | None = None
    done: asyncio.Event = field(default_factory=asyncio.Event)


class PlcService:
    """The scanner side of the register map and the handshake.

    Parameters
    ----------
    config : PlcConfig
        Limits, storage paths, recipes.
    runner : JobRunner or None
        The check, scan and calibration jobs, run on a thread; ``None`` with
        ``[jobs] worker = "process"``, where each job process builds its own from the config.
    history : JobHistory
        Where every job is recorded.
    clock : callable, optional
        Monotonic seconds (tests may pass their own).
    """

    def __init__(
        self,
        config: PlcConfig,
        runner: JobRunner | None,
        history: JobHistory,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if (runner is None) == (config.jobs.worker == "thread"):
            raise ValueError(
                f"expected a runner object with worker = 'thread' and none with 'process', got "
                f"{type(runner).__name__} with {config.jobs.worker!r}"
            )
        self.config = config
        self.runner = runner
        self.history = history
        self.clock = clock
        self.regs = [0] * (SCANNER_LAST + 1)
        self.job: _RunningJob | None = None
        self._hb_changed_at = clock()
        self._tasks: list[asyncio.Task[Any]] = []
        self._job_tasks: set[asyncio.Task[Any]] = set()
        self._stopping = False
        #: Child processes that existed when the service started (not the jobs' pools);
        #: ``None`` until :meth:`start`.
        self._children_before: set[int] | None = None
        self._set_words(Reg.PROBE, int32_to_words(WORD_ORDER_PROBE))
        self._set_results((None, None, None))
        self._restore()

    # ---------------------------------------------------------------------------------------
    # register bank (called on the event loop thread)

    @property
    def busy(self) -> bool:
        return self.job is not None

    def read_registers(self, address: int, count: int) -> list[int]:
        """Registers ``address .. address+count-1``; both blocks readable, nothing between."""
        end = address + count - 1
        if not (PLC_FIRST <= address and end <= PLC_LAST) and not (
            SCANNER_FIRST <= address and end <= SCANNER_LAST
        ):
            raise ModbusException(
                ExceptionCode.ILLEGAL_DATA_ADDRESS,
                f"expected a range inside {PLC_FIRST}-{PLC_LAST} or "
                f"{SCANNER_FIRST}-{SCANNER_LAST}, got {address}-{end}",
            )
        return self.regs[address : end + 1]

    def write_registers(self, address: int, values: list[int]) -> None:
        """A PLC write to 0-9, with the handshake; anything else is exception 2."""
        end = address + len(values) - 1
        if not (PLC_FIRST <= address and end <= PLC_LAST):
            raise ModbusException(
                ExceptionCode.ILLEGAL_DATA_ADDRESS,
                f"expected a write inside {PLC_FIRST}-{PLC_LAST}, got {address}-{end}",
            )
        new = self.regs[PLC_FIRST : PLC_LAST + 1]
        new[address : end + 1] = values
        start: tuple[Command, int] | None = None
        if address <= Reg.SEQUENCE:
            command, sequence = new[Reg.COMMAND], new[Reg.SEQUENCE]
            if command not in Command._value2member_map_:
                raise ModbusException(
                    ExceptionCode.ILLEGAL_DATA_VALUE, f"expected a command 0..4, got {command}"
                )
            is_new = command != 0 and sequence != 0 and sequence != self.regs[Reg.ACK_SEQUENCE]
            if is_new:
                if self.busy or self._stopping:
                    raise ModbusException(ExceptionCode.SERVER_BUSY, "a job is running")
                start = (Command(command), sequence)
            elif command != 0 and sequence == 0:
                log.warning(
                    "command %d with sequence number 0 ignored (expected 1..65535)", command
                )
        if new[Reg.PLC_HEARTBEAT] != self.regs[Reg.PLC_HEARTBEAT]:
            self._hb_changed_at = self.clock()
        self.regs[PLC_FIRST : PLC_LAST + 1] = new
        if start is not None:
            self._accept(*start)

    # ---------------------------------------------------------------------------------------
    # registers

    def _set_words(self, address: int, words: tuple[int, int]) -> None:
        self.regs[address], self.regs[address + 1] = words

    def _set_results(self, results_um: tuple[float | None, ...]) -> None:
        for address, value in zip((Reg.RESULT1, Reg.RESULT2, Reg.RESULT3), results_um):
            self._set_words(address, int32_to_words(micrometres_to_int32(value)))

    def _status(self, bits: Status) -> Status:
        if not self._stopping:
            bits |= Status.READY
        if Path(self.config.storage.calibration).is_file():
            bits |= Status.CALIBRATED
        return bits

    def _publish_end(
        self,
        job_id: int,
        results_um: tuple[float | None, ...],
        passed: bool,
        error: ErrorCode,
        result_valid: bool = True,
        not_proven: bool = False,
    ) -> None:
        """Results first, then status; the job id is the job's own."""
        self._set_results(results_um)
        self._set_words(Reg.JOB_ID, uint32_to_words(job_id))
        if error == ErrorCode.NONE:
            bits = Status.DONE
            if result_valid:
                bits |= Status.RESULT_VALID | (Status.PASS if passed else Status(0))
                if not_proven and not passed:
                    bits |= Status.NOT_PROVEN
            state = State.DONE
        else:
            bits, state = Status.ERROR, State.ERROR
        self.regs[Reg.ERROR_CODE] = int(error)
        self.regs[Reg.STATE] = int(state)
        self.regs[Reg.STATUS] = int(self._status(bits))

    def _restore(self) -> None:
        """Start from the history: no record left running, the last job's outcome shown."""
        self.history.mark_interrupted(
            ErrorCode.INTERRUPTED, "interrupted: the service stopped while the job ran"
        )
        latest = self.history.latest(1)
        if not latest:
            self.regs[Reg.STATUS] = int(self._status(Status(0)))
            return
        rec: JobRecord = latest[0]
        self.regs[Reg.ACK_SEQUENCE] = rec.sequence
        error = (
            ErrorCode(rec.error_code)
            if rec.error_code in ErrorCode._value2member_map_
            else (ErrorCode.INTERNAL)
        )
        if rec.state == "interrupted" and error == ErrorCode.NONE:
            error = ErrorCode.INTERRUPTED
        results = (rec.result1_um, rec.result2_um, rec.result3_um)
        self._publish_end(
            rec.id,
            results,
            bool(rec.passed),
            error,
            result_valid=rec.command != Command.CLEAR_ERROR,
            not_proven=rec.not_proven and error == ErrorCode.NONE,
        )
        log.info("restored job %d (%s): sequence %d", rec.id, rec.state, rec.sequence)

    # ---------------------------------------------------------------------------------------
    # jobs

    def _accept(self, command: Command, sequence: int) -> None:
        parameter = self.regs[Reg.PARAMETER]
        name = command.name.lower()
        job_id = self.history.start(int(command), name, sequence, parameter)
        log.info(
            "accepted job %d: %s, sequence %d, parameter %d", job_id, name, sequence, parameter
        )
        self.regs[Reg.ACK_SEQUENCE] = sequence
        if command == Command.CLEAR_ERROR:
            self.history.finish(job_id, "done")
            # Clear error has no figures: DONE without RESULT_VALID.
            self._publish_end(job_id, (None, None, None), False, ErrorCode.NONE, result_valid=False)
            return
        self._set_results((None, None, None))
        self._set_words(Reg.JOB_ID, uint32_to_words(job_id))
        self.regs[Reg.ERROR_CODE] = 0
        self.regs[Reg.STATE] = int(State.RUNNING)
        self.regs[Reg.STATUS] = int(self._status(Status.BUSY))
        work_dir = Path(self.config.storage.work_dir) / f"job-{job_id:06d}"
        ctx = JobContext(
            job_id,
            int(command),
            parameter,
            work_dir,
            self.config,
            cancel=new_cancel_event(self.config.jobs.worker),
        )
        self.job = _RunningJob(ctx, started=self.clock())
        self._hb_changed_at = self.clock()
        task = asyncio.get_running_loop().create_task(self._run(self.job, _JOB_COMMANDS[command]))
        self._job_tasks.add(task)
        task.add_done_callback(self._job_tasks.discard)

    async def _run(self, job: _RunningJob, method: str) -> None:
        loop = asyncio.get_running_loop()
        future: asyncio.Future[JobOutcome] = loop.create_future()

        def deliver(setter: Callable[[Any], None], value: Any) -> None:
            if not future.done():
                setter(value)

        def work() -> None:
            try:
                if self.runner is None:
                    outcome = run_in_process(
                        self.config, method, job.ctx, self.config.jobs.kill_after_s
                    )
                else:
                    outcome = run_in_thread(self.runner, method, job.ctx)
                args: tuple[Callable[[Any], None], Any] = (future.set_result, outcome)
            except BaseException as exc:
                args = (future.set_exception, exc)
            with contextlib.suppress(RuntimeError):  # the loop is gone: the service stopped
                loop.call_soon_threadsafe(deliver, *args)

        threading.Thread(target=work, name=f"plc-job-{job.ctx.job_id}", daemon=True).start()
        outcome: JobOutcome | None = None
        error, message = ErrorCode.NONE, ""
        try:
            outcome = await future
            error, message = outcome.error, outcome.message
        except JobCancelled:
            pass
        except JobError as exc:
            error, message = exc.code, exc.message
        except WorkerError as exc:
            error, message = ErrorCode.INTERNAL, str(exc)
        except Exception as exc:
            log.error("job %d failed", job.ctx.job_id, exc_info=exc)
            error, message = ErrorCode.INTERNAL, f"{type(exc).__name__}: {exc}"
        if job.cancel_reason is not None:
            error, message = job.cancel_reason, job.cancel_reason.text
        elif outcome is None and error == ErrorCode.NONE:
            error, message = ErrorCode.INTERNAL, "job cancelled itself"
        self._finish(job, outcome, error, message)

    def _finish(
        self, job: _RunningJob, outcome: JobOutcome | None, error: ErrorCode, message: str
    ) -> None:
        if job.done.is_set():
            return
        job.done.set()
        results = outcome.results_um if outcome is not None else (None, None, None)
        passed = bool(outcome.passed) if outcome is not None and error == ErrorCode.NONE else False
        if error == ErrorCode.NONE:
            state = "done"
        elif error == ErrorCode.INTERRUPTED:
            state = "interrupted"
        else:
            state = "error"
        try:
            self.history.finish(
                job.ctx.job_id,
                state,
                passed=passed if outcome is not None else None,
                not_proven=outcome is not None and outcome.not_proven and error == ErrorCode.NONE,
                results_um=results,
                error_code=int(error),
                error_text=message,
                session_path=job.ctx.session_path,
                report_path=outcome.report_path if outcome is not None else None,
                artefacts=outcome.artefacts if outcome is not None else (),
            )
        except Exception:
            log.exception("could not record the end of job %d", job.ctx.job_id)
            error = ErrorCode.INTERNAL
        if self.job is job:
            self.job = None
        not_proven = outcome is not None and outcome.not_proven and error == ErrorCode.NONE
        self._publish_end(job.ctx.job_id, results, passed, error, not_proven=not_proven)
        log.info(
            "job %d %s (error %d%s)",
            job.ctx.job_id,
            state,
            error,
            f": {message}" if message else "",
        )

    def cancel_job(self, reason: ErrorCode) -> None:
        """Ask the running job to stop; it ends with ``reason`` as its error code."""
        job = self.job
        if job is None or job.cancel_reason is not None:
            return
        log.warning("cancelling job %d: %s", job.ctx.job_id, reason.text)
        job.cancel_reason = reason
        job.ctx.cancel.set()

    # ---------------------------------------------------------------------------------------
    # background tasks and lifecycle

    async def _heartbeat(self) -> None:
        while True:
            await asyncio.sleep(1.0)
            self.regs[Reg.HEARTBEAT] = (self.regs[Reg.HEARTBEAT] + 1) & 0xFFFF
            calibrated = Path(self.config.storage.calibration).is_file()
            if calibrated:
                self.regs[Reg.STATUS] |= int(Status.CALIBRATED)
            else:
                self.regs[Reg.STATUS] &= ~int(Status.CALIBRATED)

    async def _watchdog(self, period_s: float) -> None:
        wd = self.config.watchdog
        while True:
            await asyncio.sleep(period_s)
            job = self.job
            if job is None or job.cancel_reason is not None:
                continue
            now = self.clock()
            if wd.heartbeat_timeout_s > 0 and now - self._hb_changed_at > wd.heartbeat_timeout_s:
                self.cancel_job(ErrorCode.WATCHDOG)
            elif wd.job_timeout_s > 0 and now - job.started > wd.job_timeout_s:
                self.cancel_job(ErrorCode.JOB_TIMEOUT)

    def start(self, watchdog_period_s: float = 0.1) -> None:
        """Start the heartbeat and the watchdog (call on the event loop)."""
        self._children_before = child_pids()
        loop = asyncio.get_running_loop()
        self._tasks = [
            loop.create_task(self._heartbeat()),
            loop.create_task(self._watchdog(watchdog_period_s)),
        ]

    async def stop(self) -> None:
        """Refuse new commands, stop a running job (or record it interrupted), stop tasks."""
        self._stopping = True
        self.regs[Reg.STATUS] &= ~int(Status.READY)
        job = self.job
        if job is not None:
            self.cancel_job(ErrorCode.INTERRUPTED)
            grace = self.config.watchdog.shutdown_grace_s
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(job.done.wait(), timeout=grace)
            if not job.done.is_set():
                log.warning("job %d did not stop within %.1f s", job.ctx.job_id, grace)
                self._finish(job, None, ErrorCode.INTERRUPTED, ErrorCode.INTERRUPTED.text)
        kill_job_processes()
        if self.config.jobs.worker == "thread" and self._children_before is not None:
            # Worker pools a job on a thread started (and left running, or still waits for):
            # otherwise the interpreter would wait for their tasks before it could exit.
            kill_new_children(self._children_before)
        for task in [*self._tasks, *self._job_tasks]:
            task.cancel()
        for task in [*self._tasks, *self._job_tasks]:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._tasks = []


async def serve(
    config: PlcConfig,
    runner: JobRunner | None = None,
    *,
    host: str | None = None,
    port: int | None = None,
    stop: asyncio.Event | None = None,
    on_listening: Callable[[str, int], None] | None = None,
) -> None:
    """Run the service until ``stop`` is set, SIGTERM or SIGINT.

    Parameters
    ----------
    config : PlcConfig
        The whole config; ``host`` and ``port`` override ``config.server``.
    runner : JobRunner, optional
        Jobs to run on a thread (needs ``[jobs] worker = "thread"``); by default the runner
        the config names, on a thread or in a process per job as the config says.
    stop : asyncio.Event, optional
        Set it to stop the service (tests); signals set it too.
    on_listening : callable, optional
        Called with the address and the port actually bound (port 0 picks one).

    Raises
    ------
    ValueError
        Before listening: ``host`` is not an IP address or host name (or does not resolve),
        ``[jobs] runner`` names no importable module, ``storage.history_db`` is not a job
        history or cannot be created (:class:`~scanner.core.fileio.InputError`).
    OSError
        The address cannot be listened on.
    """
    stop = stop or asyncio.Event()
    host = check_host(host, "host") if host is not None else config.server.host
    if runner is None:
        check_runner(config.jobs.runner)
        if config.jobs.worker == "thread":
            runner = load_runner(config.jobs.runner, config)
    try:
        history = JobHistory(config.storage.history_db)
    except InputError as exc:
        raise InputError(exc.path, f"storage.history_db: {exc.reason}") from None
    try:
        service = PlcService(config, runner, history)
    except BaseException:
        history.close()
        raise
    srv = config.server
    server = ModbusTcpServer(
        service,
        host=host,
        port=srv.port if port is None else port,
        allowed=srv.networks(),
        max_connections=srv.max_connections,
        idle_timeout_s=srv.idle_timeout_s,
    )
    loop = asyncio.get_running_loop()
    handled: list[signal.Signals] = []
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(sig, stop.set)
                handled.append(sig)
    try:
        await server.start()
        service.start()
        if on_listening is not None:
            on_listening(server.host, server.port)
        await stop.wait()
        log.info("stopping")
    finally:
        for sig in handled:
            loop.remove_signal_handler(sig)
        await server.stop()
        await service.stop()
        history.close()
