"""Full-object scanning jobs (issue #21): coverage planned and achieved, merged-cloud accuracy,
seams between sweeps, wall time - on the three sample parts of ``configs/parts``.

    python benchmarks/bench_full_object.py                    # all parts, modern cell
    python benchmarks/bench_full_object.py --parts bracket --cell paper --step-mm 1.0
    python benchmarks/bench_full_object.py --plan-only     # planning alone, both cells

Each case runs ``scanner demo --part`` (plan, capture in the virtual cell, scan with the true
calibration and ICP between sweeps, inspect) and then compares the merged cloud with the true
mesh where the virtual cell put it:

* coverage: predicted by the plan and achieved (plan samples with a cloud point within the
  frame step), both as shares of the surface visible from above;
* accuracy: distance of every cloud point to the true mesh - RMS of the merged cloud against
  the RMS of the best single sweep (the target: within 1.5x), and the share beyond 0.2 mm;
* seams: for every pair of sweeps, the mean signed distance to the mesh of each sweep's points
  where both measured the surface (a point of the other within 0.5 mm); the largest difference
  of the two means over all pairs (the target: at most 0.02 mm);
* time: the job's wall time from plan to inspection report (the target: a 6-sweep job of 1000
  frames within 5 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from scanner.formats.clouds import read_cloud
from scanner.formats.meshes import read_mesh
from scanner.scanning.planning import PlanConfig, place_on_table, plan_sweeps
from scanner.virtual_cell import load_cell

REPO = Path(__file__).resolve().parents[1]


def signed_distance(mesh_path: str, base_from_part: np.ndarray, points: np.ndarray) -> np.ndarray:
    mesh = read_mesh(mesh_path).transformed(base_from_part)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)),
        o3d.core.Tensor(mesh.triangles.astype(np.uint32)),
    )
    return scene.compute_signed_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def seams_mm(points: np.ndarray, sweep: np.ndarray, dist: np.ndarray) -> float:
    worst = 0.0
    ids = np.unique(sweep)
    trees = {k: cKDTree(points[sweep == k]) for k in ids}
    for i in ids:
        for j in ids[ids > i]:
            pi, pj = points[sweep == i], points[sweep == j]
            near_i = np.isfinite(trees[j].query(pi, distance_upper_bound=0.5)[0])
            near_j = np.isfinite(trees[i].query(pj, distance_upper_bound=0.5)[0])
            if near_i.sum() < 200 or near_j.sum() < 200:
                continue
            di, dj = dist[sweep == i][near_i], dist[sweep == j][near_j]
            keep_i, keep_j = np.abs(di) < 0.2, np.abs(dj) < 0.2  # edges and strays aside
            worst = max(worst, abs(float(di[keep_i].mean() - dj[keep_j].mean())))
    return worst


def run_case(part: str, cell: str, step_mm: float, seed: int, root: Path) -> dict:
    out = root / f"{cell}-{part}"
    mesh = REPO / "configs" / "parts" / f"{part}.stl"
    argv = [sys.executable, "-m", "scanner", "demo", "--part", str(mesh), "--cell", cell]
    argv += ["--out", str(out), "--seed", str(seed), "--step-mm", str(step_mm)]
    t0 = time.perf_counter()
    subprocess.run(argv, check=True, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    job = json.loads((out / "job.json").read_text())
    plan = json.loads((out / "plan" / "plan.json").read_text())
    cloud = read_cloud(out / "cloud.ply")
    pts = cloud.point.positions.numpy().astype(np.float64)
    sweep = cloud.point["sweep_id"].numpy().ravel()
    dist = signed_distance(plan["part"]["path"], np.asarray(plan["part"]["base_from_part"]), pts)
    single = min(np.sqrt(np.mean(dist[sweep == k] ** 2)) for k in np.unique(sweep))
    merged = float(np.sqrt(np.mean(dist**2)))
    return {
        "part": part,
        "cell": cell,
        "sweeps": job["sweeps"],
        "frames": job["frames"],
        "predicted": job["coverage"]["predicted"],
        "achieved": job["coverage"]["achieved"],
        "rms_mm": merged,
        "single_rms_mm": float(single),
        "beyond_0_2": float(np.mean(np.abs(dist) > 0.2)),
        "seam_mm": seams_mm(pts, sweep, dist),
        "icp_max_mm": max((c["translation_mm"] for c in job["icp_corrections"]), default=0.0),
        "seconds": wall,
        "render_s": job["seconds"].get("capture", float("nan")),
    }


def plan_table(parts: list[str], step_mm: float) -> None:
    """Predicted coverage, sweeps and planning time for each part on both cells, two yaws."""
    print("| cell | part | yaw | sweeps | profiles | predicted coverage | visible share | time |")
    print("|---|---|---|---|---|---|---|---|")
    for cell_name in ("modern", "paper"):
        cell = load_cell(cell_name)
        at = (cell.sweep.center_mm[0], cell.sweep.center_mm[1], cell.sweep.table_z_mm)
        for part in parts:
            mesh = read_mesh(REPO / "configs" / "parts" / f"{part}.stl")
            for yaw in (0.0, 37.0):
                t0 = time.perf_counter()
                placed = mesh.transformed(place_on_table(mesh, at, yaw))
                plan = plan_sweeps(cell.sensor_geometry(), placed, PlanConfig(step_mm=step_mm))
                print(
                    f"| {cell_name} | {part} | {yaw:g} | {len(plan.sweeps)} | {plan.frames} | "
                    f"{100 * plan.coverage:.1f} % | {100 * plan.visible_share:.1f} % | "
                    f"{time.perf_counter() - t0:.1f} s |"
                )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parts", nargs="+", default=["bracket", "stepped", "flange"])
    ap.add_argument("--cell", default="modern")
    ap.add_argument("--step-mm", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--plan-only", action="store_true", help="the planning table alone")
    args = ap.parse_args()
    if args.plan_only:
        plan_table(args.parts, args.step_mm)
        return
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for part in args.parts:
            rows.append(run_case(part, args.cell, args.step_mm, args.seed, Path(tmp)))
            r = rows[-1]
            print(f"{part}: {json.dumps(r)}", file=sys.stderr, flush=True)
    print(
        "| part | cell | sweeps | profiles | coverage planned | achieved | RMS merged / best "
        "single sweep (mm) | > 0.2 mm | worst seam (mm) | largest ICP correction (mm) | "
        "job wall time (render) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['part']} | {r['cell']} | {r['sweeps']} | {r['frames']} | "
            f"{100 * r['predicted']:.1f} % | {100 * r['achieved']:.1f} % | "
            f"{r['rms_mm']:.4f} / {r['single_rms_mm']:.4f} ({r['rms_mm'] / r['single_rms_mm']:.2f}x) | "
            f"{100 * r['beyond_0_2']:.2f} % | {r['seam_mm']:.4f} | {r['icp_max_mm']:.4f} | "
            f"{r['seconds']:.0f} s ({r['render_s']:.0f} s) |"
        )


if __name__ == "__main__":
    main()
