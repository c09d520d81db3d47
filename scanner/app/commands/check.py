"""`scanner check SESSION --calibration CALIB.json --out RESULT.json`: the paper's EF check."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "check",
        help="measure the target's largest diameter (EF) with the calibrated sensor",
        description="The paper's EF check on a `check` session: |EF| against the nominal "
        "diameter per laser image, and the spread of the target centre O in the base frame.",
    )
    p.add_argument("session", type=Path, help="capture session folder (kind: check)")
    p.add_argument("--calibration", type=Path, required=True, help="calibration file (JSON)")
    p.add_argument("--out", type=Path, required=True, help="result file to write (JSON)")
    p.add_argument(
        "--report",
        type=Path,
        default=None,
        help="HTML report to write (default: beside --out, same name with .html)",
    )
    p.add_argument(
        "--mode", choices=("fast", "precise"), default="precise", help="stripe extractor"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from metrology.ef_check import run_ef_check

    report = args.report or args.out.with_suffix(".html")
    result = run_ef_check(
        args.session, args.calibration, args.out, report, progress=True, mode=args.mode
    )
    print(
        f"EF check: {len(result.valid)}/{len(result.measurements)} frames, nominal {result.nominal_mm:.3f} mm, "
        f"mean |error| {result.mean_abs_error_mm:.4f} mm ({100 * result.mean_rel_error:.4f} %), "
        f"max {result.max_abs_error_mm:.4f} mm, spread of O {result.o_spread_mm:.4f} mm"
    )
    print(f"wrote {args.out} and {report}")
    return 0
