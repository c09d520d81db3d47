"""The handshake of interfaces.md section 4, driven by pymodbus's client over loopback."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient

from scanner.app.plc.config import PlcConfig, WatchdogConfig
from scanner.app.plc.history import JobHistory
from scanner.app.plc.registers import (
    INT32_INVALID,
    WORD_ORDER_PROBE,
    ErrorCode,
    State,
    Status,
    words_to_int32,
    words_to_uint32,
)
from tests.scanner.app.plc.conftest import Running, make_config, running_service
from tests.scanner.app.plc.fakes import FakeJobs

pytestmark = pytest.mark.timeout(60)


class Plc:
    """A PLC stand-in: pymodbus's client plus the handshake helpers."""

    def __init__(self, port: int) -> None:
        self.client = ModbusTcpClient("127.0.0.1", port=port, timeout=3, retries=0)
        if not self.client.connect():
            raise ConnectionError(f"cannot connect to 127.0.0.1:{port}")

    def close(self) -> None:
        self.client.close()

    def write(self, address: int, values: list[int]) -> int:
        """Write; 0 on success, else the Modbus exception code."""
        rr = self.client.write_registers(address, values, device_id=1)
        return rr.exception_code if rr.isError() else 0

    def read(self, address: int, count: int) -> list[int]:
        rr = self.client.read_holding_registers(address, count=count, device_id=1)
        assert not rr.isError(), rr
        return list(rr.registers)

    def status(self) -> dict[str, int]:
        r = self.read(100, 15)
        return {
            "bits": r[0],
            "ack": r[1],
            "error": r[2],
            "state": r[3],
            "heartbeat": r[4],
            "r1": words_to_int32(r[5], r[6]),
            "r2": words_to_int32(r[7], r[8]),
            "r3": words_to_int32(r[9], r[10]),
            "job": words_to_uint32(r[11], r[12]),
            "probe": words_to_int32(r[13], r[14]),
        }

    def wait(self, until: Callable[[dict[str, int]], bool], timeout: float = 60.0) -> dict:
        """Poll the status until ``until`` holds (the timeout is only a hang guard: a job on a
        spawned process can take many seconds to start on a loaded machine)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            st = self.status()
            if until(st):
                return st
            time.sleep(0.02)
        raise TimeoutError(f"status never matched; last {st}")

    def run(self, command: int, sequence: int, parameter: int = 0) -> dict[str, int]:
        """The whole handshake: wait READY and not BUSY, command, wait DONE or ERROR, command 0."""
        self.wait(lambda s: s["bits"] & Status.READY and not s["bits"] & Status.BUSY)
        assert self.write(3, [parameter]) == 0
        assert self.write(0, [command, sequence]) == 0
        st = self.wait(
            lambda s: s["ack"] == sequence and s["bits"] & (Status.DONE | Status.ERROR) != 0
        )
        assert self.write(0, [0]) == 0
        return st


def done(s: dict[str, int]) -> bool:
    return bool(s["bits"] & (Status.DONE | Status.ERROR))


@pytest.fixture
def plc(service: Running) -> Iterator[Plc]:
    p = Plc(service.port)
    yield p
    p.close()


def _history(config: PlcConfig) -> list:
    with JobHistory(config.storage.history_db) as h:
        return h.latest(100)


def test_check_job_handshake(service: Running, plc: Plc, fake_jobs: FakeJobs):
    st = plc.status()
    assert st["bits"] == Status.READY and st["state"] == State.IDLE and st["ack"] == 0
    assert st["probe"] == WORD_ORDER_PROBE
    assert (st["r1"], st["r2"], st["r3"]) == (INT32_INVALID,) * 3

    assert plc.write(3, [12]) == 0  # a 1.2 s job
    assert plc.write(0, [1, 41]) == 0
    st = plc.status()  # acknowledged before the write was answered
    assert st["bits"] & Status.BUSY and st["bits"] & Status.READY
    assert not st["bits"] & (Status.DONE | Status.RESULT_VALID | Status.ERROR)
    assert (st["ack"], st["state"], st["job"]) == (41, State.RUNNING, 1)
    beat = st["heartbeat"]
    st = plc.wait(done)  # reads keep being answered while the job runs
    assert st["heartbeat"] != beat  # and the scanner heartbeat keeps ticking
    assert st["bits"] == Status.READY | Status.DONE | Status.RESULT_VALID | Status.PASS
    assert (st["state"], st["error"], st["ack"], st["job"]) == (State.DONE, 0, 41, 1)
    assert (st["r1"], st["r2"], st["r3"]) == (12, -46, 79)
    assert plc.read(0, 4) == [1, 41, 0, 12]  # read back as written
    assert plc.write(0, [0]) == 0

    (rec,) = _history(service.config)
    assert (rec.command_name, rec.sequence, rec.state, rec.passed) == ("check", 41, "done", True)
    assert rec.result2_um == pytest.approx(-45.6)
    assert rec.report_path and Path(rec.report_path).is_file()
    assert fake_jobs.calls == [("check", 1, 12)]


def test_same_sequence_number_never_runs_twice(service: Running, plc: Plc, fake_jobs: FakeJobs):
    plc.run(1, 7)
    for _ in range(3):  # a PLC retrying, with the command written again
        assert plc.write(0, [1, 7]) == 0
    time.sleep(0.2)
    assert plc.status()["ack"] == 7
    assert len(fake_jobs.calls) == 1
    plc.run(2, 8, parameter=0)
    assert [c[0] for c in fake_jobs.calls] == ["check", "scan"]
    assert [r.sequence for r in _history(service.config)] == [8, 7]


def test_command_and_sequence_written_one_at_a_time(service: Running, plc: Plc):
    rr = plc.client.write_register(1, 300, device_id=1)  # sequence first, command 0: no job
    assert not rr.isError()
    assert plc.status()["ack"] == 0
    assert not plc.client.write_register(0, 1, device_id=1).isError()
    assert plc.wait(done)["ack"] == 300


def test_sequence_zero_starts_nothing(service: Running, plc: Plc, fake_jobs: FakeJobs):
    assert plc.write(0, [1, 0]) == 0
    time.sleep(0.2)
    assert plc.status()["state"] == State.IDLE and fake_jobs.calls == []


def test_new_command_while_busy_is_refused_and_changes_nothing(
    service: Running, plc: Plc, fake_jobs: FakeJobs
):
    assert plc.write(0, [1, 1, 0, 20]) == 0  # a 2 s job
    plc.wait(lambda s: s["bits"] & Status.BUSY)
    before_plc, before_status = plc.read(0, 10), plc.status()
    assert plc.write(0, [2, 2, 0, 1]) == 6  # server busy
    assert plc.write(1, [3]) == 6  # a new sequence number alone is a new command too
    assert plc.read(0, 10) == before_plc
    after = plc.status()
    assert {k: v for k, v in after.items() if k != "heartbeat"} == {
        k: v for k, v in before_status.items() if k != "heartbeat"
    }
    assert plc.write(2, [5]) == 0  # the heartbeat and parameters may still be written
    assert plc.write(0, [1, 1]) == 0  # repeating the running command is harmless
    assert plc.wait(done)["ack"] == 1
    assert len(fake_jobs.calls) == 1


def test_unknown_command_is_refused(service: Running, plc: Plc):
    assert plc.write(0, [5, 1]) == 3
    assert plc.write(0, [0xFFFF, 1]) == 3
    assert plc.read(0, 2) == [0, 0]
    assert plc.status()["ack"] == 0


def test_write_to_scanner_registers_is_refused(service: Running, plc: Plc):
    assert plc.write(100, [0]) == 2
    assert plc.write(101, [9]) == 2
    assert plc.status()["ack"] == 0


@pytest.mark.parametrize(
    ("parameter", "bits", "error"),
    [
        (997, Status.DONE | Status.RESULT_VALID, ErrorCode.NONE),  # out of tolerance
        (995, Status.DONE | Status.RESULT_VALID | Status.NOT_PROVEN, ErrorCode.NONE),
        (999, Status.ERROR, ErrorCode.BAD_INPUT),
        (998, Status.ERROR, ErrorCode.INTERNAL),
    ],
)
def test_failed_jobs_report_why(service: Running, plc: Plc, parameter: int, bits, error):
    st = plc.run(2, 11, parameter=parameter)
    assert st["bits"] == Status.READY | bits
    assert st["error"] == error
    assert st["state"] == (State.DONE if error == ErrorCode.NONE else State.ERROR)
    (rec,) = _history(service.config)
    assert rec.error_code == error
    assert rec.state == ("done" if error == ErrorCode.NONE else "error")
    if error == ErrorCode.INTERNAL:
        assert "RuntimeError" in rec.error_text


def test_clear_error(service: Running, plc: Plc):
    assert plc.run(1, 1, parameter=999)["bits"] & Status.ERROR
    st = plc.run(4, 2)
    assert st["bits"] == Status.READY | Status.DONE
    assert (st["error"], st["state"]) == (0, State.DONE)
    assert [r.command_name for r in _history(service.config)] == ["clear_error", "check"]


def test_full_calibration_sets_calibrated(service: Running, plc: Plc):
    assert not plc.status()["bits"] & Status.CALIBRATED
    st = plc.run(3, 1)
    assert st["bits"] & Status.CALIBRATED and st["bits"] & Status.PASS


def test_client_disconnect_mid_job_loses_nothing(service: Running, plc: Plc):
    assert plc.write(0, [1, 9, 0, 5]) == 0
    plc.close()
    other = Plc(service.port)
    try:
        st = other.wait(done)
    finally:
        other.close()
    assert st["bits"] & Status.PASS and st["ack"] == 9
    assert _history(service.config)[0].state == "done"


def _with_watchdog(config: PlcConfig, **kw: float) -> PlcConfig:
    return replace(config, watchdog=replace(config.watchdog, **kw))


def test_watchdog_aborts_when_plc_heartbeat_stops(tmp_path: Path):
    config = _with_watchdog(make_config(tmp_path), heartbeat_timeout_s=0.5)
    jobs = FakeJobs(config)
    with running_service(config, jobs) as svc:
        plc = Plc(svc.port)
        t0 = time.monotonic()
        assert plc.write(0, [1, 1, 0, 100]) == 0  # 10 s job, heartbeat never changes
        st = plc.wait(done)
        # aborted by the 0.5 s heartbeat timeout, long before the job's own 10 s (the bound
        # leaves room for a loaded machine)
        assert time.monotonic() - t0 < 7.0
        assert st["bits"] == Status.READY | Status.ERROR
        assert (st["error"], st["state"]) == (ErrorCode.WATCHDOG, State.ERROR)
        plc.close()
    (rec,) = _history(config)
    assert (rec.state, rec.error_code) == ("error", ErrorCode.WATCHDOG)


def test_a_live_plc_heartbeat_keeps_the_job_running(tmp_path: Path):
    config = _with_watchdog(make_config(tmp_path), heartbeat_timeout_s=0.5)
    with running_service(config, FakeJobs(config)) as svc:
        plc = Plc(svc.port)
        assert plc.write(0, [1, 1, 0, 15]) == 0  # 1.5 s job
        beat = 0
        while not done(plc.status()):
            beat += 1
            assert plc.write(2, [beat & 0xFFFF]) == 0
            time.sleep(0.1)
        assert plc.status()["bits"] & Status.PASS
        plc.close()


def test_job_timeout(tmp_path: Path):
    config = _with_watchdog(make_config(tmp_path), job_timeout_s=0.4)
    with running_service(config, FakeJobs(config)) as svc:
        plc = Plc(svc.port)
        assert plc.write(0, [2, 1, 0, 50]) == 0
        assert plc.wait(done)["error"] == ErrorCode.JOB_TIMEOUT
        plc.close()


def test_restart_keeps_history_and_never_reruns_the_last_command(tmp_path: Path):
    config = make_config(tmp_path)
    first = FakeJobs(config)
    with running_service(config, first) as svc:
        plc = Plc(svc.port)
        plc.run(1, 17)
        plc.run(2, 18, parameter=997)
        plc.close()
    second = FakeJobs(config)
    with running_service(config, second) as svc:
        plc = Plc(svc.port)
        st = plc.status()
        assert (st["ack"], st["job"], st["state"]) == (18, 2, State.DONE)
        assert st["bits"] == Status.READY | Status.DONE | Status.RESULT_VALID
        assert st["r1"] == 12
        assert plc.write(0, [2, 18]) == 0  # the PLC repeats its last command after the restart
        time.sleep(0.2)
        assert second.calls == []
        plc.run(1, 19)
        plc.close()
    assert [r.id for r in _history(config)] == [3, 2, 1]


def test_a_not_proven_result_is_shown_again_after_a_restart(tmp_path: Path):
    config = make_config(tmp_path)
    with running_service(config, FakeJobs(config)) as svc:
        plc = Plc(svc.port)
        before = plc.run(2, 21, parameter=995)["bits"]
        plc.close()
    (rec,) = _history(config)
    assert (rec.passed, rec.not_proven) == (False, True)
    with running_service(config, FakeJobs(config)) as svc:
        plc = Plc(svc.port)
        st = plc.status()
        plc.close()
    assert (
        st["bits"] == before == Status.READY | Status.DONE | Status.RESULT_VALID | Status.NOT_PROVEN
    )
    assert st["ack"] == 21


def test_stop_during_an_uncooperative_job_records_it_interrupted(tmp_path: Path):
    config = replace(
        make_config(tmp_path),
        watchdog=WatchdogConfig(heartbeat_timeout_s=0, job_timeout_s=0, shutdown_grace_s=0.3),
    )
    jobs = FakeJobs(config)
    with running_service(config, jobs) as svc:
        plc = Plc(svc.port)
        assert plc.write(0, [1, 5, 0, 996]) == 0
        assert jobs.started.wait(5)
        plc.close()
        t0 = time.monotonic()
        svc.shutdown()
        # stopped, not given up on by shutdown()'s own 10 s wait (the job would hold it 30 s)
        assert not svc.thread.is_alive()
        assert time.monotonic() - t0 < 8.0
    (rec,) = _history(config)
    assert (rec.state, rec.error_code) == ("interrupted", ErrorCode.INTERRUPTED)
    with running_service(config, FakeJobs(config)) as svc:  # shown to the PLC after restart
        plc = Plc(svc.port)
        st = plc.status()
        assert (st["error"], st["ack"]) == (ErrorCode.INTERRUPTED, 5)
        assert st["bits"] & Status.ERROR
        plc.close()


def test_restart_after_clear_error_shows_no_result(tmp_path: Path):
    config = make_config(tmp_path)
    with running_service(config, FakeJobs(config)) as svc:
        plc = Plc(svc.port)
        plc.run(1, 1, parameter=999)
        plc.run(4, 2)
        plc.close()
    with running_service(config, FakeJobs(config)) as svc:
        plc = Plc(svc.port)
        st = plc.status()
        assert st["bits"] == Status.READY | Status.DONE and st["ack"] == 2
        plc.close()
