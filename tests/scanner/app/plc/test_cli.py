"""`scanner serve` and `scanner history` as a user runs them, in subprocesses where it matters."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from scanner.app.cli import main
from scanner.app.plc.history import JobHistory
from scanner.app.plc.registers import ErrorCode, Status
from tests.scanner.app.plc.conftest import Served, write_config_file
from tests.scanner.app.plc.job_files import wait_for_job_pid
from tests.scanner.app.plc.test_service import Plc, done

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    s = Served(write_config_file(tmp_path, port=5020, worker="process"), "--port", "0")
    yield s
    s.stop()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}").exists() and "zombie" not in _proc_state(pid)


def _proc_state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/status").read_text().split("State:", 1)[1].split("\n")[0]
    except (OSError, IndexError):
        return "zombie"


@pytest.mark.slow
@pytest.mark.parametrize("worker", ["process", "thread"])
def test_sigkill_mid_job_then_restart_marks_the_job_interrupted(tmp_path: Path, worker: str):
    config = write_config_file(tmp_path, port=5020, worker=worker)
    first = Served(config, "--port", "0")
    try:
        plc = Plc(first.port)
        assert plc.write(0, [2, 33, 0, 600]) == 0  # a 60 s scan job
        plc.wait(lambda s: s["bits"] & Status.BUSY)
        # A spawned job process can take many seconds to start on a loaded machine.
        job_pid = wait_for_job_pid(tmp_path / "jobs", timeout_s=60)
        plc.close()
        first.proc.send_signal(signal.SIGKILL)
        first.proc.wait(10)
    finally:
        first.stop()
    if worker == "process":  # the job process does not outlive the service
        assert job_pid != first.proc.pid
        deadline = time.monotonic() + 30
        while _alive(job_pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(job_pid)
    with JobHistory(tmp_path / "history.sqlite") as h:
        assert h.latest(1)[0].state == "running"  # recorded before the kill, left as it was
    second = Served(config, "--port", "0")
    try:
        plc = Plc(second.port)
        st = plc.status()
        assert st["bits"] & Status.ERROR and st["error"] == ErrorCode.INTERRUPTED
        assert (st["ack"], st["job"]) == (33, 1)
        plc.close()
    finally:
        second.stop()
    with JobHistory(tmp_path / "history.sqlite") as h:
        (rec,) = h.latest(5)
    assert (rec.state, rec.error_code, rec.sequence) == ("interrupted", 7, 33)


@pytest.mark.slow
@pytest.mark.parametrize("worker", ["process", "thread"])
def test_sigterm_stops_cleanly_and_records_the_running_job(tmp_path: Path, worker: str):
    served = Served(write_config_file(tmp_path, port=5020, worker=worker), "--port", "0")
    try:
        _sigterm_mid_job(served, tmp_path)
    finally:
        served.stop()


def _sigterm_mid_job(served: Served, tmp_path: Path) -> None:
    plc = Plc(served.port)
    plc.run(1, 1)
    assert plc.write(0, [1, 2, 0, 600]) == 0  # a 60 s job
    plc.wait(lambda s: s["bits"] & Status.BUSY)
    t0 = time.monotonic()
    served.proc.send_signal(signal.SIGTERM)
    assert served.proc.wait(60) == 0
    # It did not wait for the job: the grace is 2 s, then the job is killed (a bound far from
    # both, so that a loaded machine's slow process exit does not fail it).
    assert time.monotonic() - t0 < 30.0
    assert "stopped" in (served.proc.stderr.read() if served.proc.stderr else "")
    plc.close()
    with JobHistory(tmp_path / "history.sqlite") as h:
        states = [r.state for r in h.latest(5)]
    assert states == ["interrupted", "done"]


def test_sigint_stops_an_idle_service(served: Served):
    plc = Plc(served.port)
    assert done(plc.run(1, 1))
    plc.close()
    served.proc.send_signal(signal.SIGINT)
    assert served.proc.wait(60) == 0


def test_print_map(capsys: pytest.CaptureFixture[str]):
    assert main(["serve", "--print-map"]) == 0
    out = capsys.readouterr().out
    assert "113-114" in out and "word-order probe" in out
    assert ErrorCode.WATCHDOG.text in out


def test_history_lists_jobs(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    db = tmp_path / "h.sqlite"
    with JobHistory(db) as h:
        a = h.start(1, "check", 5, 0)
        h.finish(a, "done", passed=True, results_um=(12.0, 40.0, 80.5))
        b = h.start(2, "scan", 6, 1)
        h.finish(b, "error", error_code=3, error_text="bad plan")
    assert main(["history", "--db", str(db), "--limit", "1"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 2 and "scan" in out[1] and "bad plan" in out[1]
    assert main(["history", "--db", str(db)]) == 0
    out = capsys.readouterr().out
    assert "80.5" in out and "check" in out


def test_history_and_serve_refuse_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    assert main(["history", "--db", str(tmp_path / "absent.sqlite")]) == 2
    assert "job history not found" in capsys.readouterr().err
    assert main(["serve", "--config", str(tmp_path / "absent.toml")]) == 2
    assert "config not found" in capsys.readouterr().err
    assert main(["history", "--db", str(tmp_path / "x"), "--limit", "0"]) == 2
