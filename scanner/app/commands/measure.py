"""`scanner measure CLOUD --plan PLAN.toml --out REPORT.json`: run an inspection plan.

Fits the plan's features in the cloud, evaluates its measurements against nominal and
tolerance, and writes ``REPORT.json`` with ``REPORT.csv`` (the table) and ``REPORT.html`` (the
report people read) beside it. Prints the summary line. Exit status 0 when the run completed
(whether or not every measurement passed; ``--strict`` makes a failed measurement exit 1).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from scanner.app import stages
from scanner.app.commands import add_calibration

EXIT_OUT_OF_TOLERANCE = 1


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "measure",
        help="fit the features of an inspection plan in a cloud and report the measurements",
        description="Run an inspection plan (configs/plans/*.toml) on a point cloud (base frame, "
        "mm): fit the features, evaluate the measurements, write JSON, CSV and HTML.",
    )
    p.add_argument("cloud", type=Path, help="point cloud (.ply, .pcd, .xyz, .npy, ...)")
    p.add_argument(
        "--plan",
        required=True,
        help="inspection plan: a TOML file, or the name of one in configs/plans/",
    )
    p.add_argument(
        "--out", type=Path, required=True, help="report to write (.json; .csv and .html beside)"
    )
    add_calibration(p, required=False)
    p.add_argument(
        "--strict", action="store_true", help="exit 1 when a measurement fails or cannot be made"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    run_ = stages.measure(args.cloud, args.plan, args.out, calibration_path=args.calibration)
    report = run_.report
    print(f"measure: {report.summary()}")
    for m in report.measurements:
        if m.row.final_status not in ("pass", "n/a"):
            print(
                f"  {m.row.final_status.upper()}: {m.row.name}"
                + (f" ({m.row.note})" if m.row.note else "")
            )
    files = run_.files
    print(f"wrote {files.json_path}, {files.csv_path.name}, {files.html_path.name}")
    return EXIT_OUT_OF_TOLERANCE if args.strict and not report.passed else 0
