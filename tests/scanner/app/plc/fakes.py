"""Fake jobs for the PLC service tests: fast, deterministic, steered by the parameter register.

Parameter (register 3) of a check or scan job:

* ``0..899``: run ``parameter * 0.1`` s (checking the cancellation flag every 10 ms) and pass
  with results 12.3, -45.6 and 78.9 µm;
* ``997``: finish at once, out of tolerance (DONE without PASS);
* ``998``: raise a bug (internal error);
* ``999``: fail on bad input (error 3);
* ``996``: run 30 s ignoring the cancellation flag (an uncooperative job).

Every call is counted in ``calls`` so tests can prove a command never runs twice. Used in the
subprocess tests too, through ``[jobs] runner = "tests.scanner.app.plc.fakes:FakeJobs"``.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

from scanner.app.plc.config import PlcConfig
from scanner.app.plc.jobs import JobContext, JobError, JobOutcome
from scanner.app.plc.registers import ErrorCode
from tests.scanner.app.plc.job_files import write_job_pid

RESULTS_UM = (12.3, -45.6, 78.9)


class FakeJobs:
    """A :class:`~scanner.app.plc.jobs.JobRunner` that only sleeps and returns fixed figures."""

    def __init__(self, config: PlcConfig | None = None) -> None:
        self.config = config
        self.calls: list[tuple[str, int, int]] = []
        self.lock = threading.Lock()
        self.started = threading.Event()

    def _run(self, name: str, ctx: JobContext) -> JobOutcome:
        with self.lock:
            self.calls.append((name, ctx.job_id, ctx.parameter))
        self.started.set()
        write_job_pid(ctx.work_dir)
        p = ctx.parameter
        if p == 999:
            raise JobError(ErrorCode.BAD_INPUT, "fake: bad input")
        if p == 998:
            raise RuntimeError("fake: a bug")
        if p == 997:
            return JobOutcome(passed=False, results_um=RESULTS_UM)
        if p == 995:  # guarded acceptance: nothing failed, conformity not proven
            return JobOutcome(passed=False, not_proven=True, results_um=RESULTS_UM)
        if p == 996:
            time.sleep(30.0)
        else:
            deadline = time.monotonic() + 0.1 * p
            while time.monotonic() < deadline:
                ctx.check_cancelled()
                time.sleep(0.01)
        report = ctx.work_dir / "report.json"
        report.write_text("{}", encoding="utf-8")
        return JobOutcome(passed=True, results_um=RESULTS_UM, report_path=report)

    def recalibration_check(self, ctx: JobContext) -> JobOutcome:
        return self._run("check", ctx)

    def scan(self, ctx: JobContext) -> JobOutcome:
        return self._run("scan", ctx)

    def full_calibration(self, ctx: JobContext) -> JobOutcome:
        outcome = self._run("calibrate", ctx)
        if self.config is not None:
            Path(self.config.storage.calibration).write_text("{}", encoding="utf-8")
        return outcome
