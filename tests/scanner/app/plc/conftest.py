"""Fixtures of the PLC service tests: a service on a loopback port in a background thread."""

from __future__ import annotations

import asyncio
import contextlib
import re
import socket
import struct
import subprocess
import threading
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import pytest

from scanner.app.plc.config import (
    JobsConfig,
    PlcConfig,
    ServerConfig,
    StorageConfig,
    WatchdogConfig,
)
from scanner.app.plc.jobs import JobRunner
from scanner.app.plc.service import serve
from scanner.core.subprocesses import start_module
from tests.conftest import REPO_ROOT
from tests.scanner.app.plc.fakes import FakeJobs

HOST = "127.0.0.1"
FAKE_RUNNER = "tests.scanner.app.plc.fakes:FakeJobs"


def make_config(tmp: Path, **server: object) -> PlcConfig:
    """A config writing under ``tmp``, on a free loopback port, watchdog off."""
    return PlcConfig(
        server=ServerConfig(**{"host": HOST, "port": 0, **server}),  # type: ignore[arg-type]
        watchdog=WatchdogConfig(heartbeat_timeout_s=0.0, job_timeout_s=0.0, shutdown_grace_s=2.0),
        storage=StorageConfig(
            history_db=str(tmp / "history.sqlite"),
            work_dir=str(tmp / "jobs"),
            calibration=str(tmp / "calibration.json"),
        ),
        jobs=JobsConfig(runner=FAKE_RUNNER, worker="thread"),
    )


def write_config_file(
    tmp: Path,
    *,
    host: str = HOST,
    port: int = 0,
    history_db: Path | None = None,
    runner: str = FAKE_RUNNER,
    worker: str = "thread",
    **watchdog: float,
) -> Path:
    """``tmp/plc.toml`` for ``scanner serve --config``: files under ``tmp``, watchdog off.

    Parameters
    ----------
    tmp : Path
        Folder of the config, the job history (unless ``history_db``) and the job outputs.
    host, port : str, int
        ``[server]`` address.
    history_db : Path, optional
        ``[storage] history_db`` (default ``tmp/history.sqlite``).
    runner, worker : str
        ``[jobs]`` runner factory and worker kind.
    **watchdog : float
        ``[watchdog]`` limits replacing the defaults (0 s: off; shutdown grace 2 s).

    Returns
    -------
    Path
        The config file written.
    """
    wd = {"heartbeat_timeout_s": 0.0, "job_timeout_s": 0.0, "shutdown_grace_s": 2.0, **watchdog}
    text = f"""
[server]
host = "{host}"
port = {port}
allowed_clients = ["127.0.0.1"]

[watchdog]
{chr(10).join(f"{k} = {v}" for k, v in wd.items())}

[storage]
history_db = "{history_db or tmp / "history.sqlite"}"
work_dir = "{tmp / "jobs"}"
calibration = "{tmp / "calibration.json"}"

[jobs]
runner = "{runner}"
worker = "{worker}"
"""
    path = tmp / "plc.toml"
    path.write_text(text, encoding="utf-8")
    return path


class Served:
    """``scanner serve --config CONFIG ARGS...`` in a subprocess, started and listening.

    Parameters
    ----------
    config : Path
        The service's config file.
    *args : str
        More arguments of ``scanner serve`` (``--port 0``, ...).
    stderr : int
        Where the service's stderr goes: a pipe (read into the error when it does not start)
        or ``subprocess.DEVNULL`` for a service that may write more than a pipe holds.
    """

    def __init__(self, config: Path, *args: str, stderr: int = subprocess.PIPE) -> None:
        self.proc = start_module(
            "scanner.app.cli",
            ["serve", "--config", str(config), *args],
            REPO_ROOT,
            stdout=subprocess.PIPE,
            stderr=stderr,
        )
        line = self.proc.stdout.readline() if self.proc.stdout else ""
        m = re.search(r"listening on 127\.0\.0\.1:(\d+)", line)
        if not m:
            self.proc.kill()
            err = self.proc.stderr.read() if self.proc.stderr else ""
            self.proc.wait(10)
            raise RuntimeError(f"serve did not start: {line!r} {err!r}")
        self.port = int(m.group(1))

    def stop(self) -> None:
        """Kill the service if it still runs, and reap it."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)


@dataclass
class Running:
    port: int
    config: PlcConfig
    runner: JobRunner
    loop: asyncio.AbstractEventLoop
    stop: asyncio.Event
    thread: threading.Thread

    def shutdown(self) -> None:
        if self.thread.is_alive():
            self.loop.call_soon_threadsafe(self.stop.set)
            self.thread.join(10.0)


@contextlib.contextmanager
def running_service(config: PlcConfig, runner: JobRunner) -> Iterator[Running]:
    """Run :func:`serve` in a thread with its own loop; stop it on exit."""
    ready = threading.Event()
    box: dict[str, object] = {}

    def main() -> None:
        async def go() -> None:
            box["loop"] = asyncio.get_running_loop()
            box["stop"] = stop = asyncio.Event()

            def listening(host: str, port: int) -> None:
                box["port"] = port
                ready.set()

            await serve(config, runner, stop=stop, on_listening=listening)

        try:
            asyncio.run(go())
        finally:
            ready.set()

    thread = threading.Thread(target=main, daemon=True)
    thread.start()
    if not ready.wait(10.0) or "port" not in box:
        raise RuntimeError("service did not start")
    running = Running(
        int(box["port"]),
        config,
        runner,
        box["loop"],
        box["stop"],
        thread,  # type: ignore[arg-type]
    )
    try:
        yield running
    finally:
        running.shutdown()


@pytest.fixture
def fake_jobs() -> FakeJobs:
    return FakeJobs()


@pytest.fixture
def service(tmp_path: Path, fake_jobs: FakeJobs) -> Iterator[Running]:
    config = make_config(tmp_path)
    fake_jobs.config = config
    with running_service(config, fake_jobs) as running:
        yield running


def with_server(config: PlcConfig, **server: object) -> PlcConfig:
    return replace(config, server=replace(config.server, **server))  # type: ignore[arg-type]


# Raw Modbus TCP over a socket, independent of any library ------------------------------------


def adu(tid: int, pdu: bytes, unit: int = 1, proto: int = 0) -> bytes:
    return struct.pack(">HHHB", tid, proto, len(pdu) + 1, unit) + pdu


def read_pdu(address: int, count: int) -> bytes:
    return struct.pack(">BHH", 3, address, count)


def write_pdu(address: int, values: list[int]) -> bytes:
    n = len(values)
    return struct.pack(f">BHHB{n}H", 16, address, n, 2 * n, *values)


def recv_exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError(f"closed after {len(data)} of {n} bytes")
        data += chunk
    return data


def recv_adu(sock: socket.socket) -> tuple[int, int, bytes]:
    """One response: (transaction id, unit id, pdu)."""
    tid, proto, length, unit = struct.unpack(">HHHB", recv_exact(sock, 7))
    assert proto == 0
    return tid, unit, recv_exact(sock, length - 1)


def connect(port: int, timeout: float = 5.0) -> socket.socket:
    sock = socket.create_connection((HOST, port), timeout=timeout)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def is_closed_by_peer(sock: socket.socket, timeout: float = 3.0) -> bool:
    """True when the server closes (EOF or reset) within ``timeout``."""
    sock.settimeout(timeout)
    try:
        return sock.recv(1024) == b""
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False
