"""The main job end to end on the virtual cell: simulate, calibrate, check, scan, measure.

A staged pipeline: every stage reads the previous stage's artefacts from the output folder and
writes its own, so any stage can be rerun alone with the ordinary commands::

    OUT/sessions/{calibration,check,sweep}/   scanner simulate
    OUT/calibration.json (+ .html)            scanner calibrate
    OUT/check.json (+ .html)                  scanner check
    OUT/cloud.ply                             scanner scan
    OUT/measure.json (+ .csv, .html)          scanner measure
    OUT/acceptance.json (+ .html)             scanner acceptance
    OUT/index.html, OUT/summary.json          this module: links everything, accuracy vs truth
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar

from calibration.compare import compare_calibrations
from scanner.app import stages
from scanner.core.config import resolve_config
from scanner.core.fileio import InputError, write_json_atomic
from scanner.core.tolerance import ToleranceRow
from scanner.formats import html as rep
from scanner.formats.layout import JobLayout
from scanner.scanning.pipeline import ScanOptions
from scanner.virtual_cell.cell import load_cell
from scanner.virtual_cell.truth import CellTruth, read_truth

__all__ = ["DemoResult", "run_demo"]

logger = logging.getLogger(__name__)

T = TypeVar("T")

STAGES = ("simulate", "calibrate", "check", "scan", "measure", "acceptance", "report")


@dataclass
class DemoResult:
    """Paths and key figures of one demo run."""

    out_dir: Path
    index_html: Path
    figures: dict[str, Any] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)


def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _plan_for(cell: str, kind: str) -> Path | None:
    """The shipped plan (``sweep``) or acceptance spec of a cell, if there is one."""
    name = f"{kind}_{cell}" if kind == "acceptance" else f"{cell}_sweep"
    try:
        return resolve_config(name, "plans")
    except InputError:
        return None


def run_demo(
    cell: str = "modern",
    out_dir: str | Path | None = None,
    seed: int = 0,
    sweep_frames: int | None = None,
    method: Literal["default", "paper"] = "default",
    reuse: bool = True,
    progress: bool = True,
) -> DemoResult:
    """Run the whole job on the virtual cell and write one HTML report linking every stage.

    Parameters
    ----------
    cell : str
        ``modern`` (distortion, 1280x1024) or ``paper`` (the paper's setup), or a cell file.
    out_dir : path, optional
        Default ``reports/demo-<cell>``.
    seed : int
        Seed of the simulation.
    sweep_frames : int, optional
        Override the number of sweep frames.
    method : {"default", "paper"}
        Calibration method.
    reuse : bool
        Keep sessions already simulated in ``out_dir`` with the same cell and seed.
    """
    out = Path(out_dir) if out_dir is not None else Path("reports") / f"demo-{Path(cell).stem}"
    out.mkdir(parents=True, exist_ok=True)
    job = JobLayout.of(out)
    result = DemoResult(out_dir=out, index_html=job.index)
    clock = stages.StageClock(result.seconds)

    def stage(name: str, fn: Callable[[], T]) -> T:
        index = STAGES.index(name) + 1
        _say(f"[{index}/{len(STAGES)}] {name} ...")
        value = clock.run(name, fn)
        _say(f"[{index}/{len(STAGES)}] {name} done in {clock.seconds[name]:.1f} s")
        return value

    truth = stage("simulate", lambda: _simulate(cell, job, seed, sweep_frames, reuse, progress))
    calibrated = stage(
        "calibrate",
        lambda: stages.calibrate(
            job.session("calibration"), job.calibration, method=method, progress=progress
        ),
    )
    errors = compare_calibrations(calibrated.result.calibration, truth.calibration())
    check = stage(
        "check",
        lambda: (
            stages.check(job.session("check"), job.calibration, job.check, progress=progress).result
        ),
    )
    # the default stripe mode, as `scanner scan` runs it: the modern plan's instrument figures
    # (its acceptance test) are that mode's
    scan_options = ScanOptions(workers=2)
    scan = stage(
        "scan",
        lambda: (
            stages.scan(
                [job.session("sweep")],
                job.calibration,
                job.cloud,
                options=scan_options,
                progress=progress,
            ).result
        ),
    )
    plan_path = _plan_for(Path(cell).stem, "sweep")
    measure = (
        stage("measure", lambda: stages.measure(job.cloud, plan_path, job.measure).result)
        if plan_path is not None
        else None
    )
    acc_path = _plan_for(Path(cell).stem, "acceptance")
    acceptance = (
        stage("acceptance", lambda: stages.acceptance(job.cloud, acc_path, job.acceptance).result)
        if acc_path is not None
        else None
    )

    quality = calibrated.quality
    figures: dict[str, Any] = {
        "cell": Path(cell).stem,
        "method": method,
        "calibration_vs_truth": errors.to_json(),
        "calibration_rms_px": quality.hand_eye_rms_px,
        "intrinsics_rms_px": quality.intrinsics_rms_px,
        "light_plane_rms_mm": quality.light_plane_rms_mm,
        "ef_mean_abs_error_mm": check.mean_abs_error_mm,
        "ef_max_abs_error_mm": check.max_abs_error_mm,
        "ef_mean_rel_error": check.mean_rel_error,
        "o_spread_mm": check.o_spread_mm,
        "scan_mode": scan_options.mode,
        "cloud_points": scan.n_points,
        "scan_seconds": scan.seconds,
    }
    if measure is not None:
        figures["measurements"] = {
            m.row.name: {
                "actual": m.row.actual,
                "nominal": m.row.nominal,
                "status": m.row.final_status,
            }
            for m in measure.measurements
        }
        figures["measure_passed"] = bool(measure.passed)
    if acceptance is not None:
        figures["acceptance"] = {
            f"{c.symbol} {c.artefact}": {
                "value_mm": c.value_mm,
                "mpe_mm": c.mpe_mm,
                "status": c.row.final_status,
            }
            for c in acceptance.characteristics
        }
        figures["acceptance_passed"] = bool(acceptance.passed)
    result.figures = figures

    def report() -> None:
        write_json_atomic(job.summary, {"figures": figures, "seconds": result.seconds})
        rep.write_page(result.index_html, _index_html(result, errors, check, measure, acceptance))

    stage("report", report)
    return result


def _simulate(
    cell: str,
    job: JobLayout,
    seed: int,
    sweep_frames: int | None,
    reuse: bool,
    progress: bool,
) -> CellTruth:
    """The job's sessions: reused when the folder holds this cell's at this seed, else rendered."""
    if reuse and job.truth.is_file():
        truth = read_truth(job.truth)
        frames = sweep_frames or load_cell(cell).sweep.frames
        if (
            truth.cell == Path(cell).stem
            and truth.seed == seed
            and "sweep" in truth.sessions
            and len(truth.sessions["sweep"].frames) == frames
            and all(
                (job.session(s) / "session.json").is_file()
                for s in ("calibration", "check", "sweep")
            )
        ):
            _say(f"    reusing the sessions in {job.sessions}")
            return truth
    return stages.simulate(
        cell, job.sessions, seed=seed, sweep_frames=sweep_frames, progress=progress
    )


def _link(path: Path, label: str) -> str:
    return f'<a href="{path.name}">{label}</a>' if path.is_file() else f"{label} (not written)"


def _index_html(result: DemoResult, errors: Any, check: Any, measure: Any, acceptance: Any) -> str:
    out = result.out_dir
    f = result.figures
    # The EF figures the demo holds its own cell to (the PLC's recalibration check has its own).
    rows = [
        ToleranceRow(name, nominal=0.0, actual=value, upper=limit_mm, unit="mm")
        for name, value, limit_mm in (
            ("EF mean absolute error", check.mean_abs_error_mm, 0.03),
            ("Spread of O in the base frame", check.o_spread_mm, 0.2),
        )
    ]
    if measure is not None:
        rows += [m.row for m in measure.measurements]
    links = " · ".join(
        [
            _link(out / "calibration.html", "calibration report"),
            _link(out / "check.html", "EF check (Table III)"),
            _link(out / "measure.html", "measurement report"),
            _link(out / "acceptance.html", "VDI/VDE 2634-2 acceptance"),
            _link(out / "cloud.ply", "point cloud (PLY)"),
            _link(out / "summary.json", "figures (JSON)"),
        ]
    )
    e = errors
    accuracy = rep.table(
        ["figure", "error against the virtual cell's truth"],
        [
            ["fx (%)", e.fx_rel_pct],
            ["fy (%)", e.fy_rel_pct],
            ["cx (px)", e.cx_px],
            ["cy (px)", e.cy_px],
            ["camera model over the image, max (px)", e.model_max_px],
            ["light plane normal (deg)", e.plane_angle_deg],
            ["light plane d (mm)", e.plane_d_mm],
            ["hand-eye rotation (deg)", e.hand_eye_rotation_deg],
            ["hand-eye translation (mm)", e.hand_eye_translation_mm],
        ],
        decimals=5,
    )
    body = (
        rep.summary_line(rows, detail=f"virtual cell '{f['cell']}', method {f['method']}")
        + rep.section("Reports", f"<p>{links}</p>")
        + rep.section("Key results", rep.tolerance_table(rows, decimals=4))
        + rep.section(
            "Calibration accuracy against the truth",
            accuracy,
            note="Only a simulator knows the truth: on a real cell the EF check and the spread of O are the figures to watch.",
        )
        + rep.section(
            "Time per stage (s)",
            rep.key_value_table({k: round(v, 1) for k, v in result.seconds.items()}),
        )
    )
    if acceptance is not None:
        body += rep.section(
            "Acceptance test (VDI/VDE 2634-2): PF, PS, SD, F against their MPEs",
            rep.summary_line(acceptance.rows) + rep.tolerance_table(acceptance.rows, decimals=4),
        )
    return rep.page("Robot laser-line scanner: demo on the virtual cell", body, subtitle=str(out))
