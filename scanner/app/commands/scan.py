"""`scanner scan SESSION [SESSION...] --calibration CALIB.json --out CLOUD.ply`.

Extracts the laser stripe of every sweep frame, triangulates it with the calibration, stitches
the sweeps in the robot base frame (mm) and writes the cloud atomically: binary PLY by default,
PCD or E57 by extension. Bad input is refused with a one-line reason before any work.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from scanner.app import stages
from scanner.app.commands import add_calibration, add_out, scan_options

SUMMARY = "turn sweep sessions into a point cloud (base frame, mm)"
DESCRIPTION = "Extract the laser stripe of every frame, triangulate it with the calibration, stitch the sweeps by the robot poses and write one cloud (.ply binary, .pcd or .e57)."


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scan", help=SUMMARY, description=DESCRIPTION)
    p.add_argument(
        "sessions", type=Path, nargs="+", metavar="SESSION", help="sweep session folder(s)"
    )
    add_calibration(p)
    add_out(p, "cloud to write: .ply, .pcd or .e57")
    p.add_argument(
        "--mode",
        choices=("fast", "precise"),
        default="fast",
        help="stripe estimator: fast (windowed centre of gravity) or precise (Steger)",
    )
    p.add_argument("--voxel-mm", type=float, default=None, help="voxel downsampling size, mm")
    p.add_argument(
        "--outliers",
        type=int,
        default=0,
        metavar="K",
        help="statistical outlier removal with K neighbours (0: off)",
    )
    p.add_argument(
        "--normals-mm", type=float, default=None, help="estimate normals within this radius, mm"
    )
    p.add_argument(
        "--icp",
        action="store_true",
        help="refine overlapping sweeps with ICP (reports corrections)",
    )
    p.add_argument(
        "--workdir",
        type=Path,
        default=None,
        help="keep per-frame profiles here so an interrupted run resumes",
    )
    p.add_argument(
        "--keep-flagged",
        action="store_true",
        help="keep flagged points (saturated, ambiguous, low contrast, border, secondary, "
        "grazing, stretch end) in the cloud with their flags; by default it holds trusted "
        "points only",
    )
    p.add_argument(
        "--max-incidence-deg",
        type=float,
        default=None,
        help="flag points seen (or, with the calibration's laser origin, lit) more obliquely "
        "than this",
    )
    p.add_argument(
        "--stretch-end-lines",
        type=int,
        default=0,
        metavar="N",
        help="flag the last N lines before the stripe is cut by a depth jump or an edge "
        "(mixed pixels; 3 suits features many lines across; default 0: none)",
    )
    p.add_argument(
        "--uneven-background",
        choices=("auto", "remove", "keep"),
        default="auto",
        help="frames without laser-off frames: take a smooth background out of every frame "
        "(remove), never (keep), or where a few frames spread over the scan show it uneven "
        "against the stripe threshold (auto, the default)",
    )
    p.add_argument("--workers", type=int, default=2, help="extraction threads (default 2)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.voxel_mm is not None and args.voxel_mm <= 0:
        raise ValueError(f"--voxel-mm: expected > 0, got {args.voxel_mm}")
    if args.normals_mm is not None and args.normals_mm <= 0:
        raise ValueError(f"--normals-mm: expected > 0, got {args.normals_mm}")
    if args.outliers < 0:
        raise ValueError(f"--outliers: expected >= 0 neighbours, got {args.outliers}")
    if args.workers < 1:
        raise ValueError(f"--workers: expected >= 1, got {args.workers}")
    options = scan_options(args)
    run_ = stages.scan(
        args.sessions,
        args.calibration,
        args.out,
        options=options,
        work_dir=args.workdir,
        progress=not args.quiet,
    )
    result = run_.result
    rate = result.n_points / result.seconds if result.seconds > 0 else 0.0
    print(f"wrote {run_.out_path}")
    print(
        f"  {result.n_points} points from {result.n_frames} frames in {result.n_sweeps} "
        f"sweep(s), {result.seconds:.1f} s ({rate:,.0f} points/s), mode {options.mode}"
    )
    if result.removed:
        reasons = ", ".join(f"{n} {name.replace('_', ' ')}" for name, n in result.removed.items())
        print(f"  left out as flagged (--keep-flagged keeps them): {reasons}")
    if result.chunks_resumed:
        print(f"  resumed {result.chunks_resumed} saved chunk(s) from {args.workdir}")
    if result.frames_without_stripe:
        print(f"  {result.frames_without_stripe} frame(s) without any stripe point")
    for c in result.corrections:
        state = "applied" if c.applied else "not applied"
        print(
            f"  ICP sweep {c.sweep}: {c.translation_mm:.3f} mm, {c.rotation_deg:.3f} deg "
            f"({state}, fitness {c.fitness:.2f})"
        )
    for w in result.warnings:
        print(f"  warning: {w}", file=sys.stderr)
    return 0
