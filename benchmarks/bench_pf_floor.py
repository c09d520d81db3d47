"""The sphere form range PF of the cloud as written, taken apart: the robot's share and the stripe's (issue #16).

Issue #16 asks for a form range PF (range of the radial residuals of every point within
1.5 mm of a sphere, about its least-squares sphere) within 0.25 mm. The cloud as written
gives 0.39-0.46 mm on the modern cell and about 0.8 mm on randomised sensor 0. Each point's
error has two sources, and the simulator's truth separates them exactly:

* **the robot**: each sweep stop lies where the robot's repeatability put it
  (``base_from_flange_true``), not where the robot reported it. The scan maps a camera point
  ``c`` to ``reported @ flange_from_cam @ c`` while it lay at ``true @ flange_from_cam @ c``, so
  ``true @ inv(reported)`` applied to a scanned point takes the robot's share away exactly;
* **the stripe** (speckle, sensor noise, the stripe's shape on a curved surface): what is
  left after that.

Per sphere this prints PF and its noise (1.4826 MAD of the residuals) for the cloud as
written, for its points with the robot's share taken away ("stripe only"), and for the true
surface points under the robot's share alone ("robot only": each point with the robot's share
taken away, moved onto the true sphere, then mapped by the reported pose again). Then the
stripe's share is scaled by ``k`` on top of the robot's (``robot + k x stripe``): the largest
``k`` whose PF is within the target says how much quieter the stripe would have to be.

With ``--image``, a second table asks whether a flag of the stripe's profile could find the
stripe's worst points: every third frame extracted again (default options,
``orientation="auto"``) and matched to the rendered stripe, each sphere's unflagged centres'
error along the scan line (px) by the centre's peak intensity relative to the running median
of its profile's (15 lines): a dark speckle grain over the stripe would show as a tail there.
Then the cloud as written with the points below a relative intensity left out (the same
running median, over each frame's points in the cloud): would such a flag pay?

The sweeps are rendered once into ``--work`` (seed 0, about 4-10 min each on two cores) and
scanned as ``scanner scan`` does by default, with the true calibration.

    python benchmarks/bench_pf_floor.py [--work /tmp/bench_pf_floor] [--cases modern randomised-0]
        [--target-mm 0.25] [--image]
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import numpy as np
from bench_laser_origin import apart_from_others, fit_sphere, sphere_figures, surface_distance
from bench_sphere_bias import cases
from bench_stretch_ends import sweep_centre_errors
from scipy.ndimage import median_filter

from scanner.app import stages
from scanner.core.conventions import invert_transform, transform_points
from scanner.formats.clouds import cloud_arrays, read_cloud
from scanner.virtual_cell.truth import CellTruth, ObjectTruth, read_truth


def robot_corrections(truth: CellTruth, frame_ids: np.ndarray) -> dict[int, np.ndarray]:
    """Per sweep frame id in ``frame_ids``: ``true @ inv(reported)`` (4x4), which takes the
    robot's repeatability error out of a point the scan put in the base frame."""
    session = truth.sessions["sweep"]
    out = {}
    for fid in np.unique(frame_ids):
        f = session.frame(int(fid))
        out[int(fid)] = f.base_from_flange_true @ invert_transform(f.base_from_flange_reported)
    return out


def per_frame(fn, points: np.ndarray, frame_ids: np.ndarray, moves: dict[int, np.ndarray]):
    """``points`` (N, 3) with ``fn(move)`` applied frame by frame: (N, 3)."""
    out = np.empty_like(points)
    for fid, move in moves.items():
        sel = frame_ids == fid
        out[sel] = transform_points(fn(move), points[sel])
    return out


def form_range(points: np.ndarray, obj: ObjectTruth) -> tuple[float, float, float]:
    """PF (mm), noise (1.4826 MAD of the residuals, mm) and diameter error (mm) of ``points``
    (N, 3) about their least-squares sphere."""
    c0 = np.asarray(obj.params["center_mm"], dtype=np.float64)
    r0 = 0.5 * float(obj.params["diameter_mm"])
    x, res = fit_sphere(points, np.append(c0, r0))
    sigma = 1.4826 * float(np.median(np.abs(res - np.median(res))))
    return float(res.max() - res.min()), sigma, float(2.0 * (x[3] - r0))


def onto_sphere(points: np.ndarray, obj: ObjectTruth) -> np.ndarray:
    """``points`` (N, 3) moved radially onto the true sphere ``obj``."""
    c0 = np.asarray(obj.params["center_mm"], dtype=np.float64)
    q = points - c0
    return c0 + 0.5 * float(obj.params["diameter_mm"]) * q / np.linalg.norm(q, axis=1)[:, None]


def run_case(name: str, work: Path, target_mm: float) -> None:
    sim = work / name
    if not (sim / "truth.json").is_file():
        stages.simulate(cases()[name], sim, seed=0, sessions=("sweep",), workers=2)
    truth = read_truth(sim / "truth.json")
    cloud = sim / "cloud_default.ply"
    if not cloud.is_file():
        stages.scan([sim / "sweep"], sim / "calibration_true.json", cloud)
    arrays = cloud_arrays(read_cloud(cloud))
    scanned = arrays["positions"]
    frame_ids = arrays["frame_id"].ravel().astype(int)
    moves = robot_corrections(truth, frame_ids)
    stripe_only = per_frame(lambda m: m, scanned, frame_ids, moves)
    apart = apart_from_others(scanned, truth)
    ks = np.round(np.arange(0.0, 1.0001, 0.05), 2)
    print(f"\n### {name}: sweep seed 0, true calibration, the cloud as written\n")
    print(
        "| sphere | points | as written: PF / noise mm | stripe only | robot only | "
        f"largest k with PF <= {target_mm:g} mm (robot + k x stripe) | stripe noise then mm |"
    )
    print("|---|---:|---|---|---|---:|---:|")
    for obj in truth.objects:
        if obj.type != "sphere":
            continue
        near = (surface_distance(scanned, obj) < 1.5) & apart
        pts, fid = scanned[near], frame_ids[near]
        clean = stripe_only[near]
        on_sphere = onto_sphere(clean, obj)
        robot_only = per_frame(invert_transform, on_sphere, fid, moves)
        stripe_err = clean - on_sphere
        rows = [form_range(p, obj) for p in (pts, clean, robot_only)]
        within = [k for k in ks if form_range(robot_only + k * stripe_err, obj)[0] <= target_mm]
        k_max = max(within) if within else 0.0
        cells = " | ".join(f"{pf:.3f} / {sigma:.4f}" for pf, sigma, _ in rows)
        print(f"| {obj.id} | {near.sum()} | {cells} | {k_max:.2f} | {k_max * rows[1][1]:.4f} |")
    print(
        "\nDiameter errors (mm), as written / stripe only / robot only: "
        + "; ".join(
            f"{obj.id} "
            + " / ".join(
                f"{form_range(p, obj)[2]:+.4f}"
                for p in (
                    scanned[m],
                    stripe_only[m],
                    per_frame(
                        invert_transform, onto_sphere(stripe_only[m], obj), frame_ids[m], moves
                    ),
                )
            )
            for obj in truth.objects
            if obj.type == "sphere"
            for m in [(surface_distance(scanned, obj) < 1.5) & apart]
        )
    )


def intensity_dip_table(name: str, work: Path) -> None:
    """Each sphere's unflagged centres' along-line error (px) by relative peak intensity."""
    bins = [0.0, 0.55, 0.7, 0.85, 1.0, 1.2, np.inf]
    errors: dict[str, list[np.ndarray]] = {}
    relative: dict[str, list[np.ndarray]] = {}
    for fe in sweep_centre_errors(work / name, every=3):
        p = fe.profile
        peak = p.intensity.astype(np.float64)
        rel = peak / np.maximum(median_filter(peak, 15, mode="nearest"), 1.0)
        ok = fe.matched & (p.flags == 0)
        for surface in ("sphere_1", "sphere_2"):
            sel = ok & (fe.surface == surface)
            errors.setdefault(surface, []).append(fe.error_px[sel])
            relative.setdefault(surface, []).append(rel[sel])
    print(f"\n{name}, in the image: unflagged sphere centres' error along the scan line (px)\n")
    print("| sphere | relative peak intensity | share of points | RMS | p99 of abs |")
    print("|---|---|---:|---:|---:|")
    for surface, parts in errors.items():
        e, r = np.concatenate(parts), np.concatenate(relative[surface])
        for lo, hi in itertools.pairwise(bins):
            m = (r >= lo) & (r < hi)
            if m.any():
                print(
                    f"| {surface} | {lo:g}-{hi:g} | {100 * m.mean():.1f} % | "
                    f"{np.sqrt(np.mean(e[m] ** 2)):.3f} | {np.percentile(np.abs(e[m]), 99):.2f} |"
                )


def dip_cut_table(name: str, work: Path) -> None:
    """The cloud's sphere figures with the points below a relative peak intensity left out."""
    truth = read_truth(work / name / "truth.json")
    arrays = cloud_arrays(read_cloud(work / name / "cloud_default.ply"))
    points = arrays["positions"]
    frame_ids = arrays["frame_id"].ravel().astype(int)
    peak = arrays["intensity"].ravel().astype(np.float64)
    rel = np.empty_like(peak)
    for fid in np.unique(frame_ids):
        sel = np.flatnonzero(frame_ids == fid)
        rel[sel] = peak[sel] / np.maximum(median_filter(peak[sel], 15, mode="nearest"), 1.0)
    print(f"\n{name}: the cloud as written without the points below a relative peak intensity\n")
    print(
        "| left out below | points left out | sphere_1 diameter / PF mm | sphere_2 | spacing mm |"
    )
    print("|---:|---:|---|---|---:|")
    for cut in (0.0, 0.5, 0.55, 0.6, 0.7):
        keep = rel >= cut
        f = sphere_figures(points[keep], truth)
        cells = " | ".join(
            f"{f[f'sphere_{k} diameter error']:+.4f} / {f[f'sphere_{k} PF']:.3f}" for k in (1, 2)
        )
        print(
            f"| {cut:g} | {100 * (1 - keep.mean()):.1f} % | {cells} | {f['spacing error']:+.4f} |"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_pf_floor"))
    ap.add_argument("--cases", nargs="+", default=["modern", "randomised-0"])
    ap.add_argument("--target-mm", type=float, default=0.25)
    ap.add_argument("--image", action="store_true", help="also the in-image table")
    args = ap.parse_args()
    for name in args.cases:
        run_case(name, args.work, args.target_mm)
        if args.image:
            intensity_dip_table(name, args.work)
            dip_cut_table(name, args.work)


if __name__ == "__main__":
    main()
