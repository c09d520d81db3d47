"""The service driven by mbpoll, a stand-alone Modbus master, as a PLC programmer would test it."""

from __future__ import annotations

import re
import shutil
import subprocess
import time

import pytest

from scanner.app.plc.registers import ErrorCode, State, Status
from tests.scanner.app.plc.conftest import Running
from tests.scanner.app.plc.fakes import FakeJobs

MBPOLL = shutil.which("mbpoll")
pytestmark = [
    pytest.mark.skipif(MBPOLL is None, reason="mbpoll is not installed (apt install mbpoll)"),
    pytest.mark.timeout(60),
]


def mbpoll(port: int, *args: str) -> subprocess.CompletedProcess[str]:
    """One mbpoll transaction: TCP, zero-based addresses (-0), poll once (-1)."""
    cmd = [MBPOLL or "mbpoll", "-m", "tcp", "-p", str(port), "-0", "-1", "-o", "2", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=20, check=False)


def mbpoll_read(port: int, address: int, count: int, *types: str) -> dict[int, int]:
    res = mbpoll(port, "-r", str(address), "-c", str(count), *types, "127.0.0.1")
    assert res.returncode == 0, res.stdout + res.stderr
    return {int(a): int(v) for a, v in re.findall(r"^\[(\d+)\]:\s+(-?\d+)", res.stdout, re.M)}


def mbpoll_write(port: int, address: int, *values: int) -> subprocess.CompletedProcess[str]:
    return mbpoll(port, "-r", str(address), "127.0.0.1", *map(str, values))


def test_mbpoll_runs_a_check_job(service: Running, fake_jobs: FakeJobs):
    port = service.port
    assert mbpoll_write(port, 3, 5).returncode == 0  # parameter: a 0.5 s fake job
    res = mbpoll_write(port, 0, 1, 7)  # command 1 and sequence 7 in one write (function 16)
    assert res.returncode == 0, res.stdout + res.stderr
    deadline = time.monotonic() + 15
    while True:
        regs = mbpoll_read(port, 100, 5)
        if regs[100] & (Status.DONE | Status.ERROR) or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    assert regs[100] == Status.READY | Status.DONE | Status.RESULT_VALID | Status.PASS
    assert (regs[101], regs[102], regs[103]) == (7, ErrorCode.NONE, State.DONE)
    results = mbpoll_read(port, 105, 5, "-t", "4:int", "-B")  # int32, high word first
    assert results == {105: 12, 107: -46, 109: 79, 111: 1, 113: 16909060}
    assert mbpoll_write(port, 0, 0).returncode == 0
    assert len(fake_jobs.calls) == 1


def test_mbpoll_write_to_status_is_refused(service: Running):
    res = mbpoll_write(service.port, 100, 0)
    assert res.returncode != 0
    assert "Illegal data address" in res.stdout + res.stderr
    res = mbpoll_write(service.port, 0, 9, 1)
    assert res.returncode != 0
    assert "Illegal data value" in res.stdout + res.stderr
