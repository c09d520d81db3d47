"""Robustness of `scanner serve` (issue #17, items 9 and 11): bad input refused in one line
before listening, connection guards that a slow or flapping client cannot defeat, and no
worker-pool process left behind when the service is stopped or killed."""

from __future__ import annotations

import os
import signal
import socket
import sqlite3
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from scanner.app.plc.registers import Status
from tests.conftest import REPO_ROOT
from tests.scanner.app.plc.conftest import (
    HOST,
    Served,
    adu,
    connect,
    make_config,
    read_pdu,
    recv_adu,
    running_service,
    write_config_file,
    write_pdu,
)
from tests.scanner.app.plc.fakes import FakeJobs
from tests.scanner.app.plc.test_service import Plc

pytestmark = pytest.mark.timeout(120)

POOL_RUNNER = "tests.scanner.app.plc.pool_fakes:PoolJobs"


def _scanner(*args: str, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
    """``scanner ARGS`` in a subprocess; a service that starts instead of refusing is killed
    after ``timeout`` (``TimeoutExpired`` fails the test)."""
    return subprocess.run(
        [sys.executable, "-m", "scanner.app.cli", *args],
        cwd=REPO_ROOT,
        env={**os.environ, "PYTHONPATH": str(REPO_ROOT)},
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _assert_refused(proc: subprocess.CompletedProcess[str], *needles: str) -> str:
    err = proc.stderr.strip()
    assert proc.returncode == 2, (proc.returncode, err)
    assert "listening" not in proc.stdout
    assert "\n" not in err, err  # one line, no traceback
    assert "internal error" not in err
    for needle in needles:
        assert needle in err, err
    return err


# Item 9: one-line reasons for bad input of `scanner serve` ----------------------------------


@pytest.mark.parametrize("kind", ["not-sqlite", "foreign-sqlite"])
def test_serve_refuses_a_history_db_that_is_not_a_job_history(tmp_path: Path, kind: str):
    db = tmp_path / "history.sqlite"
    if kind == "not-sqlite":
        db.write_bytes(b"garbage, not SQLite\n" * 100)
    else:
        con = sqlite3.connect(db)
        con.execute("CREATE TABLE parts (id INTEGER PRIMARY KEY)")
        con.commit()
        con.close()
    before = db.read_bytes()
    proc = _scanner("serve", "--config", str(write_config_file(tmp_path, history_db=db)))
    _assert_refused(proc, str(db), "storage.history_db", "not a job history")
    assert db.read_bytes() == before


def test_serve_refuses_an_unwritable_history_db(tmp_path: Path):
    blocker = tmp_path / "var"
    blocker.write_text("a regular file where a folder should be", encoding="utf-8")
    db = blocker / "plc" / "history.sqlite"
    proc = _scanner("serve", "--config", str(write_config_file(tmp_path, history_db=db)))
    _assert_refused(proc, str(db), "storage.history_db", "cannot create the job history")
    assert blocker.read_text(encoding="utf-8").startswith("a regular file")


@pytest.mark.parametrize("worker", ["process", "thread"])
@pytest.mark.parametrize(
    "runner", ["no_such_package.jobs:Factory", "tests.scanner.app.plc.no_such_module:Factory"]
)
def test_serve_refuses_a_runner_module_that_does_not_exist(
    tmp_path: Path, worker: str, runner: str
):
    config = write_config_file(tmp_path, runner=runner, worker=worker)
    proc = _scanner("serve", "--config", str(config))
    _assert_refused(proc, str(config), "[jobs] runner", runner)
    assert not (tmp_path / "history.sqlite").exists()  # refused before anything was created


def test_serve_refuses_a_host_that_is_not_an_address(tmp_path: Path):
    config = write_config_file(tmp_path)
    proc = _scanner("serve", "--config", str(config), "--host", "999.1.1.1")
    _assert_refused(proc, "--host", "999.1.1.1", "expected an IP address")
    bad = write_config_file(tmp_path, host="999.1.1.1")
    proc = _scanner("serve", "--config", str(bad))
    _assert_refused(proc, str(bad), "server.host", "999.1.1.1")


# Item 11 (a): a partial frame does not keep a connection alive --------------------------------


def test_bytes_of_a_partial_frame_do_not_rearm_the_idle_timer(tmp_path: Path):
    idle = 1.0
    config = make_config(tmp_path, idle_timeout_s=idle)
    frame = adu(2, write_pdu(0, [0] * 120))  # 247 bytes: ~100 s at one byte per 0.4 s
    with running_service(config, FakeJobs(config)) as svc, connect(svc.port) as sock:
        sock.sendall(adu(1, read_pdu(113, 2)))
        recv_adu(sock)  # the last complete request: the idle time counts from here
        t0 = time.monotonic()
        closed_after: float | None = None
        sock.settimeout(0.4)
        for byte in frame[:-1]:  # never complete the frame
            if time.monotonic() - t0 > idle + 4.0:
                break
            try:
                sock.sendall(bytes((byte,)))
                if sock.recv(64) == b"":
                    closed_after = time.monotonic() - t0
                    break
            except TimeoutError:
                continue
            except OSError:  # reset or broken pipe: closed too
                closed_after = time.monotonic() - t0
                break
    assert closed_after is not None, "a client trickling one byte every 0.4 s was never closed"
    assert closed_after < idle + 4.0  # a re-armed timer would take about 100 s


# Item 11 (b): the connection count drops as soon as a client has gone ------------------------


@pytest.mark.parametrize("mode", ["close", "reset", "request-then-close"])
@pytest.mark.parametrize("max_connections", [2, 8])
def test_quick_connect_and_close_cycles_do_not_lock_out_the_next_client(
    tmp_path: Path, mode: str, max_connections: int
):
    config = make_config(tmp_path, max_connections=max_connections)
    with running_service(config, FakeJobs(config)) as svc:
        for i in range(20):
            sock = socket.create_connection((HOST, svc.port), timeout=5.0)
            if mode == "reset":
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            elif mode == "request-then-close":
                sock.sendall(adu(i, read_pdu(113, 2)))
            sock.close()
        t0 = time.monotonic()
        with connect(svc.port, timeout=5.0) as sock:
            sock.sendall(adu(99, read_pdu(113, 2)))
            assert recv_adu(sock)[0] == 99  # accepted at once, not reset
        assert time.monotonic() - t0 < 4.0  # not after a socket timeout (5 s)


# Item 11 (c): no worker-pool process outlives the service ------------------------------------


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/status").read_text().split("State:", 1)[1].split("\n")[0]
    except (OSError, IndexError):
        return False
    return "zombie" not in state


@pytest.fixture
def pool_job(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[tuple[Served, list[int]]]:
    """A service (worker from the test's parameter) running a job that keeps a 2-process pool
    busy; yields the service and the pool workers' pids, and kills leftovers afterwards."""
    worker = request.param
    served = Served(
        write_config_file(tmp_path, runner=POOL_RUNNER, worker=worker), stderr=subprocess.DEVNULL
    )
    pids: list[int] = []
    try:
        plc = Plc(served.port)
        assert plc.write(0, [2, 5, 0, 1]) == 0
        plc.wait(lambda s: s["bits"] & Status.BUSY)
        pid_file = tmp_path / "jobs" / "job-000001" / "pool_pids"
        deadline = time.monotonic() + 60.0
        while not pid_file.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        pids = [int(p) for p in pid_file.read_text().split()]
        assert pids and all(_alive(p) for p in pids)
        plc.close()
        yield served, pids
    finally:
        served.stop()
        for pid in pids:  # only the processes this test's service started
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


def _pool_gone_within(pids: list[int], seconds: float) -> list[int]:
    deadline = time.monotonic() + seconds
    while any(_alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    return [p for p in pids if _alive(p)]


@pytest.mark.slow
@pytest.mark.parametrize("pool_job", ["thread", "process"], indirect=True)
def test_sigterm_leaves_no_pool_worker_behind(pool_job: tuple[Served, list[int]]):
    served, pids = pool_job
    served.proc.send_signal(signal.SIGTERM)
    assert served.proc.wait(15) == 0  # grace 2 s; it must not wait for the pool's tasks
    assert _pool_gone_within(pids, 5.0) == []


@pytest.mark.slow
@pytest.mark.parametrize("pool_job", ["process", "thread"], indirect=True)
def test_sigkill_leaves_no_pool_worker_behind(pool_job: tuple[Served, list[int]]):
    """Of a job process or of a job thread: killing the service takes the pool with it."""
    served, pids = pool_job
    served.proc.send_signal(signal.SIGKILL)
    served.proc.wait(10)
    assert _pool_gone_within(pids, 5.0) == []
