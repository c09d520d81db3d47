"""`scanner target`: draw a target spec at 1:1 scale (SVG, PDF or PNG) with the spec beside it."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from scanner.core.fileio import InputError, check_outputs_apart
from scanner.core.targets import TargetSpec, parse_target
from scanner.virtual_cell.capture import printed_target
from scanner.virtual_cell.cell import load_cell, load_target
from scanner.virtual_cell.drawing import (
    PAGES_MM,
    drawing_bounds_mm,
    save_target_drawing,
    smallest_page,
)
from scanner.virtual_cell.scene import PrintedTarget

SUMMARY = "draw a calibration target at 1:1 scale (SVG in mm, or PDF/PNG) with its spec"
DESCRIPTION = "Draw the target of a virtual cell (--cell) or of a spec file (--spec: a configs/targets TOML, a target JSON or a session.json) at 1:1 scale. The spec is written beside the drawing as <stem>.json (the 'target' object of session.json)."


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("target", help=SUMMARY, description=DESCRIPTION)
    p.add_argument("--out", required=True, type=Path, help="output .svg, .pdf or .png")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--cell", default=None, help="virtual cell name or TOML (default: paper)")
    src.add_argument("--spec", type=Path, default=None, help="target spec file (.toml or .json)")
    p.add_argument(
        "--page",
        choices=tuple(PAGES_MM),
        default=None,
        help="(.pdf) lay the drawing out at 100 %% on pages of this size: one page when it "
        "fits, else overlapping tiles with alignment marks",
    )
    p.set_defaults(func=run)


def _spec_from_file(path: Path) -> TargetSpec:
    if not path.is_file():
        raise InputError(path, "target spec file not found")
    if path.suffix.lower() == ".toml":
        return load_target(path)
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(path, f"cannot read the spec: {exc}") from None
    if isinstance(obj, dict) and isinstance(obj.get("target"), dict):
        obj = obj["target"]
    try:
        return parse_target(obj)
    except ValueError as exc:
        raise InputError(path, str(exc)) from None


def run(args: argparse.Namespace) -> int:

    if args.spec is not None:
        printed = PrintedTarget(_spec_from_file(args.spec))
    else:
        printed = printed_target(load_cell(args.cell or "paper"))
    if args.spec is not None:
        check_outputs_apart([args.spec], [args.out, args.out.with_suffix(".json")])
    drawing, spec_path = save_target_drawing(printed, args.out, page=args.page)
    x0, x1, y0, y1 = drawing_bounds_mm(printed)
    page = smallest_page(printed)
    fits = f"fits one {page} page" if page else "larger than A3: print with --page A4 (tiles)"
    print(
        f"{drawing}: {x1 - x0:.1f} x {y1 - y0:.1f} mm ({fits}); print at 100 % and check the "
        f"scale bar with a ruler; spec in {spec_path}"
    )
    sys.stdout.flush()
    return 0
