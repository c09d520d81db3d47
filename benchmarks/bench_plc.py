"""Load benchmark of the PLC service: many clients polling status while a job runs.

Starts ``scanner serve`` in a subprocess on a free loopback port (so the clients do not share
its interpreter), then for each scenario runs N clients, each reading registers 100-114 in a
loop over its own connection, while a PLC client starts a job and waits for it with the normal
handshake. Prints one table: requests, errors, read latency p50/p99/max, throughput, and whether
the job finished as it should.

    .venv/bin/python benchmarks/bench_plc.py [--clients 50] [--seconds 5]

Scenarios: ``idle`` (no job), ``sleep job`` (the job waits, as on I/O or a camera), and
``cpu job`` (the job burns the CPU in Python on the worker thread, which competes with the
event loop for the GIL: the worst case for latency).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import re
import struct
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scanner.app.plc.config import PlcConfig
from scanner.app.plc.jobs import JobContext, JobOutcome
from scanner.core.subprocesses import start_module

REPO = Path(__file__).resolve().parents[1]

READ_STATUS = struct.pack(">BHH", 3, 100, 15)


class BenchJobs:
    """Jobs for the benchmark: parameter < 1000 sleeps p*0.1 s, >= 1000 burns (p-1000)*0.1 s."""

    def __init__(self, config: PlcConfig) -> None:
        self.config = config

    def _run(self, ctx: JobContext) -> JobOutcome:
        cpu = ctx.parameter >= 1000
        deadline = time.monotonic() + 0.1 * (ctx.parameter - 1000 if cpu else ctx.parameter)
        while time.monotonic() < deadline:
            ctx.check_cancelled()
            if cpu:
                sum(i * i for i in range(20000))
            else:
                time.sleep(0.01)
        return JobOutcome(passed=True, results_um=(1.0, 2.0, 3.0))

    recalibration_check = scan = full_calibration = _run


@dataclass
class ClientStats:
    latencies: list[float]
    errors: int


async def _transact(
    reader: asyncio.StreamReader, writer: asyncio.StreamWriter, tid: int, pdu: bytes
) -> bytes:
    writer.write(struct.pack(">HHHB", tid, 0, len(pdu) + 1, 1) + pdu)
    head = await reader.readexactly(7)
    rtid, proto, length, _ = struct.unpack(">HHHB", head)
    body = await reader.readexactly(length - 1)
    if rtid != tid or proto != 0:
        raise RuntimeError(f"expected transaction {tid}, got {rtid}")
    return body


async def poller(port: int, stop: asyncio.Event) -> ClientStats:
    stats = ClientStats([], 0)
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    tid = 0
    try:
        while not stop.is_set():
            tid = (tid + 1) & 0xFFFF
            t0 = time.perf_counter()
            try:
                body = await asyncio.wait_for(_transact(reader, writer, tid, READ_STATUS), 5.0)
            except (OSError, asyncio.IncompleteReadError, asyncio.TimeoutError, RuntimeError):
                stats.errors += 1
                break
            stats.latencies.append(time.perf_counter() - t0)
            if body[0] != 3 or body[1] != 30:
                stats.errors += 1
    finally:
        writer.close()
    return stats


async def plc_job(port: int, sequence: int, parameter: int) -> tuple[str, float]:
    """Start a job with the handshake and wait for its end; (outcome, seconds)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        values = [2, sequence, 0, parameter]
        pdu = struct.pack(">BHHB4H", 16, 0, 4, 8, *values)
        t0 = time.monotonic()
        body = await _transact(reader, writer, 1, pdu)
        if body[0] != 16:
            return f"refused ({body.hex()})", 0.0
        tid = 1
        while True:
            tid += 1
            body = await _transact(reader, writer, tid, READ_STATUS)
            status, ack, error = struct.unpack_from(">3H", body, 2)
            if ack == sequence and status & 0b100100:
                break
            await asyncio.sleep(0.05)
        await _transact(reader, writer, tid + 1, struct.pack(">BHH", 6, 0, 0))
        outcome = "DONE+PASS" if status & 0b10100 == 0b10100 else f"error {error}"
        return outcome, time.monotonic() - t0
    finally:
        writer.close()


async def scenario(
    port: int, clients: int, seconds: float, sequence: int, parameter: int | None
) -> dict[str, object]:
    stop = asyncio.Event()
    pollers = [asyncio.create_task(poller(port, stop)) for _ in range(clients)]
    job = asyncio.create_task(plc_job(port, sequence, parameter)) if parameter is not None else None
    t0 = time.perf_counter()
    await asyncio.sleep(seconds)
    stop.set()
    results = await asyncio.gather(*pollers)
    elapsed = time.perf_counter() - t0
    outcome = "-"
    if job is not None:
        state, took = await job
        outcome = f"{state} in {took:.1f} s"
    lat = np.array([x for r in results for x in r.latencies]) * 1000.0
    return {
        "requests": lat.size,
        "errors": sum(r.errors for r in results),
        "p50": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "p99": float(np.percentile(lat, 99)) if lat.size else float("nan"),
        "max": float(lat.max()) if lat.size else float("nan"),
        "rate": lat.size / elapsed,
        "job": outcome,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    job_tenths = int(args.seconds * 10 * 0.6)  # the job ends before the pollers stop
    rows = []
    for worker, scenarios in (
        ("process", [("idle", None), ("sleep job", job_tenths), ("cpu job", 1000 + job_tenths)]),
        ("thread", [("cpu job", 1000 + job_tenths)]),
    ):
        for name, row in run_service(args, worker, scenarios):
            rows.append((worker, name, row))
    print(
        f"PLC service load: {args.clients} clients reading 100-114 in a loop, "
        f"{args.seconds:.0f} s per scenario, loopback, {os.cpu_count()} CPUs, "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    print()
    print(
        f"| {'worker':<7} | {'scenario':<10} | {'requests':>8} | {'errors':>6} | {'p50 ms':>7} "
        f"| {'p99 ms':>7} | {'max ms':>7} | {'req/s':>7} | job"
    )
    print(
        f"|{'-' * 9}|{'-' * 12}|{'-' * 10}|{'-' * 8}|{'-' * 9}|{'-' * 9}|{'-' * 9}|{'-' * 9}"
        f"|{'-' * 20}"
    )
    failed = False
    for worker, name, r in rows:
        failed |= bool(r["errors"])
        print(
            f"| {worker:<7} | {name:<10} | {r['requests']:>8} | {r['errors']:>6} | "
            f"{r['p50']:>7.2f} | {r['p99']:>7.2f} | {r['max']:>7.2f} | {r['rate']:>7.0f} | "
            f"{r['job']}"
        )
    return 1 if failed else 0


def run_service(
    args: argparse.Namespace, worker: str, scenarios: list[tuple[str, int | None]]
) -> list[tuple[str, dict[str, object]]]:
    """Start `scanner serve` with this worker and run the scenarios against it."""
    rows: list[tuple[str, dict[str, object]]] = []
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "plc.toml"
        config.write_text(
            f"""[server]
max_connections = {args.clients + 4}
[watchdog]
heartbeat_timeout_s = 0
[storage]
history_db = "{tmp}/history.sqlite"
work_dir = "{tmp}/jobs"
calibration = "{tmp}/calibration.json"
[jobs]
runner = "benchmarks.bench_plc:BenchJobs"
worker = "{worker}"
""",
            encoding="utf-8",
        )
        proc = start_module(
            "scanner.app.cli",
            ["serve", "--config", str(config), "--port", "0"],
            REPO,
            stdout=subprocess.PIPE,
        )
        try:
            line = proc.stdout.readline() if proc.stdout else ""
            m = re.search(r":(\d+)$", line.strip())
            if not m:
                raise RuntimeError(f"service did not start: {line!r}")
            port = int(m.group(1))
            for seq, (name, parameter) in enumerate(scenarios, start=1):
                rows.append(
                    (name, asyncio.run(scenario(port, args.clients, args.seconds, seq, parameter)))
                )
        finally:
            proc.terminate()
            proc.wait(10)
    return rows


if __name__ == "__main__":
    sys.exit(main())
