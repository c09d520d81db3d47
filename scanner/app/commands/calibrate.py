"""`scanner calibrate SESSION --out CALIB.json`: intrinsics, light plane and hand-eye.

Writes the calibration file (``scan-calibration/1``) and its HTML report beside it
(``CALIB.html``), together or not at all.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from scanner.app import stages
from scanner.app.commands import add_out, add_session

SUMMARY = "calibrate camera, light plane and hand-eye from a calibration session"
DESCRIPTION = "Calibrate intrinsics, the laser light plane and the hand-eye transform (flange_from_cam) from a scan-session/1 calibration folder."


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help=SUMMARY, description=DESCRIPTION)
    add_session(p, "calibration")
    add_out(p, "calibration file to write (JSON)")
    p.add_argument(
        "--method",
        choices=("default", "paper"),
        default="default",
        help="default: every feature, robust joint adjustment; paper: the method's stages "
        "(concentric-circles target only)",
    )
    p.add_argument(
        "--report", type=Path, default=None, help="HTML report (default: beside --out, .html)"
    )
    p.add_argument(
        "--report-dir",
        type=Path,
        default=None,
        help="folder of the HTML report (named after --out); --report takes precedence",
    )
    p.add_argument("--no-report", action="store_true", help="do not write the HTML report")
    p.add_argument(
        "--refine-intrinsics",
        action="store_true",
        help="let the hand-eye adjustment refine the intrinsics too",
    )
    p.add_argument(
        "--laser-origin-mm",
        type=float,
        nargs=3,
        default=None,
        metavar=("X", "Y", "Z"),
        help="apex of the laser fan in the camera frame, mm, from the sensor's drawing: written "
        "to the file as laser_origin_cam instead of the one estimated from the laser frames' "
        "shadow edges (scanning uses it for each point's illumination angle)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def _figure(value: float | None, decimals: int) -> str:
    """A quality figure, or ``n/a`` where the method does not give it."""
    return "n/a" if value is None else f"{value:.{decimals}f}"


def run(args: argparse.Namespace) -> int:
    report: Path | str | None = "beside"
    if args.no_report:
        report = None
    elif args.report is not None:
        report = args.report
    elif args.report_dir is not None:
        report = args.report_dir / Path(args.out).with_suffix(".html").name

    def stage(name: str) -> None:
        if not args.quiet:
            print(f"calibrate: {name} ...", file=sys.stderr, flush=True)

    run_ = stages.calibrate(
        args.session,
        args.out,
        report=report,  # type: ignore[arg-type]
        method=args.method,
        refine_intrinsics=args.refine_intrinsics,
        laser_origin_cam_mm=None if args.laser_origin_mm is None else tuple(args.laser_origin_mm),
        progress=not args.quiet and sys.stderr.isatty(),
        on_stage=stage,
    )
    q = run_.quality
    print(f"wrote {run_.calibration_path}")
    plane_um = None if q.light_plane_rms_mm is None else q.light_plane_rms_mm * 1000
    plane = (
        "no light plane (no laser images: a camera-only calibration)"
        if run_.result.calibration.light_plane is None
        else f"light plane RMS {_figure(plane_um, 1)} um ({q.light_plane_frames} frames)"
    )
    print(
        f"  intrinsics RMS {_figure(q.intrinsics_rms_px, 3)} px; {plane}; hand-eye "
        f"{q.hand_eye_method}, chain RMS {_figure(q.hand_eye_rms_px, 3)} px"
    )
    if run_.report_path is not None:
        print(f"  report {run_.report_path}")
    for w in q.warnings:
        print(f"  warning: {w}")
    print(f"verdict: {q.verdict}")
    return 0
