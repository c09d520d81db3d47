"""Speed and accuracy of the feature fits on synthetic clouds; prints a table.

    python benchmarks/bench_fit.py                 # 10k, 100k and 1M points
    python benchmarks/bench_fit.py --sizes 1000000 --repeat 5 --threads 2

Each primitive is sampled with Gaussian noise (``--noise-mm``), fitted by plain least squares
and after RANSAC with 20 % clutter added; the table gives the best wall time of ``--repeat``
runs and the errors against the truth. "wall s" is elapsed time, "cpu s" the process's CPU time (the
same on an idle machine; the honest figure when other jobs share the cores). The target: a plane, sphere or cylinder on 1 million
points in under 1 s. BLAS threads default to 1 (``--threads``): on a shared machine a
multi-threaded BLAS spends more time waiting than computing on these thin matrices.
"""

from __future__ import annotations

import argparse
import os
import sys


def _parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    p.add_argument("--repeat", type=int, default=3, help="runs per case; the best time is kept")
    p.add_argument("--noise-mm", type=float, default=0.01)
    p.add_argument("--threads", type=int, default=1, help="BLAS threads (set before numpy loads)")
    p.add_argument("--kinds", nargs="+", default=["plane", "sphere", "cylinder", "circle", "line"])
    return p.parse_args()


ARGS = _parse() if __name__ == "__main__" else None
if ARGS is not None:
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(ARGS.threads)

import time  # noqa: E402

import numpy as np  # noqa: E402

from metrology.fits import fit_circle, fit_cylinder, fit_line, fit_plane, fit_sphere  # noqa: E402

AXIS = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])
CENTER = np.array([620.0, -35.0, 48.0])


def _basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    u = np.cross(n, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def sample(kind: str, n: int, noise: float, rng: np.random.Generator) -> np.ndarray:
    u, v = _basis(AXIS)
    if kind == "plane":
        st = rng.uniform(-60, 60, (n, 2))
        p = CENTER + st[:, :1] * u + st[:, 1:] * v
    elif kind == "sphere":
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1)[:, None]
        d[:, 2] = np.abs(d[:, 2])
        p = CENTER + 12.7 * d
    elif kind == "cylinder":
        th = rng.uniform(0, np.pi, n)
        t = rng.uniform(-40, 40, n)
        p = CENTER + t[:, None] * AXIS + 20 * (np.cos(th)[:, None] * u + np.sin(th)[:, None] * v)
    elif kind == "circle":
        th = rng.uniform(0, 2 * np.pi, n)
        p = CENTER + 15 * (np.cos(th)[:, None] * u + np.sin(th)[:, None] * v)
    else:
        p = CENTER + rng.uniform(-80, 80, (n, 1)) * AXIS
    return p + rng.normal(0.0, noise, p.shape)


def errors(kind: str, fit) -> tuple[float, float]:
    """(position or size error in µm, angle error in degrees) against the truth."""
    if not fit:
        return float("nan"), float("nan")

    def ang(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.degrees(np.arccos(min(1.0, abs(float(a @ b))))))

    if kind == "plane":
        return abs(float(fit.signed_distance(CENTER[None])[0])) * 1e3, ang(fit.normal, AXIS)
    if kind == "sphere":
        return max(np.linalg.norm(fit.center_mm - CENTER), abs(fit.radius_mm - 12.7)) * 1e3, 0.0
    if kind == "cylinder":
        q = fit.point_mm - CENTER
        off = np.linalg.norm(q - (q @ AXIS) * AXIS)
        return max(off, abs(fit.radius_mm - 20)) * 1e3, ang(fit.axis, AXIS)
    if kind == "circle":
        err = max(np.linalg.norm(fit.center_mm - CENTER), abs(fit.radius_mm - 15))
        return err * 1e3, ang(fit.normal, AXIS)
    q = fit.point_mm - CENTER
    return float(np.linalg.norm(q - (q @ AXIS) * AXIS)) * 1e3, ang(fit.direction, AXIS)


FITTERS = {
    "plane": fit_plane,
    "sphere": fit_sphere,
    "cylinder": fit_cylinder,
    "circle": fit_circle,
    "line": fit_line,
}


def run(args: argparse.Namespace) -> None:
    rng = np.random.default_rng(0)
    print(
        f"# feature fits: best of {args.repeat} runs, noise {args.noise_mm * 1e3:.0f} µm, "
        f"BLAS threads {args.threads}"
    )
    print(
        f"| {'kind':8} | {'points':>9} | {'mode':7} | {'wall s':>7} | {'cpu s':>7} | {'rms µm':>7} | "
        f"{'err µm':>7} | {'err deg':>8} | {'inliers':>9} |"
    )
    print(
        f"|{'-' * 10}|{'-' * 11}|{'-' * 9}|{'-' * 9}|{'-' * 9}|{'-' * 9}|{'-' * 9}|{'-' * 10}|"
        f"{'-' * 11}|"
    )
    for kind in args.kinds:
        for n in args.sizes:
            pts = sample(kind, n, args.noise_mm, rng)
            lo, hi = pts.min(axis=0), pts.max(axis=0)
            clutter = rng.uniform(lo - 5, hi + 5, (n // 5, 3))
            cases = [("lsq", pts, None), ("ransac", np.vstack([pts, clutter]), 0.05)]
            for mode, cloud, thr in cases:
                best, best_cpu, fit = float("inf"), float("inf"), None
                for _ in range(args.repeat):
                    t0, c0 = time.perf_counter(), time.process_time()
                    fit = FITTERS[kind](cloud, thr)
                    best = min(best, time.perf_counter() - t0)
                    best_cpu = min(best_cpu, time.process_time() - c0)
                e_mm, e_deg = errors(kind, fit)
                rms = fit.rms_mm * 1e3 if fit else float("nan")
                print(
                    f"| {kind:8} | {n:9d} | {mode:7} | {best:7.3f} | {best_cpu:7.3f} | {rms:7.2f} | "
                    f"{e_mm:7.3f} | "
                    f"{e_deg:8.5f} | {fit.n_inliers if fit else 0:9d} |",
                    flush=True,
                )


if __name__ == "__main__":
    assert ARGS is not None
    run(ARGS)
    sys.exit(0)
