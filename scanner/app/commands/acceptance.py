"""`scanner acceptance CLOUD --spec ACCEPTANCE.toml --out RESULT.json`: VDI/VDE 2634-2 test.

Evaluates the probing errors PF and PS, the sphere-spacing error SD and the flatness
measurement error F on a scan of a sphere bar and a flat plate, against the MPEs of the
specification; writes ``RESULT.json``, ``RESULT.csv`` and ``RESULT.html``. Exit status 0 when
the evaluation completed (``--strict``: 1 when the test failed).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from scanner.app import stages
from scanner.app.commands import add_calibration

EXIT_TEST_FAILED = 1


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "acceptance",
        help="acceptance test after VDI/VDE 2634-2 on a scan of a sphere bar and a plate",
        description="Evaluate PF, PS, SD and F (VDI/VDE 2634 Part 2) on a scan of a sphere bar "
        "and a flat plate against the maximum permissible errors of a specification.",
    )
    p.add_argument("cloud", type=Path, help="point cloud of the scan (.ply, .pcd, .xyz, .npy, ...)")
    p.add_argument(
        "--spec",
        required=True,
        help="acceptance specification: a TOML file, or the name of one in configs/plans/",
    )
    p.add_argument(
        "--out", type=Path, required=True, help="result to write (.json; .csv and .html beside)"
    )
    add_calibration(p, required=False)
    p.add_argument("--strict", action="store_true", help="exit 1 when the test fails")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    run_ = stages.acceptance(args.cloud, args.spec, args.out, calibration_path=args.calibration)
    result = run_.result
    print(f"acceptance: {result.summary()}")
    for c in result.characteristics:
        if not c.passed:
            value = "n/a" if c.value_mm is None else f"{c.value_mm * 1000:+.1f} µm"
            print(
                f"  {c.row.final_status.upper()}: {c.symbol} {c.artefact} {value} "
                f"(MPE {c.mpe_mm * 1000:.1f} µm){' - ' + c.row.note if c.value_mm is None else ''}"
            )
    files = run_.files
    print(f"wrote {files.json_path}, {files.csv_path.name}, {files.html_path.name}")
    return EXIT_TEST_FAILED if args.strict and not result.passed else 0
