"""EF check accuracy on both virtual cells, for each calibration method, beside the paper's table.

Usage: ``python benchmarks/bench_ef.py [--work DIR]`` prints a markdown table.
The truth row calibrates with the simulator's true parameters: what is left is the image
measurement of E and F alone.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from calibration.pipeline import calibrate_session
from metrology.ef_check import run_ef_check
from scanner.formats.calibration_file import read_calibration, write_calibration
from scanner.formats.session import read_session
from scanner.virtual_cell.simulate import simulate_cell

PAPER_ROW = "| paper (real cell, Table III) | paper | 0.330 | 0.820 | 0.210 | - | - |"


def simulated(work: Path, cell: str, seed: int = 0) -> Path:
    out = work / f"{cell}-{seed}"
    if not (out / "truth.json").is_file():
        simulate_cell(cell, out, seed=seed, sessions=("calibration", "check"))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--work", type=Path, default=None, help="folder for simulated sessions (reused)"
    )
    parser.add_argument("--cells", nargs="+", default=["paper", "modern"])
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-ef-"))
    lines = [
        "| cell | calibration | mean abs EF error (mm) | max abs EF error (mm) | mean rel error (%) | spread of O (mm) | calibrate (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for cell in args.cells:
        sim = simulated(work, cell)
        calibrations = {"truth": (sim / "calibration_true.json", float("nan"))}
        for method in ("paper", "default"):
            path = sim / f"calibration_{method}.json"
            t0 = time.perf_counter()
            try:
                res = calibrate_session(
                    read_session(sim / "calibration"), method=method, progress=False
                )
            except ValueError as exc:
                lines.append(f"| {cell} | {method} | failed: {exc} | | | | |")
                continue
            write_calibration(path, res.calibration)
            calibrations[method] = (path, time.perf_counter() - t0)
        for name, (path, seconds) in calibrations.items():
            r = run_ef_check(read_session(sim / "check"), read_calibration(path))
            t = "-" if seconds != seconds else f"{seconds:.1f}"
            lines.append(
                f"| {cell} | {name} | {r.mean_abs_error_mm:.4f} | {r.max_abs_error_mm:.4f} | "
                f"{100 * r.mean_rel_error:.4f} | {r.o_spread_mm:.4f} | {t} |"
            )
    lines.append(PAPER_ROW)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
