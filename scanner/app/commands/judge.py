"""`scanner measure` and `scanner acceptance`: judge a cloud against a plan or a spec.

``scanner measure CLOUD --plan PLAN.toml --out REPORT.json`` fits the plan's features in the
cloud and evaluates its measurements against nominal and tolerance. ``scanner
acceptance CLOUD [CLOUD ...] --spec ACCEPTANCE.toml --out RESULT.json`` evaluates the
VDI/VDE 2634-2 figures PF, PS, SD and F on scans of a sphere bar and a flat plate against
the spec's MPEs (several scans: the guideline's full test, each characteristic decided by
its worst scan). Both write the
JSON with a CSV (the table) and an HTML report beside it, print the summary line and what
did not pass, and exit 0 when the run completed (``--strict``: 1 when something failed).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass

from scanner.app import stages
from scanner.app.commands import add_cloud_judging

__all__ = ["ACCEPTANCE", "EXIT_FAILED_JUDGEMENT", "MEASURE"]

#: Exit status of ``--strict`` when a measurement or the acceptance test failed.
EXIT_FAILED_JUDGEMENT = 1


def _measure(args: argparse.Namespace) -> stages.Judged:
    return stages.measure(args.cloud, args.plan, args.out, calibration_path=args.calibration)


def _accept(args: argparse.Namespace) -> stages.Judged:
    # one cloud: that scan's test (its own report); several: the full test over them
    clouds = args.cloud[0] if len(args.cloud) == 1 else args.cloud
    return stages.acceptance(clouds, args.spec, args.out, calibration_path=args.calibration)


def _measure_failures(judged: stages.Judged) -> list[str]:
    return [
        f"{r.final_status.upper()}: {r.name}" + (f" ({r.note})" if r.note else "")
        for r in judged.result.rows
        if r.final_status not in ("pass", "n/a")
    ]


def _acceptance_failures(judged: stages.Judged) -> list[str]:
    lines = []
    for c in judged.result.characteristics:
        if not c.passed:
            value = "n/a" if c.value_mm is None else f"{c.value_mm * 1000:+.1f} µm"
            note = f" - {c.row.note}" if c.value_mm is None else ""
            lines.append(
                f"{c.row.final_status.upper()}: {c.symbol} {c.artefact} {value} "
                f"(MPE {c.mpe_mm * 1000:.1f} µm){note}"
            )
    return lines


@dataclass(frozen=True)
class JudgeCommand:
    """One of the two commands: its words, its stage and how it lists what failed."""

    name: str
    summary: str
    description: str
    option: str
    what: str
    strict: str
    stage: Callable[[argparse.Namespace], stages.Judged]
    failures: Callable[[stages.Judged], list[str]]
    several: str = ""
    """Where the command takes several clouds: what they mean (empty: one cloud)."""

    def register(self, sub: argparse._SubParsersAction) -> None:
        p = sub.add_parser(self.name, help=self.summary, description=self.description)
        add_cloud_judging(p, self.option, self.what, self.strict, self.several)
        p.set_defaults(func=self.run)

    def run(self, args: argparse.Namespace) -> int:
        judged = self.stage(args)
        print(f"{self.name}: {judged.result.summary()}")
        for line in self.failures(judged):
            print(f"  {line}")
        files = judged.files
        print(f"wrote {files.json_path}, {files.csv_path.name}, {files.html_path.name}")
        return EXIT_FAILED_JUDGEMENT if args.strict and not judged.result.passed else 0


MEASURE = JudgeCommand(
    "measure",
    "fit the features of an inspection plan in a cloud and report the measurements",
    "Run an inspection plan (configs/plans/*.toml) on a point cloud (base frame, mm): fit the "
    "features, evaluate the measurements, write JSON, CSV and HTML.",
    "--plan",
    "inspection plan",
    "a measurement fails or cannot be made",
    _measure,
    _measure_failures,
)

ACCEPTANCE = JudgeCommand(
    "acceptance",
    "acceptance test after VDI/VDE 2634-2 on a scan of a sphere bar and a plate",
    "Evaluate PF, PS, SD and F (VDI/VDE 2634 Part 2) on a scan of a sphere bar and a flat "
    "plate against the maximum permissible errors of a specification. Several scans (the "
    "guideline's full test: the bar and plate in several positions) give one report in which "
    "each characteristic is decided by its worst scan.",
    "--spec",
    "acceptance specification",
    "the test fails",
    _accept,
    _acceptance_failures,
    several="the scans of one test, each characteristic decided by its worst scan",
)
