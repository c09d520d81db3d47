"""`scanner demo`: the whole job on the built-in virtual cell, one HTML report under reports/."""

from __future__ import annotations

import argparse
from pathlib import Path

from scanner.app.demo import run_demo
from scanner.app.full_object import run_full_object

SUMMARY = "run the whole job on the virtual cell and write a report under reports/"
DESCRIPTION = "Simulate a capture on the virtual cell, calibrate, run the EF check, scan the sphere bar and plate, measure them against a plan, and write one HTML report linking everything. Each stage's artefact stays in the output folder."


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help=SUMMARY, description=DESCRIPTION)
    p.add_argument(
        "--cell",
        default="modern",
        help="virtual cell: modern (default), paper, or a cell TOML file",
    )
    p.add_argument(
        "--out", type=Path, default=None, help="output folder (default reports/demo-<cell>)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the simulation (default 0)")
    p.add_argument(
        "--method", choices=("default", "paper"), default="default", help="calibration method"
    )
    p.add_argument(
        "--sweep-frames",
        type=int,
        default=None,
        help="number of sweep frames (default: the cell's)",
    )
    p.add_argument(
        "--fresh", action="store_true", help="simulate again even if the folder holds sessions"
    )
    p.add_argument(
        "--part",
        type=Path,
        default=None,
        metavar="PART.stl",
        help="full-object job instead: plan sweeps over this mesh (e.g. configs/parts/"
        "bracket.stl), capture, scan and merge them, inspect against the mesh "
        "(default out: reports/part-<name>)",
    )
    p.add_argument(
        "--step-mm", type=float, default=1.0, help="with --part: travel between profiles"
    )
    p.set_defaults(func=run)


def _run_part(args: argparse.Namespace) -> int:
    r = run_full_object(
        args.part, cell=args.cell, out_dir=args.out, seed=args.seed, step_mm=args.step_mm
    )
    print(
        f"full-object job on the '{args.cell}' virtual cell: {r.sweeps} sweeps, {r.frames} "
        f"profiles, {sum(r.seconds.values()):.0f} s"
    )
    print(
        f"  coverage of the surface visible from above: planned {100 * r.predicted_coverage:.1f} %, "
        f"achieved {100 * r.achieved_coverage:.1f} %"
    )
    for c in r.corrections:
        print(
            f"  ICP correction of sweep {c['sweep']}: {c['translation_mm']:.4f} mm, "
            f"{c['rotation_deg']:.4f} deg"
        )
    print(f"  inspection: {r.verdict.upper()}, deviation rms {r.deviation_rms_mm:.4f} mm")
    print(f"report: {r.inspection_html}; figures: {r.job_json}")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.part is not None:
        return _run_part(args)
    result = run_demo(
        cell=args.cell,
        out_dir=args.out,
        seed=args.seed,
        sweep_frames=args.sweep_frames,
        method=args.method,
        reuse=not args.fresh,
    )
    f = result.figures
    e = f["calibration_vs_truth"]
    print(
        f"demo on the '{f['cell']}' virtual cell ({f['method']} calibration), {sum(result.seconds.values()):.0f} s"
    )
    print(
        f"  calibration vs truth: fx {e['fx_rel_pct']:+.4f} %, fy {e['fy_rel_pct']:+.4f} %, "
        f"camera model max {e['model_max_px']:.3f} px, light plane {e['plane_angle_deg']:.4f} deg / "
        f"{e['plane_d_mm']:+.3f} mm, hand-eye {e['hand_eye_rotation_deg']:.4f} deg / "
        f"{e['hand_eye_translation_mm']:.3f} mm"
    )
    print(
        f"  EF check: mean |error| {f['ef_mean_abs_error_mm']:.4f} mm "
        f"({100 * f['ef_mean_rel_error']:.4f} %; the paper: 0.33 mm, 0.21 %), "
        f"spread of O {f['o_spread_mm']:.4f} mm"
    )
    print(f"  scan: {f['cloud_points']} points in {f['scan_seconds']:.1f} s")
    for name, m in f.get("measurements", {}).items():
        actual = "-" if m["actual"] is None else f"{m['actual']:.4f}"
        print(f"  {name}: {actual} (nominal {m['nominal']}) {m['status'].upper()}")
    for name, c in f.get("acceptance", {}).items():
        value = "n/a" if c["value_mm"] is None else f"{c['value_mm'] * 1000:.1f} µm"
        print(
            f"  acceptance {name}: {value} (MPE {c['mpe_mm'] * 1000:.1f} µm) {c['status'].upper()}"
        )
    print(f"report: {result.index_html}")
    return 0
