"""Run every benchmark in one go and write ``benchmarks/RESULTS.md`` (date, machine, tables).

    python benchmarks/run_all.py [--quick] [--only NAME ...] [--out benchmarks/RESULTS.md]

Each benchmark is a script that prints Markdown tables; this runner calls them one after the
other (so they do not compete for the cores), shares one folder of simulated sessions between
them, and collects their output under a header that says when and where it was measured.
A benchmark that fails is reported with its error and the others still run.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent

# (name, title, arguments, arguments in --quick mode)
BENCHMARKS: list[tuple[str, str, list[str], list[str]]] = [
    (
        "intrinsics",
        "Intrinsics: concentric target (default, paper) vs OpenCV chessboard, and real data",
        [],
        ["--cell", "modern", "--views", "12"],
    ),
    (
        "calibration",
        "Light plane and hand-eye: default vs paper vs OpenCV anchor; real data",
        ["--work", "{work}/calibration"],
        ["--work", "{work}/calibration", "--cells", "modern"],
    ),
    (
        "detection",
        "Concentric-target detection over the randomised domain (issue #15)",
        ["--views", "200", "--empty", "30", "--timing", "10"],
        ["--views", "60", "--empty", "10", "--timing", "5"],
    ),
    (
        "calibrate_cli",
        "`scanner calibrate` on a 20-frame 1280x1024 session",
        ["--work", "{work}/calibrate_cli"],
        ["--work", "{work}/calibrate_cli"],
    ),
    (
        "ef",
        "EF check (the paper's Table III) on both virtual cells",
        ["--work", "{work}/ef"],
        ["--work", "{work}/ef", "--cells", "paper"],
    ),
    (
        "stripe",
        "Stripe extraction: speed vs the frame-read floor, accuracy vs rendered truth",
        [],
        [],
    ),
    (
        "scan",
        "Scan chain: points per second, sphere bar and plate on the virtual cell",
        ["--simulate", "300"],
        ["--frames", "100", "--simulate", "120"],
    ),
    (
        "fit",
        "Feature fits: accuracy and time on up to 1 million points",
        [],
        ["--sizes", "100000", "1000000", "--repeat", "1"],
    ),
    (
        "inspect",
        "Scan-to-CAD inspection: pose, deviations, time (issue #18)",
        [],
        ["--sizes", "100000", "--seeds", "0", "--no-cli"],
    ),
    (
        "plc",
        "PLC service: status-read latency with 50 clients while jobs run",
        [],
        ["--seconds", "2"],
    ),
    (
        "batch",
        "`scanner batch` on Dask against serial scan + measure runs",
        ["--work", "{work}/batch"],
        ["--work", "{work}/batch", "--frames", "100", "--small", "8"],
    ),
]


def machine_line() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        kb = int(Path("/proc/meminfo").read_text().split()[1])
        mem = f", {kb / 1024**2:.0f} GiB"
    except (OSError, ValueError, IndexError):
        pass
    versions = []
    for pkg in ("numpy", "scipy", "opencv-python-headless", "open3d-cpu", "open3d", "pymodbus"):
        try:
            versions.append(f"{pkg} {metadata.version(pkg)}")
        except metadata.PackageNotFoundError:
            continue
    return (
        f"{cpu}, {os.cpu_count()} cores{mem}; {platform.system()} {platform.release()}; "
        f"Python {platform.python_version()}; " + ", ".join(versions)
    )


def run_one(name: str, args: list[str], work: Path) -> tuple[str, float, bool]:
    script = HERE / f"bench_{name}.py"
    cmd = [sys.executable, str(script), *[a.format(work=work) for a in args]]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, check=False)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = "\n".join((proc.stderr or proc.stdout).strip().splitlines()[-15:])
        return f"**failed** (exit {proc.returncode}):\n\n```\n{tail}\n```\n", seconds, False
    return proc.stdout.strip() + "\n", seconds, True


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="smaller runs (minutes, not tens of minutes)"
    )
    parser.add_argument(
        "--only", nargs="+", help="benchmark names to run", choices=[b[0] for b in BENCHMARKS]
    )
    parser.add_argument("--out", type=Path, default=HERE / "RESULTS.md")
    parser.add_argument(
        "--work",
        type=Path,
        default=Path("/tmp/scanner-bench"),
        help="shared folder of simulated sessions",
    )
    args = parser.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    started = datetime.now(timezone.utc)
    sections = []
    ok_all = True
    for name, title, full, quick in BENCHMARKS:
        if args.only and name not in args.only:
            continue
        print(f"running bench_{name} ...", file=sys.stderr, flush=True)
        text, seconds, ok = run_one(name, quick if args.quick else full, args.work)
        ok_all &= ok
        command = f"python benchmarks/bench_{name}.py " + " ".join(quick if args.quick else full)
        sections.append(f"## {title}\n\n`{command.strip()}` ({seconds:.0f} s)\n\n{text}")
        print(f"  done in {seconds:.0f} s", file=sys.stderr, flush=True)
    header = (
        "# Benchmark results\n\n"
        f"Measured {started:%Y-%m-%d %H:%M} UTC by `python benchmarks/run_all.py"
        f"{' --quick' if args.quick else ''}` on: {machine_line()}.\n\n"
        "Accuracy figures on the virtual cells are errors against the simulator's truth. "
        "Times are wall-clock on this machine; where a table has a CPU-time column, that is the "
        "honest figure when other work shares the cores.\n\n"
    )
    args.out.write_text(header + "\n".join(sections), encoding="utf-8")
    print(f"wrote {args.out}", file=sys.stderr)
    return 0 if ok_all else 1


if __name__ == "__main__":
    sys.exit(main())
