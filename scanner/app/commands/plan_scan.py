"""`scanner plan-scan PART --cell CELL | --calibration CALIB.json --out PLAN_DIR`.

Plans straight robot sweeps that cover a part from its mesh (``scanner.scanning.planning``):
writes ``plan.json`` and ``sweeps.csv`` (``scan-plan/1``: one flange pose per profile, in the
session format's pose columns with a ``sweep`` column), ``coverage.npz`` and the coverage map
``coverage.png``. Exit 0 when the target coverage is predicted, 1 when it is not (the plan is
written anyway, with the reason).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from scanner.app import stages
from scanner.scanning.coverage import CoverageLimits
from scanner.scanning.planning import PlanConfig

SUMMARY = "plan robot sweeps that cover a part (from its mesh), with the predicted coverage"
DESCRIPTION = (
    "Choose straight sweeps of the line sensor around a part standing on the table so that "
    "a target share of its surface visible from above is measured within the incidence and "
    "depth limits, without occlusion. Writes the flange poses to send to the robot, the "
    "predicted coverage and a map of what stays unseen."
)


def _triple(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected x,y,z in mm, got {text!r}") from None
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected three numbers x,y,z, got {text!r}")
    return values  # type: ignore[return-value]


def _pair(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected MIN,MAX in mm, got {text!r}") from None
    if not 0 <= lo < hi:
        raise argparse.ArgumentTypeError(f"expected 0 <= MIN < MAX, got {text!r}")
    return lo, hi


def _share(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0 < value <= 100:
        raise argparse.ArgumentTypeError(f"expected a percentage in (0, 100], got {value}")
    return value / 100.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plan-scan", help=SUMMARY, description=DESCRIPTION)
    p.add_argument("part", type=Path, help="part mesh: .stl, .ply or .obj, mm")
    source = p.add_mutually_exclusive_group()
    source.add_argument(
        "--cell",
        default=None,
        help="virtual cell (name or TOML) whose sensor plans (default: modern)",
    )
    source.add_argument(
        "--calibration", type=Path, default=None,
        help="calibration file of a real sensor (must hold laser_origin_cam)",
    )  # fmt: skip
    p.add_argument("--out", type=Path, required=True, help="plan folder to write")
    p.add_argument(
        "--part-at", type=_triple, default=None, metavar="X,Y,Z",
        help="middle of the part's footprint on the table, base frame, mm (default: a cell's "
        "sweep centre)",
    )  # fmt: skip
    p.add_argument("--part-yaw-deg", type=float, default=0.0, help="part turned about z, deg")
    p.add_argument(
        "--coverage", type=_share, default=0.95, metavar="PERCENT",
        help="target share of the surface visible from above (default 95)",
    )  # fmt: skip
    p.add_argument("--step-mm", type=float, default=0.5, help="travel between profiles")
    p.add_argument("--max-sweeps", type=int, default=12)
    p.add_argument(
        "--reach-mm", type=_pair, default=(0.0, float("inf")), metavar="MIN,MAX",
        help="horizontal distance of the flange from the robot's base axis it can reach "
        "(default: anywhere)",
    )  # fmt: skip
    p.add_argument(
        "--max-incidence-deg", type=float, default=70.0,
        help="largest angle between a surface's normal and the camera or the laser",
    )  # fmt: skip
    p.add_argument(
        "--rotation", default="quaternion_wxyz",
        help="rotation columns of sweeps.csv: quaternion_wxyz, rotvec_rad, euler_xyz_deg, "
        "euler_zyx_deg",
    )  # fmt: skip
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    limits = CoverageLimits(args.max_incidence_deg, args.max_incidence_deg)
    config = PlanConfig(
        target_coverage=args.coverage,
        max_sweeps=args.max_sweeps,
        step_mm=args.step_mm,
        limits=limits,
        reach_mm=args.reach_mm,
    )
    cell = args.cell if args.cell is not None or args.calibration is not None else "modern"
    done = stages.plan_scan(
        args.part,
        args.out,
        cell=cell,
        calibration_path=args.calibration,
        part_at_mm=args.part_at,
        part_yaw_deg=args.part_yaw_deg,
        config=config,
        rotation=args.rotation,
    )
    plan = done.plan
    print(
        f"plan-scan: {len(plan.sweeps)} sweeps, {plan.frames} profiles, predicted coverage "
        f"{100 * plan.coverage:.1f} % of the surface visible from above "
        f"({100 * plan.visible_share:.1f} % of the part's surface); "
        f"{plan.reachable} of {plan.candidates} candidate sweeps within reach"
    )
    for k, gain in enumerate(plan.gains):
        sw = plan.sweeps[k]
        print(
            f"  sweep {k + 1}: {sw.frames} profiles over {sw.length_mm:.1f} mm, +{100 * gain:.1f} %"
        )
    if not plan:
        print(f"plan-scan: target {100 * plan.target_coverage:.1f} % not reached: {plan.reason}")
    print(f"wrote {done.plan_path.parent}/ (plan.json, sweeps.csv, coverage.npz, coverage.png)")
    return 0 if plan else 1
