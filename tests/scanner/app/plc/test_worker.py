"""Jobs in worker processes: outcomes, errors and cancellation cross the process boundary."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import pytest

from scanner.app.plc.config import JobsConfig, PlcConfig
from scanner.app.plc.history import JobHistory
from scanner.app.plc.jobs import JobCancelled, JobContext, JobError
from scanner.app.plc.registers import ErrorCode, Status
from scanner.app.plc.worker import WorkerError, load_runner, new_cancel_event, run_in_process
from tests.scanner.app.plc.conftest import make_config, running_service
from tests.scanner.app.plc.fakes import RESULTS_UM
from tests.scanner.app.plc.job_files import wait_for_job_pid
from tests.scanner.app.plc.test_service import Plc, done

pytestmark = pytest.mark.timeout(60)


def _process_config(tmp: Path, **watchdog: float) -> PlcConfig:
    config = make_config(tmp)
    return replace(
        config,
        jobs=JobsConfig(
            runner="tests.scanner.app.plc.fakes:FakeJobs", worker="process", kill_after_s=0.3
        ),
        watchdog=replace(config.watchdog, **watchdog),
    )


def _ctx(config: PlcConfig, tmp: Path, parameter: int) -> JobContext:
    return JobContext(1, 1, parameter, tmp / "job", config, cancel=new_cancel_event("process"))


def test_outcome_comes_back_from_the_process(tmp_path: Path):
    config = _process_config(tmp_path)
    outcome = run_in_process(config, "recalibration_check", _ctx(config, tmp_path, 0))
    assert outcome.passed and outcome.results_um == RESULTS_UM
    assert outcome.report_path is not None and outcome.report_path.is_file()


@pytest.mark.parametrize(
    ("parameter", "error", "match"),
    [(999, JobError, "fake: bad input"), (998, WorkerError, "RuntimeError: fake: a bug")],
)
def test_errors_come_back_from_the_process(tmp_path: Path, parameter: int, error, match: str):
    config = _process_config(tmp_path)
    with pytest.raises(error, match=match) as info:
        run_in_process(config, "scan", _ctx(config, tmp_path, parameter))
    if error is JobError:
        assert info.value.code == ErrorCode.BAD_INPUT


def test_an_uncooperative_job_is_killed_after_cancellation(tmp_path: Path):
    config = _process_config(tmp_path)
    ctx = _ctx(config, tmp_path, 996)  # ignores the flag for 30 s
    ctx.cancel.set()
    t0 = time.monotonic()
    with pytest.raises(JobCancelled):
        run_in_process(config, "scan", ctx, kill_after_s=0.3)
    assert time.monotonic() - t0 < 10.0


def test_watchdog_kills_a_stuck_job_process(tmp_path: Path):
    config = _process_config(tmp_path, heartbeat_timeout_s=0.5)
    with running_service(config, None) as svc:  # type: ignore[arg-type]
        plc = Plc(svc.port)
        t0 = time.monotonic()
        assert plc.write(0, [1, 1, 0, 996]) == 0
        st = plc.wait(done, timeout=20)
        assert time.monotonic() - t0 < 10.0
        assert st["bits"] & Status.ERROR and st["error"] == ErrorCode.WATCHDOG
        assert plc.write(0, [0]) == 0
        assert plc.write(0, [1, 2, 0, 1]) == 0  # the next job runs, with a live heartbeat
        beat = 0
        while not done(st := plc.status()) or st["ack"] != 2:
            beat += 1
            assert plc.write(2, [beat]) == 0
            time.sleep(0.1)
        assert st["bits"] & Status.PASS
        plc.close()


def test_runner_names_are_checked(tmp_path: Path):
    with pytest.raises(ValueError, match=r"package\.module:factory"):
        load_runner("nocolon", make_config(tmp_path))


def test_stop_kills_a_job_process_that_outlives_the_grace(tmp_path: Path):
    config = _process_config(tmp_path, shutdown_grace_s=0.2)
    config = replace(config, jobs=replace(config.jobs, kill_after_s=30.0))
    with running_service(config, None) as svc:  # type: ignore[arg-type]
        plc = Plc(svc.port)
        assert plc.write(0, [1, 1, 0, 996]) == 0  # ignores cancellation for 30 s
        pid = wait_for_job_pid(tmp_path / "jobs", timeout_s=15)
        plc.close()
        t0 = time.monotonic()
        svc.shutdown()
        assert time.monotonic() - t0 < 8.0
    assert (
        not Path(f"/proc/{pid}").exists() or "Z" in Path(f"/proc/{pid}/stat").read_text().split()[2]
    )
    with JobHistory(config.storage.history_db) as h:
        assert h.latest(1)[0].state == "interrupted"
