"""`scanner calibrate SESSION --out CALIB.json`: intrinsics, light plane and hand-eye.

Writes the calibration file (``scan-calibration/1``, atomically) and an HTML calibration
report under ``--report-dir``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="calibrate camera, light plane and hand-eye from a calibration session",
        description="Calibrate intrinsics, the laser light plane and the hand-eye transform "
        "(flange_from_cam) from a scan-session/1 calibration folder.",
    )
    p.add_argument("session", type=Path, help="calibration session folder")
    p.add_argument("--out", type=Path, required=True, help="calibration file to write (JSON)")
    p.add_argument(
        "--method",
        choices=("default", "paper"),
        default="default",
        help="default: every feature, robust joint adjustment; paper: the method's stages "
        "(concentric-circles target only)",
    )
    p.add_argument(
        "--report-dir", type=Path, default=Path("reports"), help="folder of the HTML report"
    )
    p.add_argument("--no-report", action="store_true", help="do not write the HTML report")
    p.add_argument(
        "--refine-intrinsics",
        action="store_true",
        help="let the hand-eye adjustment refine the intrinsics too",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from calibration.pipeline import calibrate_session
    from scanner.formats.calibration_file import write_calibration
    from scanner.formats.session import read_session

    session = read_session(args.session)
    show = not args.quiet and sys.stderr.isatty()

    def stage(name: str) -> None:
        if not args.quiet:
            print(f"calibrate: {name} ...", file=sys.stderr, flush=True)

    result = calibrate_session(
        session,
        method=args.method,
        progress=show,
        refine_intrinsics=args.refine_intrinsics,
        on_stage=stage,
    )
    write_calibration(args.out, result.calibration)
    q = result.calibration.quality
    lp = q["light_plane"]
    he = q["hand_eye"]
    print(f"wrote {args.out}")
    print(
        f"  intrinsics RMS {q['intrinsics']['rms_px']:.3f} px; light plane RMS "
        f"{lp['rms_mm'] * 1000:.1f} um ({len(lp['per_frame'])} frames); hand-eye "
        f"{he['method']}, chain RMS {he['rms_px']:.3f} px"
    )
    if not args.no_report:
        from calibration.report import write_calibration_report

        path = write_calibration_report(result, args.report_dir)
        print(f"  report {path}")
    for w in q["warnings"]:
        print(f"  warning: {w}")
    print(f"verdict: {q['verdict']}")
    return 0
