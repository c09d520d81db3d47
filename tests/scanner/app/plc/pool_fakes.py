"""A fake job runner whose jobs start a process pool, as the real stages do.

Used through ``[jobs] runner = "tests.scanner.app.plc.pool_fakes:PoolJobs"`` by the tests that
check no pool worker outlives the service. Every job starts :func:`scanner.core.parallel.process_pool`
with two workers, gives each a task that sleeps (at most :data:`TASK_S`), and once both tasks
run writes the workers' process ids to ``job-NNNNNN/pool_pids``; then it waits for the tasks,
checking for cancellation.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import Future
from pathlib import Path

from scanner.app.plc.config import PlcConfig
from scanner.app.plc.jobs import JobContext, JobOutcome
from scanner.core.parallel import process_pool
from tests.scanner.app.plc.job_files import write_job_pid, write_whole

#: How long each pool task sleeps (bounded, so a leaked worker still ends eventually).
TASK_S = 60.0
WORKERS = 2


def pool_task(seconds: float, folder: str) -> int:
    """Say ``running-PID`` in ``folder``, sleep ``seconds`` in a pool worker, return the pid."""
    (Path(folder) / f"running-{os.getpid()}").write_text("", encoding="utf-8")
    time.sleep(seconds)
    return os.getpid()


class PoolJobs:
    """A :class:`~scanner.app.plc.jobs.JobRunner` whose every job keeps a process pool busy."""

    def __init__(self, config: PlcConfig | None = None) -> None:
        self.config = config

    def _run(self, ctx: JobContext) -> JobOutcome:
        write_job_pid(ctx.work_dir)
        pool = process_pool(WORKERS)
        try:
            futures: list[Future[int]] = [
                pool.submit(pool_task, TASK_S, str(ctx.work_dir)) for _ in range(WORKERS)
            ]
            running: list[Path] = []
            deadline = time.monotonic() + 60.0
            while time.monotonic() < deadline:  # both tasks running, in two workers
                running = sorted(ctx.work_dir.glob("running-*"))
                if len(running) >= WORKERS or any(f.done() for f in futures):
                    break
                ctx.check_cancelled()
                time.sleep(0.05)
            pids = sorted(int(p.name.split("-", 1)[1]) for p in running)
            write_whole(ctx.work_dir / "pool_pids", " ".join(str(p) for p in pids))
            deadline = time.monotonic() + TASK_S + 10.0
            while not all(f.done() for f in futures) and time.monotonic() < deadline:
                ctx.check_cancelled()
                time.sleep(0.05)
        finally:
            pool.shutdown(wait=False, cancel_futures=True)
        return JobOutcome(passed=True, results_um=(1.0, 2.0, 3.0))

    def recalibration_check(self, ctx: JobContext) -> JobOutcome:
        return self._run(ctx)

    def scan(self, ctx: JobContext) -> JobOutcome:
        return self._run(ctx)

    def full_calibration(self, ctx: JobContext) -> JobOutcome:
        return self._run(ctx)
