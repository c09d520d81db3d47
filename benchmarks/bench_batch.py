"""`scanner batch` on Dask against serial `scanner scan` + `scanner measure` runs.

1. Four sweep sessions of the modern virtual cell (``--frames`` frames each; one render,
   copied under four names, so every session costs the same), measured with the shipped plan
   ``modern_sweep`` and the cell's true calibration: the sum of four serial CLI runs
   (``scanner scan`` then ``scanner measure``, each a fresh process as a person or a script
   would run them) against one ``scanner batch`` of the four on a local cluster of
   ``--workers`` processes. The batch's numbers are checked to be those of the serial runs.
2. A larger simulated run: ``--small`` small sessions (the analytic table-and-block scene,
   61 frames each) through ``scanner batch`` on local clusters of 1 and of ``--workers``
   processes: throughput per worker and the cluster's start-up cost.

    python benchmarks/bench_batch.py [--frames 300] [--small 20] [--workers 2] [--work DIR]

Prints Markdown tables with the date and the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from scanner.formats.calibration_file import write_calibration
from scanner.virtual_cell.analytic import (
    TableStepScene,
    table_step_plan,
    write_table_step_sweep,
)
from scanner.virtual_cell.simulate import simulate_cell

SCANNER = [sys.executable, "-m", "scanner.app.cli"]


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


@dataclass(frozen=True)
class Timing:
    """Wall seconds and CPU seconds (the process and the children it waited for)."""

    wall: float
    cpu: float

    def __add__(self, other: Timing) -> Timing:
        return Timing(self.wall + other.wall, self.cpu + other.cpu)


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run(args: list[str]) -> Timing:
    """Wall and CPU seconds of one ``scanner`` process (which must succeed)."""
    t0, c0 = time.perf_counter(), _children_cpu()
    proc = subprocess.run([*SCANNER, *args], capture_output=True, text=True, check=False)
    timing = Timing(time.perf_counter() - t0, _children_cpu() - c0)
    if proc.returncode != 0:
        raise SystemExit(f"scanner {' '.join(args)} failed:\n{proc.stderr[-2000:]}")
    return timing


def batch(sessions: list[Path], calibration: Path, plan: str, out: Path, workers: int) -> Timing:
    args = [*map(str, sessions), "--calibration", str(calibration), "--plan", plan]
    args += ["--out", str(out), "--workers", str(workers), "--quiet", "--redo"]
    return run(["batch", *args, "--dashboard", "127.0.0.1:0"])


def sweep_sessions(work: Path, frames: int, count: int) -> tuple[list[Path], Path]:
    """``count`` copies of one modern-cell sweep of ``frames`` frames (images hard-linked)."""
    cell = work / "cell"
    if not (cell / "sweep" / "session.json").is_file():
        t0 = time.perf_counter()
        simulate_cell(
            "modern", cell, seed=0, sessions=("sweep",), sweep_frames=frames, progress=False
        )
        print(f"(rendered a {frames}-frame sweep in {time.perf_counter() - t0:.0f} s)\n")
    sessions = []
    for i in range(count):
        dest = work / "sweeps" / f"sweep_{i}"
        if not dest.exists():
            shutil.copytree(cell / "sweep", dest, copy_function=os.link)
        sessions.append(dest)
    return sessions, cell / "calibration_true.json"


def serial_against_batch(work: Path, frames: int, count: int, workers: int) -> None:
    sessions, calibration = sweep_sessions(work, frames, count)
    serial: list[Timing] = []
    for s in sessions:
        out = work / "serial" / s.name
        out.mkdir(parents=True, exist_ok=True)
        cloud = out / "x.ply"
        t_scan = run(["scan", str(s), "--calibration", str(calibration), "--out", str(cloud)])
        t_meas = run(
            ["measure", str(cloud), "--plan", "modern_sweep", "--out", str(out / "m.json")]
        )
        serial.append(t_scan + t_meas)
    out_dir = work / "batch"
    timing = batch(sessions, calibration, "modern_sweep", out_dir, workers)
    wall = timing.wall
    summary = json.loads((out_dir / "summary.json").read_text())
    same = all(
        (out_dir / s.name / "measure.csv").read_text()
        == (work / "serial" / s.name / "m.csv").read_text()
        for s in sessions
    )
    print(f"### {count} sweep sessions of {frames} frames, plan modern_sweep\n")
    print("| run | wall s | per session s | CPU s | speed-up (wall) |")
    print("|---|---:|---:|---:|---:|")
    total = serial[0]
    for t in serial[1:]:
        total = total + t
    print(f"| {count} x (`scanner scan` + `scanner measure`), serial | {total.wall:.1f} | "
          f"{total.wall / count:.1f} | {total.cpu:.1f} | 1.00 |")  # fmt: skip
    print(f"| `scanner batch`, local cluster of {workers} | {wall:.1f} | {wall / count:.1f} | "
          f"{timing.cpu:.1f} | {total.wall / wall:.2f} |")  # fmt: skip
    print(
        f"\nBatch: {summary['ok']}/{summary['sessions']} ok, task time "
        f"{summary['task_seconds']:.1f} s in {summary['seconds']:.1f} s of the runner (the rest "
        f"of the wall time is the process and cluster start); measure.csv identical to the "
        f"serial runs': {'yes' if same else 'NO'}.\n"
    )


def small_sessions(work: Path, count: int) -> tuple[list[Path], Path, Path]:
    root = work / "small"
    sessions = []
    for i in range(count):
        s = root / f"part_{i:03d}"
        if not (s / "session.json").is_file():
            write_table_step_sweep(s, x_mm=np.linspace(-30.0, 30.0, 61), seed=i)
        sessions.append(s)
    calibration = root / "calibration.json"
    write_calibration(calibration, TableStepScene().calibration())
    plan = root / "plan.toml"
    plan.write_text(table_step_plan(), encoding="utf-8")
    return sessions, calibration, plan


def throughput(work: Path, count: int, workers: int) -> None:
    sessions, calibration, plan = small_sessions(work, count)
    print(f"### {count} small sessions (61 frames of 320 x 240 each)\n")
    print("| local cluster | wall s | CPU s | runner s | task s (sum) | sessions/min (wall) | "
          "per worker, wall | per worker, busy | speed-up |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    base = None
    for n in sorted({1, workers}):
        out = work / f"small_out_{n}"
        timing = batch(sessions, calibration, str(plan), out, n)
        wall = timing.wall
        summary = json.loads((out / "summary.json").read_text())
        assert summary["ok"] == count, summary["failed"]
        rate = count / wall * 60
        base = base or wall
        busy = count / summary["task_seconds"] * 60
        print(
            f"| {n} worker(s) | {wall:.1f} | {timing.cpu:.1f} | {summary['seconds']:.1f} | "
            f"{summary['task_seconds']:.1f} | {rate:.0f} | {rate / n:.0f} | {busy:.0f} | "
            f"{base / wall:.2f} |"
        )
    print(
        "\nwall: the `scanner batch` process; runner: its batch (cluster start included); "
        "task: time inside the tasks, summed over the workers; per worker, busy: sessions per "
        "minute of a worker's task time.\n"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="frames per modern-cell sweep")
    ap.add_argument("--sessions", type=int, default=4, help="sweep sessions (part 1)")
    ap.add_argument("--small", type=int, default=20, help="small sessions (part 2)")
    ap.add_argument("--workers", type=int, default=2, help="local cluster worker processes")
    ap.add_argument("--work", type=Path, default=None, help="keep sessions and outputs here")
    args = ap.parse_args()
    print(
        f"Measured {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC on {cpu_model()}, "
        f"nproc {os.cpu_count()} ({len(os.sched_getaffinity(0))} usable), Python "
        f"{platform.python_version()}; load average {os.getloadavg()[0]:.2f} at the start "
        "(other work on the cores slows the wall times; the CPU column is the honest figure).\n"
    )
    with tempfile.TemporaryDirectory(prefix="bench-batch-") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        serial_against_batch(work, args.frames, args.sessions, args.workers)
        throughput(work, args.small, args.workers)


if __name__ == "__main__":
    main()
