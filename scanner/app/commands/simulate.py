"""`scanner simulate`: render a virtual cell's calibration, check and sweep sessions + truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from scanner.app import stages

SUMMARY = "render a virtual cell: calibration, check and sweep sessions plus truth.json"
DESCRIPTION = "Simulate the robot, camera, laser and scene of a virtual cell (configs/cells) and write OUT/calibration, OUT/check, OUT/sweep (scan-session/1), OUT/truth.json, OUT/<session>_stripes.npz and OUT/calibration_true.json."


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help=SUMMARY, description=DESCRIPTION)
    p.add_argument("--cell", default="paper", help="cell name in configs/cells or a TOML path")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--target",
        default=None,
        help="print another target at the same poses: concentric (default), chessboard, "
        "circle_grid, or a configs/targets name or path",
    )
    p.add_argument(
        "--sweep-frames", "--frames-sweep", type=int, default=None, help="number of sweep frames"
    )
    p.add_argument("--workers", type=int, default=2, help="rendering processes (default 2)")
    p.add_argument(
        "--sessions",
        default="calibration,check,sweep",
        help="comma-separated sessions to write (default all three)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    sessions = tuple(s.strip() for s in args.sessions.split(",") if s.strip())
    unknown = [s for s in sessions if s not in ("calibration", "check", "sweep")]
    if unknown or not sessions:
        raise ValueError(
            f"--sessions: expected calibration, check and/or sweep, got {args.sessions!r}"
        )
    if args.sweep_frames is not None and args.sweep_frames < 1:
        raise ValueError(f"--sweep-frames: expected >= 1, got {args.sweep_frames}")
    truth = stages.simulate(
        args.cell,
        args.out,
        seed=args.seed,
        target=args.target,
        sweep_frames=args.sweep_frames,
        workers=max(1, args.workers),
        sessions=sessions,
        progress=True,
    )
    for name, s in truth.sessions.items():
        posed = sum(f.base_from_flange_reported is not None for f in s.frames)
        print(f"{args.out / name}: {len(s.frames)} frames ({posed} with pose)")
    print(f"{args.out / 'truth.json'}: ground truth (cell {truth.cell}, seed {truth.seed})")
    return 0
