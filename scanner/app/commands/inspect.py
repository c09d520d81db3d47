"""`scanner inspect CLOUD --nominal MESH --out RESULT.json [--deviations DEV.ply]`.

Scan-to-CAD inspection (contract section 5): finds the part's pose in the cloud without a
starting guess, measures every point's signed deviation from the nominal surface (positive:
too much material), judges it on the spec's tolerance bands and writes the result JSON, the
deviations cloud when asked and an HTML report beside the JSON. Exit 0 when the inspection
ran (``--strict``: 1 when the verdict is fail or the pose is ambiguous).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from scanner.app import stages
from scanner.app.commands import add_out

SUMMARY = "scan-to-CAD inspection: align a cloud to its nominal mesh, map the deviations"
DESCRIPTION = (
    "Find the part's pose in a cloud without a guess (global search, then a robust best-fit), "
    "measure every point's signed deviation from the nominal mesh (STL, PLY, OBJ; mm) and "
    "judge it on the tolerance bands of an inspection spec."
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("inspect", help=SUMMARY, description=DESCRIPTION)
    p.add_argument("cloud", type=Path, help="point cloud (.ply, .pcd, .e57, .xyz, .npy, ...)")
    p.add_argument(
        "--nominal", type=Path, required=True, help="nominal mesh: .stl, .ply or .obj, mm"
    )
    add_out(p, "result to write (.json, scan-inspection/1; the .html report beside it)")
    p.add_argument(
        "--deviations",
        type=Path,
        default=None,
        metavar="DEV.ply",
        help="write every point (nominal frame) with deviation_mm and outlier",
    )
    p.add_argument(
        "--spec",
        default="default",
        help="inspection spec: a TOML file or the name of one in configs/inspect/ "
        "(default: +-0.1 mm on every point)",
    )
    p.add_argument("--no-report", action="store_true", help="do not write the HTML report")
    p.add_argument(
        "--strict", action="store_true", help="exit 1 when the verdict is fail or ambiguous"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    done = stages.inspect(
        args.cloud,
        args.nominal,
        args.out,
        deviations=args.deviations,
        spec=args.spec,
        report=None if args.no_report else "beside",
    )
    result = done.result
    stats, a = result.stats, result.alignment
    print(
        f"inspect: {result.verdict.upper()}, {result.points} points "
        f"({int(result.outlier.sum())} outliers), deviation rms {stats.rms:.4f} mm, "
        f"range {stats.min:+.4f} .. {stats.max:+.4f} mm; alignment rms {a.rms_mm:.4f} mm, "
        f"pose u {a.pose_u_mm:.4f} mm"
    )
    for region in result.regions:
        if region.status != "pass":
            print(
                f"  {region.status.upper()}: {region.name} "
                f"({100 * region.share_in_band:.1f} % in {region.lower_mm:+g}..{region.upper_mm:+g} mm)"
            )
    for warning in a.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    written = [p for p in (done.out_path, done.deviations_path, done.report_path) if p]
    print("wrote " + ", ".join(str(p) for p in written))
    failed = result.verdict != "pass" or a.ambiguous
    return 1 if args.strict and failed else 0
