# ruff: noqa: E402  (thread limits are set before NumPy loads)
"""Scan chain: throughput from decoded frames to a base-frame cloud, and virtual-cell accuracy.

Throughput: frames already decoded in memory (as a frame grabber delivers them), through
stripe extraction (fast mode), triangulation (undistortion table, light plane, robot pose) and
the Open3D tensor cloud, on one and on two worker processes. Target: >= 1 million points/s.

Accuracy (``--cell DIR``, a ``simulate_cell`` output with ``sweep/``, ``truth.json`` and
``calibration_true.json``; or ``--simulate N`` to render a modern-cell sweep of N frames into a
temporary folder first): ``scan_session`` with the true calibration, then the sphere bar
(spacing and diameters) and the plate's top (flatness) against the truth. Targets: spacing
within 0.05 mm, diameter within 0.03 mm; the plate's residual range should be that of the
stripe noise (range / RMS about 6 for Gaussian noise, larger for systematic form).
Points seen or lit beyond ``--max-incidence`` degrees are dropped (``ScanOptions``; the laser's
emitter position is the sensor's design value, read from the cell's description): grazing
stripes are skewed and their centres biased, and on a sphere they sit at the rim of the cap,
where they move the fitted radius most.

    python benchmarks/bench_scan.py [--frames 400] [--cell DIR | --simulate 400]
        [--max-incidence 65]
"""

from __future__ import annotations

import os

# One core means one BLAS thread too (set before NumPy loads).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import multiprocessing
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from scanner.formats.calibration_file import Calibration
from scanner.scanning.stitch import build_cloud
from scanner.scanning.triangulate import Triangulator
from scanner.stripe.extract import (
    StripeFlag,
    StripeOptions,
    auto_half_window,
    estimate_noise,
    extract_stripe,
)
from scanner.virtual_cell.analytic import StripeSegment, TableStepScene, render_stripes

SHAPE = (768, 1024)
_FRAMES: list[np.ndarray] = []  # inherited by forked workers, never pickled


def _calibration() -> Calibration:
    cal = TableStepScene(width=SHAPE[1], height=SHAPE[0], focal_px=1400.0).calibration()
    cal.dist = np.array([-0.12, 0.08, 0.0005, -0.0003, -0.01])
    return cal


def _frames(n_distinct: int = 24) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    out = []
    for i in range(n_distinct):
        seg = StripeSegment(
            (0, SHAPE[0]),
            (rng.uniform(300, 700), rng.uniform(-0.2, 0.2), rng.uniform(-1e-4, 1e-4)),
            amplitude=rng.uniform(120, 200),
            sigma_px=1.5,
        )
        img, _ = render_stripes(SHAPE, [seg], noise=2.0, background=8.0, seed=i, supersample=1)
        out.append(img)
    return out


def _extract_range(args: tuple[int, int, StripeOptions]) -> tuple[np.ndarray, ...]:
    start, stop, opts = args
    cv2.setNumThreads(1)
    us, vs, fs, its = [], [], [], []
    for i in range(start, stop):
        p = extract_stripe(_FRAMES[i], mode="fast", orientation="rows", options=opts)
        us.append(p.u)
        vs.append(p.v)
        its.append(p.intensity)
        fs.append(np.full(len(p), i, np.int32))
    return np.concatenate(us), np.concatenate(vs), np.concatenate(its), np.concatenate(fs)


def throughput(n_frames: int) -> None:
    global _FRAMES
    distinct = _frames()
    _FRAMES = [distinct[i % len(distinct)] for i in range(n_frames)]
    cal = _calibration()
    # Per-sweep constants, as scan_session fixes them once: window and noise.
    noise = estimate_noise(_FRAMES[0])
    opts = StripeOptions(half_window_px=auto_half_window(_FRAMES[0], noise), noise=noise)
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    poses[:, 0, 3] = np.arange(n_frames) * 0.1
    tri = Triangulator(cal)

    rows = []
    for workers in (1, 2):
        c0 = time.process_time()
        t0 = time.perf_counter()
        chunk = 32
        jobs = [(s, min(n_frames, s + chunk), opts) for s in range(0, n_frames, chunk)]
        if workers == 1:
            parts = [_extract_range(j) for j in jobs]
        else:
            ctx = multiprocessing.get_context("fork")
            with ProcessPoolExecutor(workers, mp_context=ctx) as pool:
                parts = list(pool.map(_extract_range, jobs))
        u, v, inten, fi = (np.concatenate(x) for x in zip(*parts))
        t1 = time.perf_counter()
        pts = tri.points_base(np.column_stack([u, v]), fi, poses)
        t2 = time.perf_counter()
        cloud = build_cloud(pts, {"intensity": inten, "frame_id": fi})
        t3 = time.perf_counter()
        n = len(cloud.point.positions)
        cpu = time.process_time() - c0 if workers == 1 else float("nan")
        rows.append((workers, n, t1 - t0, t2 - t1, t3 - t2, t3 - t0, cpu))
    print(
        f"\nThroughput, {n_frames} decoded 1024x768 frames in memory -> base-frame cloud (fast mode)"
    )
    print(
        f"{'workers':>7s} {'points':>9s} {'extract':>9s} {'triang.':>8s} {'cloud':>7s}"
        f" {'wall pts/s':>12s} {'CPU pts/s':>12s} {'frames/s':>9s}"
    )
    for w, n, te, tt, tc, tall, cpu in rows:
        print(
            f"{w:7d} {n:9d} {te:8.2f}s {tt:7.3f}s {tc:6.3f}s {n / tall:12,.0f}"
            f" {n / cpu:12,.0f} {n_frames / tall:9.0f}"
        )
    w, n, te, tt, tc, tall, _ = rows[-1]
    print(
        f"stage rates (2 workers, wall): extraction {n / te:,.0f} pts/s, "
        f"triangulation {n / tt:,.0f} pts/s; target chain >= 1,000,000 pts/s"
    )
    print("CPU pts/s: the one-worker chain per CPU second of this process (robust to other load)")


def _local_sphere_fit(p: np.ndarray) -> tuple[np.ndarray, float]:
    a = np.column_stack([2 * p, np.ones(len(p))])
    b = (p**2).sum(axis=1)
    x, *_ = np.linalg.lstsq(a, b, rcond=None)
    c = x[:3]
    return c, float(np.sqrt(x[3] + c @ c))


def _fit_sphere(p: np.ndarray) -> tuple[np.ndarray, float, float]:
    try:
        from metrology.fits import fit_sphere

        f = fit_sphere(p)
        if f:
            return np.asarray(f.center_mm), float(f.radius_mm), float(f.rms_mm)
    except ImportError:
        pass
    c, r = _local_sphere_fit(p)
    return c, r, float(np.sqrt(np.mean((np.linalg.norm(p - c, axis=1) - r) ** 2)))


def _cylinder_distance(p: np.ndarray, params: dict) -> np.ndarray:
    """Distance of points to a finite cylinder's surface (axis segment p0-p1, diameter)."""
    p0, p1 = np.asarray(params["p0_mm"]), np.asarray(params["p1_mm"])
    axis = p1 - p0
    length = np.linalg.norm(axis)
    axis = axis / length
    t = np.clip((p - p0) @ axis, 0.0, length)
    radial = np.linalg.norm(p - (p0 + t[:, None] * axis), axis=1)
    return np.abs(radial - params["diameter_mm"] / 2)


def _fit_plane(p: np.ndarray) -> tuple[np.ndarray, float]:
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[2]
    return n, float(-n @ c)


def accuracy(
    cell_dir: Path, max_incidence_deg: float | None = 65.0, laser_origin: bool = True
) -> None:
    from scanner.scanning.pipeline import ScanOptions, scan_session
    from scanner.virtual_cell.truth import read_truth

    truth = read_truth(cell_dir / "truth.json")
    objects = {o.id: {"type": o.type, "params": o.params} for o in truth.objects}
    spheres = [{"id": o.id, "params": o.params} for o in truth.objects if o.type == "sphere"]
    sphere_pairs = truth.extra.get("sphere_pairs", [])
    limit = f"incidence <= {max_incidence_deg:g} deg" if max_incidence_deg else "no incidence limit"
    if max_incidence_deg and not laser_origin:
        limit += ", viewing angle only (no laser origin)"
    print(f"\nVirtual cell accuracy ({cell_dir}, true calibration, {limit})")
    header = (
        f"{'mode':8s} {'points':>8s} {'time':>6s} {'sphere':>9s} {'d err mm':>9s} {'fit RMS':>8s}"
        f" {'spacing err':>12s} {'plate RMS':>10s} {'range':>7s} {'range/RMS':>10s}"
    )
    print(header)
    for mode in ("fast", "precise"):
        r = scan_session(
            cell_dir / "sweep",
            cell_dir / "calibration_true.json",
            ScanOptions(
                mode=mode,
                max_incidence_deg=max_incidence_deg or None,
                laser_origin_mm=tuple(truth.laser_origin_cam) if laser_origin else None,
            ),
            None,
            progress=False,
        )
        pts = r.cloud.point.positions.numpy()
        flags = r.cloud.point.flags.numpy().ravel()
        # Points a metrology step would trust: not low-contrast, not ambiguous (saturated is
        # fine: the flanks give the centre).
        trusted = (flags & int(StripeFlag.LOW_CONTRAST | StripeFlag.AMBIGUOUS)) == 0
        # Distance to the other objects, to keep the bar and post (which touch the spheres)
        # out of the sphere fits.
        cyl = [o.params for o in truth.objects if o.type == "cylinder"]
        near_cyl = np.zeros(len(pts), bool)
        for c in cyl:
            near_cyl |= _cylinder_distance(pts, c) < 1.5
        centres = {}
        lines = []
        for o in spheres:
            c0 = np.asarray(o["params"]["center_mm"])
            r0 = o["params"]["diameter_mm"] / 2
            near = (np.abs(np.linalg.norm(pts - c0, axis=1) - r0) < 1.0) & ~near_cyl & trusted
            if np.count_nonzero(near) < 50:
                lines.append(f"{o['id']:>9s} too few points ({np.count_nonzero(near)})")
                continue
            c, rad, rms = _fit_sphere(pts[near])
            centres[o["id"]] = c
            lines.append(f"{o['id']:>9s} {2 * rad - 2 * r0:+9.4f} {rms:8.4f}")
        spacing = ""
        for pair in sphere_pairs:
            if pair["a"] in centres and pair["b"] in centres:
                d = np.linalg.norm(centres[pair["a"]] - centres[pair["b"]])
                spacing = f"{d - pair['distance_mm']:+12.4f}"
        plate = ""
        if "plate" in objects:
            tp = objects["plate"]["params"]["top_plane"]
            n0, d0 = np.asarray(tp["normal"]), tp["d"]
            m = np.asarray(objects["plate"]["params"]["base_from_box"])
            size = np.asarray(objects["plate"]["params"]["size_mm"])
            local = (pts - m[:3, 3]) @ m[:3, :3]
            on_top = (
                (np.abs(pts @ n0 + d0) < 1.0)
                & np.all(np.abs(local[:, :2]) < size[:2] / 2 - 2.0, axis=1)
                & trusted
            )
            if np.count_nonzero(on_top) > 50:
                n, d = _fit_plane(pts[on_top])
                res = pts[on_top] @ n + d
                rms = float(np.sqrt(np.mean(res**2)))
                rng = float(res.max() - res.min())
                plate = f"{rms:10.4f} {rng:7.4f} {rng / rms:10.1f}"
        for i, line in enumerate(lines):
            lead = f"{mode:8s} {r.n_points:8d} {r.seconds:5.1f}s" if i == 0 else " " * 24
            tail = f" {spacing:>12s} {plate}" if i == 0 else ""
            print(f"{lead} {line}{tail}")
    print(
        "fits use unflagged or saturated points, away from the bar and post that touch the "
        "spheres\ntargets: spacing within 0.05 mm, diameter within 0.03 mm; "
        "plate range/RMS ~6 means noise only"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=400, help="frames for the throughput run")
    parser.add_argument("--cell", type=Path, help="a simulate_cell output folder")
    parser.add_argument(
        "--simulate", type=int, default=0, help="render a modern-cell sweep of N frames"
    )
    parser.add_argument(
        "--max-incidence",
        type=float,
        default=65.0,
        help="drop points seen or lit beyond this angle, degrees (0: keep all)",
    )
    parser.add_argument(
        "--no-laser-origin",
        action="store_true",
        help="incidence limit from the viewing angle only (the sensor drawing's laser origin unknown)",
    )
    args = parser.parse_args()
    if args.frames > 0:
        throughput(args.frames)
    cell = args.cell
    if cell is None and args.simulate:
        from scanner.virtual_cell.simulate import simulate_cell

        cell = Path(tempfile.mkdtemp(prefix="bench_scan_"))
        t0 = time.perf_counter()
        simulate_cell("modern", cell, seed=0, sweep_frames=args.simulate, sessions=("sweep",))
        print(
            f"\nsimulated {args.simulate} sweep frames in {time.perf_counter() - t0:.0f} s into {cell}"
        )
    if cell is not None:
        accuracy(cell, args.max_incidence, not args.no_laser_origin)


if __name__ == "__main__":
    main()
