"""Scanning: the sweeps that cover a part (``scanner plan-scan``), and sweep sessions to one
base-frame cloud (``scanner scan``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from metrology.coverage_map import write_coverage_map
from scanner.app.stages.common import provenance
from scanner.core.fileio import InputError, check_outputs_apart, commit_together
from scanner.formats.calibration_file import read_calibration
from scanner.formats.clouds import FORMATS
from scanner.formats.meshes import read_mesh
from scanner.formats.scan_plan import write_scan_plan
from scanner.formats.session import read_session
from scanner.scanning.coverage import SensorGeometry
from scanner.scanning.pipeline import ScanOptions, ScanResult, check_scan_inputs, scan_session
from scanner.scanning.planning import PlanConfig, SweepPlan, place_on_table, plan_sweeps
from scanner.virtual_cell.cell import CellConfig, load_cell

# --------------------------------------------------------------------------------------------
# plan-scan


@dataclass(frozen=True)
class PlanRun:
    """Sweeps planned for a part: the plan and the files written into the plan folder.

    ``plan.json`` and ``sweeps.csv`` (``scan-plan/1``), ``coverage.npz`` (the surface samples
    in the part's frame, which are visible from above and which sweep measures each) and
    ``coverage.png`` (the map).
    """

    plan: SweepPlan
    base_from_part: NDArray
    plan_path: Path
    sweeps_path: Path
    samples_path: Path
    map_path: Path


def plan_scan(
    part_path: Path,
    out_dir: Path,
    *,
    cell: str | CellConfig | None = None,
    calibration_path: Path | None = None,
    part_at_mm: tuple[float, float, float] | None = None,
    part_yaw_deg: float = 0.0,
    config: PlanConfig | None = None,
    rotation: str = "quaternion_wxyz",
) -> PlanRun:
    """Plan the sweeps that cover a part (``scanner plan-scan``).

    The sensor is a virtual cell's (``cell``) or a calibration file's (``calibration_path``,
    which must hold the laser origin). The part stands on the table with the middle of its
    footprint at ``part_at_mm`` (default: the cell's sweep centre on its table).
    """
    part_path, out_dir = Path(part_path), Path(out_dir)
    if (cell is None) == (calibration_path is None):
        raise ValueError("plan-scan: expected either a cell or a calibration file, not both")
    names = ("plan.json", "sweeps.csv", "coverage.npz", "coverage.png")
    inputs = [part_path, *([calibration_path] if calibration_path is not None else [])]
    check_outputs_apart(inputs, [out_dir / n for n in names])
    part = read_mesh(part_path)
    if calibration_path is not None:
        calibration = read_calibration(calibration_path)
        calibration.require_light_plane(calibration_path, "planning")
        try:
            sensor = SensorGeometry.from_calibration(calibration)
        except ValueError as exc:
            raise InputError(calibration_path, str(exc)) from None
        source = {"calibration": str(calibration_path)}
        if part_at_mm is None:
            raise ValueError("--part-at: expected where the part stands (x,y,z mm, base frame)")
    else:
        cell_config = load_cell(cell)
        sensor = cell_config.sensor_geometry()
        source = {"cell": cell_config.name}
        if part_at_mm is None:
            sw = cell_config.sweep
            part_at_mm = (sw.center_mm[0], sw.center_mm[1], sw.table_z_mm)
    config = config or PlanConfig()
    base_from_part = place_on_table(part, part_at_mm, part_yaw_deg)
    plan = plan_sweeps(sensor, part.transformed(base_from_part), config)
    part_from_base = np.linalg.inv(base_from_part)
    record = {
        "part": {"path": str(part_path), "base_from_part": base_from_part.tolist()},
        "sensor": source,
        "coverage": {
            "predicted": plan.coverage,
            "target": plan.target_coverage,
            "reached": bool(plan),
            "reason": plan.reason,
            "visible_share_of_surface": plan.visible_share,
            "samples": len(plan.points_base),
            "limits": {
                "max_view_incidence_deg": config.limits.max_view_incidence_deg,
                "max_laser_incidence_deg": config.limits.max_laser_incidence_deg,
                "depth_range_mm": list(config.limits.depth_range_mm),
                "image_margin_px": config.limits.image_margin_px,
            },
        },
        "candidates": plan.candidates,
        "reachable_candidates": plan.reachable,
        "frames": plan.frames,
        "sweeps": [
            {
                "index": k,
                "frames": sw.frames,
                "length_mm": sw.length_mm,
                "step_mm": sw.step_mm,
                "direction": sw.direction.tolist(),
                "base_from_cam_start": sw.base_from_cam_start.tolist(),
                "gain": gain,
            }
            for k, (sw, gain) in enumerate(zip(plan.sweeps, plan.gains))
        ],
        "provenance": provenance("plan-scan", {"part": part_path, "calibration": calibration_path}),
    }
    points_part = plan.points_base @ part_from_base[:3, :3].T + part_from_base[:3, 3]
    normals_part = plan.normals_base @ part_from_base[:3, :3].T
    paths = [out_dir / n for n in names]
    with commit_together() as staged:
        folder = staged(paths[0]).parent
        staged(paths[1])
        write_scan_plan(
            folder,
            [sw.base_from_flange(sensor.flange_from_cam) for sw in plan.sweeps],
            record,
            rotation,
        )
        np.savez_compressed(
            staged(paths[2]),
            points_part=points_part,
            normals_part=normals_part,
            visible=plan.visible,
            measured_by=plan.measured_by,
        )
        write_coverage_map(
            staged(paths[3]),
            part,
            points_part,
            plan.visible,
            plan.measured_by,
            f"{part_path.name}: {len(plan.sweeps)} sweeps, {plan.frames} profiles, predicted "
            f"coverage {100 * plan.coverage:.1f} % of the surface visible from above",
        )
    return PlanRun(plan, base_from_part, *paths)


# --------------------------------------------------------------------------------------------
# scan


@dataclass(frozen=True)
class ScanRun:
    """A cloud written: the scan's result (counts, timings, corrections) and the file."""

    result: ScanResult
    out_path: Path


def scan(
    session_dirs: Sequence[Path],
    calibration_path: Path,
    out: Path,
    *,
    options: ScanOptions | None = None,
    work_dir: Path | None = None,
    progress: bool = False,
    check_cancelled: Callable[[], None] | None = None,
) -> ScanRun:
    """Sweep sessions to one base-frame cloud, written atomically (``.ply``, ``.pcd``, ``.e57``).

    Everything that can be refused (file names, calibration, sessions, image sizes) is
    refused before any image is decoded. ``check_cancelled`` is called between chunks of
    frames and between the later steps: what it raises stops the scan (a PLC job's
    cancellation).
    """
    out = Path(out)
    if out.suffix.lower() not in FORMATS:
        raise InputError(
            out, f"expected a {', '.join(FORMATS)} file name, got {out.suffix or 'none'!r}"
        )
    if not session_dirs:
        raise ValueError("sessions: expected at least one sweep session, got none")
    check_outputs_apart([*session_dirs, calibration_path], [out])
    calibration = read_calibration(calibration_path)
    calibration.require_light_plane(calibration_path, "scanning")
    options = options or ScanOptions()
    if options.laser_origin_mm is None and calibration.laser_origin_cam is not None:
        # The calibration's laser origin gives each point's illumination angle.
        options = replace(options, laser_origin_mm=tuple(calibration.laser_origin_cam.tolist()))
    sessions = [read_session(s, check_images=True) for s in session_dirs]
    check_scan_inputs(sessions, calibration)
    result = scan_session(
        sessions,
        calibration,
        options,
        out_path=out,
        work_dir=work_dir,
        progress=progress,
        calibration_path=Path(calibration_path),
        check_cancelled=check_cancelled,
    )
    return ScanRun(result, out)
