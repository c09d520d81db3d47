"""`scanner batch SESSION... --calibration CALIB.json --plan PLAN --out DIR [--scheduler ADDRESS]`.

Reprocesses stored sweep sessions on Dask: each session is scanned and measured as one task
(:mod:`scanner.app.batch`), on a local cluster of this machine's cores or on the scheduler at
``ADDRESS``. Writes ``DIR/<session>/`` (cloud, measurement JSON, CSV, HTML), ``DIR/results.csv``
and ``DIR/summary.json``; with ``--compare PREVIOUS_DIR`` it prints the sessions whose verdict
changed and how far each measurement moved, and writes them to ``DIR/compare.csv``. Exit status
0 when every session was processed, 1 when one failed (recorded with its reason, the others
went on) or, with ``--strict``, when one is out of tolerance; 2 for bad input.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from scanner.app.batch import (
    RESULT_COLUMNS,
    BatchRequest,
    BatchRun,
    BatchState,
    ClusterInfo,
    ResultRow,
    Verdict,
    run_batch,
    verdict_of,
)
from scanner.app.commands import add_calibration, add_out, positive_int
from scanner.core.fileio import InputError, write_text_atomic

EXIT_SESSION_FAILED = 1
COMPARE_COLUMNS = tuple(
    "session previous_verdict verdict name unit previous_actual actual moved previous_status "
    "status".split()
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "batch",
        help="scan and measure many stored sweep sessions on Dask",
        description="Scan every sweep session with the calibration and measure it with the "
        "plan, one Dask task per session, on a local cluster (this machine's cores) or on a "
        "running Dask scheduler. A failing session is recorded with its reason and the others "
        "go on; a batch started again skips the sessions whose outputs are complete.",
    )
    p.add_argument(
        "sessions",
        nargs="+",
        metavar="SESSION",
        help="sweep session folders (a quoted glob such as 'sessions/*' is expanded too)",
    )
    add_calibration(p)
    p.add_argument(
        "--plan",
        required=True,
        help="inspection plan: a TOML file, or the name of one in configs/plans/",
    )
    add_out(p, "output folder: one folder per session, results.csv, summary.json")
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="a running Dask scheduler (tcp://host:8786); default: a local cluster",
    )
    p.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help="worker processes of the local cluster (default: one per core)",
    )
    p.add_argument(
        "--mode",
        choices=("fast", "precise"),
        default="fast",
        help="stripe estimator, as scanner scan --mode (default fast)",
    )
    p.add_argument(
        "--redo", action="store_true", help="process every session again, even complete ones"
    )
    p.add_argument(
        "--compare",
        type=Path,
        metavar="PREVIOUS_DIR",
        default=None,
        help="a previous batch's --out: list the sessions whose verdict changed (compare.csv)",
    )
    p.add_argument(
        "--dashboard",
        metavar="ADDRESS",
        default="127.0.0.1:8787",
        help="where the local cluster serves its dashboard (default 127.0.0.1:8787)",
    )
    p.add_argument(
        "--strict", action="store_true", help="exit 1 when a session is out of tolerance"
    )
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.set_defaults(func=run)


# --------------------------------------------------------------------------------------------
# progress on stderr


def _duration(seconds: float) -> str:
    s = round(seconds)
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


@dataclass
class ProgressLine:
    """Sessions done / failed / running and the time left, on one line of ``stream``.

    On a terminal the line is redrawn in place; otherwise a line is written each time a
    session settles.
    """

    stream: TextIO = field(default_factory=lambda: sys.stderr)
    _last: str = ""

    @staticmethod
    def text(state: BatchState) -> str:
        left = state.seconds_left
        if state.done == state.total:
            eta = "finished"
        else:
            eta = "estimating the time left" if left is None else f"~{_duration(left)} left"
        running = "" if state.running is None else f", {state.running} running"
        reused = f" ({state.reused} reused)" if state.reused else ""
        return (
            f"batch: {state.done}/{state.total} done{reused}, {state.failed} failed{running}, "
            f"{_duration(state.elapsed_s)} elapsed, {eta}"
        )

    def update(self, state: BatchState) -> None:
        text = self.text(state)
        if self.stream.isatty():
            self.stream.write("\r" + text.ljust(len(self._last)))
            self.stream.flush()
            self._last = text
        elif text.split(",")[:2] != self._last.split(",")[:2]:
            self.stream.write(text + "\n")
            self.stream.flush()
            self._last = text

    def close(self) -> None:
        if self.stream.isatty() and self._last:
            self.stream.write("\n")
            self.stream.flush()


# --------------------------------------------------------------------------------------------
# --compare: the sessions whose verdict changed


@dataclass(frozen=True)
class MeasureChange:
    """One measurement of a session whose verdict changed since a previous run."""

    session: str
    previous_verdict: Verdict
    verdict: Verdict
    name: str
    unit: str
    previous_actual: float | None
    actual: float | None
    previous_status: str
    status: str

    @property
    def moved(self) -> float | None:
        if self.actual is None or self.previous_actual is None:
            return None
        return self.actual - self.previous_actual


@dataclass(frozen=True)
class Comparison:
    """This run against a previous one: changes, and sessions in only one of the two."""

    previous_dir: Path
    changes: tuple[MeasureChange, ...]
    only_now: tuple[str, ...]
    only_before: tuple[str, ...]

    @property
    def changed_sessions(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(c.session for c in self.changes))


def read_results(path: Path) -> dict[str, tuple[ResultRow, ...]]:
    """A batch's ``results.csv`` as rows per session (for ``--compare``)."""
    if not path.is_file():
        raise InputError(path, "no results.csv here (expected the --out folder of a batch)")
    try:
        with open(path, encoding="utf-8", newline="") as fh:
            rows: dict[str, list[ResultRow]] = {}
            for row in csv.DictReader(fh):
                rows.setdefault(row["session"], []).append(
                    ResultRow(**{k: row[k] for k in RESULT_COLUMNS[1:]})
                )
    except (KeyError, TypeError, csv.Error) as exc:
        raise InputError(path, f"not a batch results table ({exc})") from None
    return {k: tuple(v) for k, v in rows.items()}


def _actual(row: ResultRow) -> float | None:
    try:
        return float(row.actual) if row.actual else None
    except ValueError:
        return None


def compare_results(
    previous: dict[str, tuple[ResultRow, ...]],
    current: dict[str, tuple[ResultRow, ...]],
    previous_dir: Path,
) -> Comparison:
    """The measurements of every session whose verdict differs between two runs."""
    changes: list[MeasureChange] = []
    for session in sorted(set(previous) & set(current)):
        before, now = previous[session], current[session]
        v0, v1 = verdict_of(before), verdict_of(now)
        if v0 == v1:
            continue
        by_name = {r.name: r for r in before}
        now_names = {r.name for r in now}
        for r in now:
            p = by_name.get(r.name)
            changes.append(
                MeasureChange(
                    session,
                    v0,
                    v1,
                    r.name,
                    r.unit,
                    _actual(p) if p else None,
                    _actual(r),
                    p.status if p else "",
                    r.status,
                )
            )
        for p in before:
            if p.name not in now_names:
                changes.append(
                    MeasureChange(session, v0, v1, p.name, p.unit, _actual(p), None, p.status, "")
                )
    return Comparison(
        previous_dir,
        tuple(changes),
        tuple(sorted(set(current) - set(previous))),
        tuple(sorted(set(previous) - set(current))),
    )


def _number(value: float | None) -> str:
    return "" if value is None or not math.isfinite(value) else repr(value)


def compare_csv(comparison: Comparison) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(COMPARE_COLUMNS)
    for c in comparison.changes:
        writer.writerow(
            [
                c.session,
                c.previous_verdict,
                c.verdict,
                c.name,
                c.unit,
                _number(c.previous_actual),
                _number(c.actual),
                _number(c.moved),
                c.previous_status,
                c.status,
            ]
        )
    return buf.getvalue()


# --------------------------------------------------------------------------------------------
# printing


def _announce(info: ClusterInfo) -> None:
    where = "local cluster" if info.local else "scheduler"
    print(
        f"dask: {where} {info.scheduler}, {info.workers} worker(s), {info.threads} thread(s)",
        flush=True,
    )
    print(f"  dashboard: {info.dashboard or 'not available (install bokeh)'}", flush=True)


def _print_comparison(comparison: Comparison) -> None:
    sessions = comparison.changed_sessions
    print(f"compared with {comparison.previous_dir}: {len(sessions)} session(s) changed verdict")
    if comparison.only_now or comparison.only_before:
        print(
            f"  {len(comparison.only_now)} session(s) only in this run, "
            f"{len(comparison.only_before)} only in the previous one"
        )
    if not comparison.changes:
        return
    header = ("session", "verdict", "measurement", "before", "now", "moved", "status")
    table = [header]
    for c in comparison.changes:
        table.append(
            (
                c.session,
                f"{c.previous_verdict} -> {c.verdict}",
                c.name,
                "-" if c.previous_actual is None else f"{c.previous_actual:.4f}",
                "-" if c.actual is None else f"{c.actual:.4f}",
                "-" if c.moved is None else f"{c.moved:+.4f} {c.unit}",
                f"{c.previous_status or '-'} -> {c.status or '-'}",
            )
        )
    widths = [max(len(row[i]) for row in table) for i in range(len(header))]
    for row in table:
        print("  " + "  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip())


def _print_run(run_: BatchRun) -> None:
    s = run_.summary
    print(
        f"batch: {s.ok} of {s.sessions} session(s) ok, {len(s.failed)} failed, "
        f"{s.passed} in tolerance; {s.processed} processed, {s.reused} reused, "
        f"{s.seconds:.1f} s"
    )
    for f in s.failed:
        print(f"  FAILED {f.session}: {f.reason}", file=sys.stderr)
    if s.out_of_tolerance:
        print(f"  out of tolerance: {', '.join(s.out_of_tolerance)}")
    if s.not_proven:
        print(f"  conformity not proven: {', '.join(s.not_proven)}")
    print(f"wrote {run_.results_path}, {run_.summary_path.name}")


def run(args: argparse.Namespace) -> int:
    # The previous results are read first: --compare may name the --out folder itself.
    previous = read_results(args.compare / "results.csv") if args.compare else None
    request = BatchRequest(
        sessions=args.sessions,
        calibration=args.calibration,
        plan=args.plan,
        out_dir=args.out,
        scheduler=args.scheduler,
        workers=args.workers,
        mode=args.mode,
        redo=args.redo,
        dashboard_address=args.dashboard,
    )
    progress = None if args.quiet else ProgressLine()
    try:
        run_ = run_batch(
            request,
            on_cluster=_announce,
            on_progress=None if progress is None else progress.update,
        )
    finally:
        if progress is not None:
            progress.close()
    _print_run(run_)
    if previous is not None:
        comparison = compare_results(
            previous, {o.name: o.rows for o in run_.outcomes}, args.compare
        )
        compare_path = run_.results_path.with_name("compare.csv")
        write_text_atomic(compare_path, compare_csv(comparison))
        _print_comparison(comparison)
        print(f"wrote {compare_path}")
    if run_.summary.failed:
        return EXIT_SESSION_FAILED
    return EXIT_SESSION_FAILED if args.strict and run_.summary.out_of_tolerance else 0
