"""The laser origin estimated by ``scanner calibrate`` (issue #16) against the cells' truth.

For each cell and seed: a calibration session is rendered, calibrated (``stages.calibrate``, the
command's stage), and the ``laser_origin_cam`` it writes compared with the cell's design origin:
the error, the stated one-sigma within the plane, and the Mahalanobis distance of the error under
the stated covariance (2 degrees of freedom: 95 % of honest estimates lie within 2.45).
Cells: the modern and the paper cell, and randomised sensors (other camera, lens, laser baseline
and fan tilt: :func:`scanner.virtual_cell.random_cell.randomised_cell`).

``--spheres`` also scans the sweep (seed 0) of the modern cell and of randomised sensor 0 with
the true calibration three ways: as ``scanner scan`` does by default, and in precise mode with a
65 deg incidence limit using the design origin and then the estimated one (that cell's seed 0).
Each cloud as written is judged against the truth: every point within 1.5 mm of each sphere
(and not within 1.5 mm of the bar joining them), the least-squares diameter's error, the form
range PF and the spacing's error, with the points' noise and the range that noise alone gives.
Targets (issue #16): diameters within 0.03 mm, PF within 0.25 mm, spacing within 0.05 mm; the
estimated origin changes the figures by less than 0.005 mm.

    python benchmarks/bench_laser_origin.py [--seeds 3] [--randomised 3] [--spheres]
        [--work /tmp/bench_laser_origin]

Results are cached per case in ``WORK/<cell>-<seed>/result.json`` (delete to measure again).
"""

from __future__ import annotations

import argparse
import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from scanner.app import stages
from scanner.formats.calibration_file import read_calibration, write_calibration
from scanner.formats.clouds import cloud_arrays, read_cloud
from scanner.scanning.pipeline import ScanOptions
from scanner.virtual_cell.cell import CellConfig, load_cell
from scanner.virtual_cell.random_cell import randomised_cell
from scanner.virtual_cell.truth import CellTruth, ObjectTruth, read_truth

SPHERE_FIGURES = ("sphere spacing", "sphere_1 diameter", "sphere_2 diameter")


def run_case(kind: str, seed: int, work: Path) -> dict:
    """Render, calibrate and compare one case; cached in ``work/<kind>-<seed>/result.json``."""
    folder = work / f"{kind}-{seed:03d}"
    cached = folder / "result.json"
    if cached.is_file():
        return json.loads(cached.read_text())
    if kind == "randomised":
        cell = randomised_cell(load_cell("modern"), np.random.default_rng(10_000 + seed))
    else:
        cell = load_cell(kind)
    sim = folder / "sim"
    truth = stages.simulate(cell, sim, seed=seed, sessions=("calibration",), workers=2)
    run = stages.calibrate(sim / "calibration", folder / "cal.json", report=None)
    cal = run.result.calibration
    record = dict(cal.quality.record.get("laser_origin") or {})
    true_origin = np.asarray(truth.laser_origin_cam, dtype=np.float64)
    result = {"kind": kind, "seed": seed, "true_mm": true_origin.tolist(), **record}
    if record.get("estimated"):
        err = np.asarray(record["origin_cam_mm"]) - true_origin
        cov = np.asarray(record["covariance_mm2"])
        result["error_mm"] = err.tolist()
        result["error_norm_mm"] = float(np.linalg.norm(err))
        result["mahalanobis"] = float(np.sqrt(err @ np.linalg.pinv(cov) @ err))
        result["written"] = cal.laser_origin_cam is not None
    shutil.rmtree(sim / "calibration", ignore_errors=True)
    folder.mkdir(parents=True, exist_ok=True)
    cached.write_text(json.dumps(result, indent=1))
    return result


def surface_distance(points: np.ndarray, obj: ObjectTruth) -> np.ndarray:
    """Unsigned distance of ``points`` (N, 3) to a true sphere, cylinder or plane, mm."""
    p = obj.params
    if obj.type == "sphere":
        c = np.asarray(p["center_mm"], dtype=np.float64)
        return np.abs(np.linalg.norm(points - c, axis=1) - 0.5 * float(p["diameter_mm"]))
    if obj.type == "cylinder":
        p0, p1 = np.asarray(p["p0_mm"], float), np.asarray(p["p1_mm"], float)
        axis = (p1 - p0) / np.linalg.norm(p1 - p0)
        t = np.clip((points - p0) @ axis, 0.0, np.linalg.norm(p1 - p0))
        radial = np.linalg.norm(points - p0 - np.outer(t, axis), axis=1)
        return np.abs(radial - 0.5 * float(p["diameter_mm"]))
    if obj.type == "plane":
        return np.abs(points @ np.asarray(p["normal"], float) + float(p["d"]))
    return np.full(len(points), np.inf)


def apart_from_others(points: np.ndarray, truth: CellTruth, gap_mm: float = 1.5) -> np.ndarray:
    """Which of ``points`` (N, 3) lie more than ``gap_mm`` from every true object that is not a
    sphere (the bar, post and table joining the spheres): (N,) bool."""
    apart = np.ones(len(points), bool)
    for obj in truth.objects:
        if obj.type != "sphere":
            apart &= surface_distance(points, obj) > gap_mm
    return apart


def cloud_sphere_figures(cloud_path: Path, truth: CellTruth) -> dict[str, float]:
    """The cloud as written, every point within 1.5 mm of each true sphere (and not within
    1.5 mm of the bar, post or table joining it): :func:`sphere_figures` of its points."""
    return sphere_figures(cloud_arrays(read_cloud(cloud_path))["positions"], truth)


def sphere_points(points: np.ndarray, truth: CellTruth) -> list[tuple[ObjectTruth, np.ndarray]]:
    """Each true sphere with its points among ``points`` (N, 3), base frame, mm: those within
    1.5 mm of it and not within 1.5 mm of the bar, post or table joining it ((M, 3) each)."""
    apart = apart_from_others(points, truth)
    return [
        (obj, points[(surface_distance(points, obj) < 1.5) & apart])
        for obj in truth.objects
        if obj.type == "sphere"
    ]


def fit_sphere(points: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares sphere of ``points`` (N, 3) from ``start`` (centre x, y, z, radius, mm):
    the fitted (4,) and the radial residuals (N,)."""
    fit = least_squares(lambda x: np.linalg.norm(points - x[:3], axis=1) - x[3], start)
    return fit.x, fit.fun


def sphere_figures(points: np.ndarray, truth: CellTruth) -> dict[str, float]:
    """Each true sphere's points among ``points`` (N, 3), base frame, mm, as
    :func:`sphere_points` takes them: the least-squares diameter's error, the form range PF
    (range of radial residuals), the spacing's error; and the points' noise (1.4826 MAD of the
    residuals) with the range that noise alone gives that many Gaussian points (about
    2 sigma sqrt(2 ln N))."""
    out: dict[str, float] = {}
    centres = []
    for k, (obj, near) in enumerate(sphere_points(points, truth), start=1):
        c0 = np.asarray(obj.params["center_mm"], dtype=np.float64)
        r0 = 0.5 * float(obj.params["diameter_mm"])
        x, res = fit_sphere(near, np.append(c0, r0))
        sigma = 1.4826 * float(np.median(np.abs(res - np.median(res))))
        out[f"sphere_{k} diameter error"] = 2 * (x[3] - r0)
        out[f"sphere_{k} PF"] = float(res.max() - res.min())
        out[f"sphere_{k} noise sigma"] = sigma
        out[f"sphere_{k} PF of that noise alone"] = 2 * sigma * np.sqrt(2 * np.log(len(near)))
        out[f"sphere_{k} points"] = len(near)
        centres.append((x[:3], c0))
    if len(centres) == 2:
        (a, ta), (b, tb) = centres
        out["spacing error"] = float(np.linalg.norm(a - b) - np.linalg.norm(ta - tb))
    return out


def sphere_change(
    work: Path, name: str, cell: CellConfig, estimated_mm: list[float]
) -> dict[str, dict[str, float]]:
    """A cell's sweep (seed 0) scanned three ways with the true calibration: as ``scanner scan``
    does by default, and in precise mode with a 65 deg incidence limit using the design origin
    and ``estimated_mm``; each cloud's sphere figures as written (:func:`cloud_sphere_figures`)."""
    folder = work / f"spheres-{name}"
    sim = folder / "sim"
    if not (sim / "truth.json").is_file():
        stages.simulate(cell, sim, seed=0, sessions=("sweep",), workers=2)
    truth = read_truth(sim / "truth.json")
    true_cal = read_calibration(sim / "calibration_true.json")
    runs = {
        "default scan": (None, ScanOptions()),
        "precise, 65 deg, design origin": (
            truth.laser_origin_cam,
            ScanOptions(mode="precise", max_incidence_deg=65.0),
        ),
        "precise, 65 deg, estimated origin": (
            estimated_mm,
            ScanOptions(mode="precise", max_incidence_deg=65.0),
        ),
    }
    figures = {}
    for k, (run, (origin, options)) in enumerate(runs.items()):
        cal_path = folder / f"cal_{k}.json"
        write_calibration(
            cal_path,
            replace(
                true_cal,
                laser_origin_cam=None if origin is None else np.asarray(origin, dtype=np.float64),
            ),
        )
        cloud = folder / f"cloud_{k}.ply"
        if not cloud.is_file():
            stages.scan([sim / "sweep"], cal_path, cloud, options=options)
        figures[run] = cloud_sphere_figures(cloud, truth)
    return figures


def _print_spheres(title: str, figures: dict[str, dict[str, float]]) -> None:
    names = list(figures)
    print(f"\n{title}; the cloud as written, every point within 1.5 mm of each sphere:")
    print("| figure | " + " | ".join(names) + " |")
    print("|---|" + "---:|" * len(names))
    for key in figures[names[0]]:
        fmt = "{:.0f}" if key.endswith("points") else "{:+.4f}"
        print(f"| {key} | " + " | ".join(fmt.format(figures[n][key]) for n in names) + " |")
    a, b = figures[names[1]], figures[names[2]]
    change = max(abs(a[k] - b[k]) for k in a if "error" in k)
    print(
        f"\nlargest change of a diameter or spacing error, estimated against design origin: "
        f"{change:.4f} mm"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=3, help="seeds of the modern and paper cells")
    ap.add_argument("--randomised", type=int, default=3, help="randomised sensors")
    ap.add_argument("--spheres", action="store_true", help="also the sphere figures' change")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_laser_origin"))
    args = ap.parse_args()
    cases = [("modern", s) for s in range(args.seeds)] + [("paper", s) for s in range(args.seeds)]
    cases += [("randomised", s) for s in range(args.randomised)]
    results = [run_case(kind, seed, args.work) for kind, seed in cases]
    print(
        "| cell | seed | error (x, y, z) mm | abs error mm | stated std mm | Mahalanobis |"
        " shadow edges used / found | frames | written |"
    )
    print("|---|---:|---|---:|---:|---:|---|---:|---|")
    for r in results:
        if not r.get("estimated"):
            print(f"| {r['kind']} | {r['seed']} | not estimated: {r.get('reason')} | | | | | | |")
            continue
        e = ", ".join(f"{v:+.2f}" for v in r["error_mm"])
        print(
            f"| {r['kind']} | {r['seed']} | {e} | {r['error_norm_mm']:.2f} | {r['std_mm']:.2f} | "
            f"{r['mahalanobis']:.2f} | {r['inliers']} / {r['lines']} | {len(r['frames'])} | "
            f"{'yes' if r['written'] else 'no'} |"
        )
    done = [r for r in results if r.get("estimated")]
    if done:
        within = sum(r["error_norm_mm"] <= 2.0 for r in done)
        covered = sum(r["mahalanobis"] <= 2.45 for r in done)
        print(
            f"\nestimated {len(done)} of {len(results)}; within 2 mm: {within}; error within "
            f"the stated 95 % ellipse: {covered}; worst error {max(r['error_norm_mm'] for r in done):.2f} mm"
        )
    if args.spheres:
        for kind, cell in (
            ("modern", load_cell("modern")),
            ("randomised", randomised_cell(load_cell("modern"), np.random.default_rng(10_000))),
        ):
            case = next((r for r in results if r["kind"] == kind and r["seed"] == 0), None)
            if case is None or not case.get("estimated"):
                continue
            figures = sphere_change(args.work, kind, cell, case["origin_cam_mm"])
            _print_spheres(f"{kind} cell's sweep (seed 0), true calibration", figures)


if __name__ == "__main__":
    main()
