"""Fixtures of the PLC service tests: a service on a loopback port in a background thread."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
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
from tests.scanner.app.plc.fakes import FakeJobs

HOST = "127.0.0.1"


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
        jobs=JobsConfig(runner="tests.scanner.app.plc.fakes:FakeJobs", worker="thread"),
    )


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
