"""`scanner check SESSION --calibration CALIB.json --out RESULT.json`: the paper's EF check."""

from __future__ import annotations

import argparse
from pathlib import Path

from metrology.ef_check import EFTolerances
from scanner.app import stages
from scanner.app.commands import add_calibration, add_out, add_session

SUMMARY = "measure the target's largest diameter (EF) with the calibrated sensor"
DESCRIPTION = "The paper's EF check on a `check` session: |EF| against the nominal diameter per laser image, and the spread of the target centre O in the base frame."


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("check", help=SUMMARY, description=DESCRIPTION)
    add_session(p, "check")
    add_calibration(p)
    add_out(p, "result file to write (JSON)")
    p.add_argument(
        "--report",
        type=Path,
        default=None,
        help="HTML report to write (default: beside --out, same name with .html)",
    )
    p.add_argument(
        "--mode", choices=("fast", "precise"), default="precise", help="stripe extractor"
    )
    defaults = EFTolerances()
    for option, key, what in (
        ("--max-mean-error-mm", "max_mean_abs_mm", "mean absolute EF error"),
        ("--max-error-mm", "max_abs_mm", "largest absolute EF error"),
        ("--max-o-spread-mm", "max_o_spread_mm", "spread of O in the base frame"),
    ):
        default = getattr(defaults, key)
        p.add_argument(
            option,
            dest=key,
            type=float,
            default=default,
            help=f"limit of the {what} (default {default})",
        )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    run_ = stages.check(
        args.session,
        args.calibration,
        args.out,
        report=args.report or "beside",
        mode=args.mode,
        tolerances=EFTolerances(args.max_mean_abs_mm, args.max_abs_mm, args.max_o_spread_mm),
        progress=True,
    )
    r = run_.result
    print(
        f"EF check: {len(r.valid)}/{len(r.measurements)} frames, nominal {r.nominal_mm:.3f} mm, "
        f"mean |error| {r.mean_abs_error_mm:.4f} mm ({100 * r.mean_rel_error:.4f} %), "
        f"max {r.max_abs_error_mm:.4f} mm, spread of O {r.o_spread_mm:.4f} mm"
    )
    print(
        f"verdict: {'PASS' if r.passed else 'FAIL'} ({r.n_passed} of {len(r.rows)} within limits)"
    )
    print(f"wrote {run_.out_path} and {run_.report_path}")
    return 0
