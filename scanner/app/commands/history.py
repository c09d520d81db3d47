"""`scanner history`: the jobs the PLC service ran, newest first.

The history is opened read-only (SQLite ``mode=ro``): listing it never changes the file, even
while the service writes to it, and a file that is not a job history is refused (exit 2).
``--json`` prints the records as a JSON list (the columns of the history, newest first).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from scanner.app.plc.config import load_plc_config
from scanner.app.plc.history import JobHistory
from scanner.core.fileio import InputError

SUMMARY = "list the jobs of the PLC service"
DESCRIPTION = "List the jobs the PLC service recorded, newest first."


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("history", help=SUMMARY, description=DESCRIPTION)
    p.add_argument(
        "--db", default=None, help="job history file (default: storage.history_db of --config)"
    )
    p.add_argument("--config", default=None, help="PLC service config (default configs/plc.toml)")
    p.add_argument("--limit", type=int, default=20, help="how many jobs to list (default 20)")
    p.add_argument(
        "--json", action="store_true", help="print the jobs as a JSON list of records, newest first"
    )
    p.set_defaults(func=run)


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def run(args: argparse.Namespace) -> int:

    if args.limit < 1:
        raise ValueError(f"--limit: expected >= 1, got {args.limit}")
    db = Path(args.db) if args.db else Path(load_plc_config(args.config).storage.history_db)
    if not db.is_file():
        raise InputError(db, "job history not found")
    with JobHistory(db, read_only=True) as history:
        records = history.latest(args.limit)
    if args.json:
        print(json.dumps([r.to_dict() for r in records], indent=2))
        return 0
    if not records:
        print("no jobs recorded")
        return 0
    header = (
        f"{'id':>6}  {'command':<20} {'seq':>5} {'par':>4}  {'state':<11} {'started (UTC)':<23} "
        f"{'pass':<4} {'r1 um':>8} {'r2 um':>8} {'r3 um':>8} {'err':>3}  detail"
    )
    print(header)
    for r in records:
        passed = (
            "-" if r.passed is None else ("yes" if r.passed else "n.p." if r.not_proven else "no")
        )
        detail = r.error_text or (r.report_path or "")
        print(
            f"{r.id:>6}  {r.command_name:<20} {r.sequence:>5} {r.parameter:>4}  {r.state:<11} "
            f"{r.started_at[:23]:<23} {passed:<4} {_fmt(r.result1_um):>8} "
            f"{_fmt(r.result2_um):>8} {_fmt(r.result3_um):>8} {r.error_code:>3}  {detail}"
        )
    return 0
