"""The full-object scanning job: plan sweeps from CAD, capture, scan and merge, inspect.

``scanner demo --part PART.stl`` runs it on the virtual cell; each step is a stage of
:mod:`scanner.app.stages`:

1. ``plan``     sweeps that cover the part (``plan/``: plan.json, sweeps.csv, coverage map);
2. ``capture``  the planned sweeps rendered with the part on the table (``sessions/sweep``);
3. ``scan``     one cloud from all sweeps without the table, overlapping sweeps refined
                against each other by ICP with every correction reported (``cloud.ply``);
4. ``inspect``  scan-to-CAD: the part's pose found in the cloud, every point's deviation
                (``inspection.json`` and its HTML report);
5. ``coverage`` what the cloud achieved against the plan's prediction, on the plan's own
                surface samples (``coverage_achieved.png``), and ``job.json`` with the figures.

The scan uses the cell's true calibration (``sessions/calibration_true.json``): the job
shows the planning, merging and inspection, not a calibration's error (the demo without
``--part`` shows that).
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from metrology.coverage_map import write_coverage_map
from scanner.app import stages
from scanner.core.fileio import write_json_atomic
from scanner.formats.clouds import read_cloud
from scanner.formats.meshes import TriangleMesh, read_mesh
from scanner.formats.scan_plan import read_scan_plan
from scanner.scanning.coverage import measured_by_cloud
from scanner.scanning.pipeline import ScanOptions
from scanner.scanning.planning import PlanConfig
from scanner.virtual_cell.cell import CellConfig, ObjectConfig, load_cell

__all__ = ["FullObjectResult", "cell_with_part", "full_object_scan_options", "run_full_object"]

log = logging.getLogger(__name__)

STEPS = ("plan", "capture", "scan", "inspect", "coverage")

#: The cloud is kept within the planned part's box grown by this (placement and robot errors).
REGION_MARGIN_MM = 5.0


@dataclass
class FullObjectResult:
    """What the job wrote and measured.

    Attributes
    ----------
    out_dir : Path
    predicted_coverage, achieved_coverage : float
        Shares of the surface visible from above: planned, and found in the cloud.
    sweeps, frames : int
    corrections : list of dict
        ICP correction of each sweep (translation_mm, rotation_deg).
    deviation_rms_mm : float
        Scan-to-CAD deviation RMS of the inlier points.
    verdict : str
    seconds : dict
        Wall time of each step.
    """

    out_dir: Path
    predicted_coverage: float = float("nan")
    achieved_coverage: float = float("nan")
    sweeps: int = 0
    frames: int = 0
    corrections: list[dict[str, Any]] = field(default_factory=list)
    deviation_rms_mm: float = float("nan")
    verdict: str = ""
    seconds: dict[str, float] = field(default_factory=dict)

    @property
    def job_json(self) -> Path:
        return self.out_dir / "job.json"

    @property
    def inspection_html(self) -> Path:
        return self.out_dir / "inspection.html"


def cell_with_part(cell: CellConfig, part_path: Path, base_from_part: np.ndarray) -> CellConfig:
    """The cell with ``part_path`` standing where the plan put it, and nothing else."""
    euler = Rotation.from_matrix(base_from_part[:3, :3]).as_euler("xyz", degrees=True)
    part = ObjectConfig(
        type="mesh",
        id="part",
        path=str(Path(part_path).resolve()),
        center_mm=tuple(float(v) for v in base_from_part[:3, 3]),
        euler_xyz_deg=tuple(float(v) for v in euler),
        albedo=0.6,
    )
    return replace(cell, sweep=replace(cell.sweep, objects=(part,)))


def full_object_scan_options(
    base_from_part: np.ndarray, part: TriangleMesh, workers: int = 2
) -> ScanOptions:
    """How planned sweeps are scanned: precise stripes, ICP between sweeps, only the box where
    the plan put the part (grown by ``REGION_MARGIN_MM``), the table the part stands on (the
    lowest point of the part where the plan put it) left out, and isolated
    points removed (fewer than 3 others within 2 mm: a single stray point tens of mm off would
    otherwise dominate the cloud's RMS against the CAD; a statistical filter would also thin
    the sparse, legitimate points of bore walls seen at a slant)."""
    lo, hi = part.transformed(base_from_part).bounds()
    table_z = float(lo[2])
    return ScanOptions(
        mode="precise",
        icp=True,
        workers=workers,
        table_z_mm=table_z,
        region_mm=(tuple(lo - REGION_MARGIN_MM), tuple(hi + REGION_MARGIN_MM)),
        isolated_radius_mm=2.0,
        isolated_min_neighbors=3,
    )


def _say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def run_full_object(
    part_path: str | Path,
    cell: str = "modern",
    out_dir: str | Path | None = None,
    *,
    seed: int = 0,
    step_mm: float = 1.0,
    coverage: float = 0.95,
    part_yaw_deg: float = 0.0,
    workers: int = 2,
    progress: bool = True,
) -> FullObjectResult:
    """Plan, capture, scan, inspect a part in the virtual cell (see the module's steps).

    Parameters
    ----------
    part_path : path
        The part's mesh (STL, PLY, OBJ), mm, z up; it stands on its lowest face.
    cell : str
        Virtual cell name or TOML.
    out_dir : path, optional
        Default ``reports/part-<part name>``.
    seed : int
        Of the capture (robot repeatability, noise).
    step_mm : float
        Travel between profiles.
    coverage : float
        Target share of the surface visible from above.
    part_yaw_deg : float
        The part turned on the table.
    """
    part_path = Path(part_path)
    out = Path(out_dir) if out_dir is not None else Path("reports") / f"part-{part_path.stem}"
    out.mkdir(parents=True, exist_ok=True)
    result = FullObjectResult(out_dir=out)
    clock = stages.StageClock(result.seconds)
    part = read_mesh(part_path)  # refuse a bad mesh before anything is written

    def step(name: str, fn: Any) -> Any:
        index = STEPS.index(name) + 1
        _say(f"[{index}/{len(STEPS)}] {name} ...")
        value = clock.run(name, fn)
        _say(f"[{index}/{len(STEPS)}] {name} done in {result.seconds[name]:.1f} s")
        return value

    cell_config = load_cell(cell)
    planned = step(
        "plan",
        lambda: stages.plan_scan(
            part_path,
            out / "plan",
            cell=cell_config,
            part_yaw_deg=part_yaw_deg,
            config=PlanConfig(step_mm=step_mm, target_coverage=coverage),
        ),
    )
    plan = planned.plan
    result.predicted_coverage = plan.coverage
    result.sweeps, result.frames = len(plan.sweeps), plan.frames
    if not plan.sweeps:
        raise ValueError(f"{part_path}: no sweep can measure the part ({plan.reason})")
    poses = read_scan_plan(out / "plan").base_from_flange
    scene_cell = cell_with_part(cell_config, part_path, planned.base_from_part)
    sessions = out / "sessions"
    step(
        "capture",
        lambda: stages.simulate(
            scene_cell,
            sessions,
            seed=seed,
            sessions=("sweep",),
            workers=workers,
            progress=progress,
            sweep_paths=poses,
        ),
    )
    cloud_path = out / "cloud.ply"
    scanned = step(
        "scan",
        lambda: stages.scan(
            [sessions / "sweep"],
            sessions / "calibration_true.json",
            cloud_path,
            options=full_object_scan_options(planned.base_from_part, part, workers),
            progress=progress,
        ),
    )
    result.corrections = [
        {
            "sweep": c.sweep,
            "translation_mm": c.translation_mm,
            "rotation_deg": c.rotation_deg,
        }
        for c in scanned.result.corrections
    ]
    inspected = step(
        "inspect",
        lambda: stages.inspect(cloud_path, part_path, out / "inspection.json"),
    )
    result.deviation_rms_mm = float(inspected.result.stats.rms)
    result.verdict = str(inspected.result.verdict)

    def achieved() -> None:
        samples = np.load(out / "plan" / "coverage.npz")
        cloud = read_cloud(cloud_path)
        pts = cloud.point.positions.numpy().astype(np.float64)
        sweep_of = cloud.point["sweep_id"].numpy().reshape(-1).astype(np.int64)
        n_c = inspected.result.alignment.nominal_from_cloud
        pts_part = pts @ n_c[:3, :3].T + n_c[:3, 3]
        radius = max(step_mm, 0.5)
        points_part = samples["points_part"]
        seen = measured_by_cloud(points_part, pts_part, radius)
        visible = samples["visible"]
        result.achieved_coverage = float(np.count_nonzero(seen & visible) / visible.sum())
        from_cloud = np.full(len(points_part), -1, dtype=np.int64)
        if len(pts_part):
            _, nearest = cKDTree(pts_part).query(points_part[seen])
            from_cloud[seen] = sweep_of[nearest]
        write_coverage_map(
            out / "coverage_achieved.png",
            part,
            points_part,
            visible,
            np.where(visible, from_cloud, -1),
            f"{part_path.name}: achieved coverage {100 * result.achieved_coverage:.1f} % "
            f"(planned {100 * result.predicted_coverage:.1f} %)",
        )
        write_json_atomic(
            result.job_json,
            {
                "format": "scan-full-object/1",
                "part": str(part_path),
                "cell": cell_config.name,
                "seed": seed,
                "sweeps": result.sweeps,
                "frames": result.frames,
                "coverage": {
                    "predicted": result.predicted_coverage,
                    "achieved": result.achieved_coverage,
                    "radius_mm": radius,
                },
                "icp_corrections": result.corrections,
                "inspection": {
                    "verdict": result.verdict,
                    "deviation_rms_mm": result.deviation_rms_mm,
                    "alignment_rms_mm": inspected.result.alignment.rms_mm,
                },
                "seconds": result.seconds,
            },
        )

    step("coverage", achieved)
    return result
