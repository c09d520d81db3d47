"""Stretch ends (StripeFlag.STRETCH_END): how far off they are, and what leaving them out does.

Two tables, on the sweep (seed 0) of the modern cell and of randomised sensor 0
(:func:`scanner.virtual_cell.random_cell.randomised_cell`):

* in the image: each extracted point's error along its scan line against the rendered truth,
  for the points the flag marks and for the clean ones (no flag at all), every 4th frame;
* in the cloud as ``scanner scan`` writes it (true calibration) with ``end_lines`` 0 (no flag)
  and the given values: the spheres' figures as :func:`bench_laser_origin.cloud_sphere_figures`
  gives them, and the plate top's tilt and noise (points within 0.5 mm of its true plane).

    python benchmarks/bench_stretch_ends.py [--work /tmp/bench_stretch_ends] [--end-lines 3 6]
        [--rescan]

The sweeps are rendered once into ``--work``; the clouds are kept too, so after a change to
the extractor or the scan pass ``--rescan``.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from bench_laser_origin import cloud_sphere_figures

from scanner.app import stages
from scanner.formats.clouds import cloud_arrays, read_cloud
from scanner.formats.session import read_session
from scanner.scanning.pipeline import ScanOptions
from scanner.stripe.extract import extract_stripe
from scanner.stripe.profile import StripeFlag, StripeOptions, StripeProfile
from scanner.virtual_cell.cell import load_cell
from scanner.virtual_cell.random_cell import randomised_cell
from scanner.virtual_cell.truth import CellTruth, StripeTable, along_line_errors, read_truth


@dataclass(frozen=True)
class FrameErrors:
    """One sweep frame's extracted centres against the rendered stripe.

    Attributes
    ----------
    profile : StripeProfile
        The frame's N extracted centres.
    error_px : ndarray, shape (N,)
        Each centre's error along its scan line.
    surface : ndarray, shape (N,)
        The surface of the rendered sample nearest each centre.
    matched : ndarray, shape (N,), bool
        The centre lies within 2 px of its nearest rendered sample and the rendered stripe
        crosses its scan line there (``along_line_errors``' ``ok``).
    """

    profile: StripeProfile
    error_px: np.ndarray
    surface: np.ndarray
    matched: np.ndarray


def sweep_centre_errors(sim: Path, every: int = 1, **extract: Any) -> Iterator[FrameErrors]:
    """Every ``every``-th frame of ``sim``'s sweep extracted (``extract_stripe`` with
    ``orientation="auto"`` and ``extract``) and matched to the rendered stripe; frames with
    fewer than two centres or two rendered samples are skipped."""
    session = read_session(sim / "sweep")
    table = StripeTable.load(sim / "sweep_stripes.npz")
    for f in session.frames[::every]:
        p = extract_stripe(session.load_laser_image(f), orientation="auto", **extract)
        uv_true, surface = table.of_frame(f.id)
        if len(p) < 2 or len(uv_true) < 2:
            continue
        e, dist, nearest, ok = along_line_errors(p.uv, p.orientation, uv_true)
        yield FrameErrors(p, e, np.asarray(surface)[nearest], ok & (dist < 2.0))


def image_errors(sim: Path, end_lines: int, every: int = 4) -> dict[str, tuple[int, float]]:
    """Points and RMS error (px) along the scan line: flagged STRETCH_END only (``end_lines``
    lines, the flag being off by default), and clean."""
    errs: dict[str, list[np.ndarray]] = {"stretch end": [], "clean": []}
    for fe in sweep_centre_errors(sim, every, mode="precise", end_lines=end_lines):
        flags = fe.profile.flags
        errs["stretch end"].append(fe.error_px[fe.matched & (flags == StripeFlag.STRETCH_END)])
        errs["clean"].append(fe.error_px[fe.matched & (flags == 0)])
    out = {}
    for name, parts in errs.items():
        e = np.concatenate(parts)
        out[name] = (e.size, float(np.sqrt(np.mean(e**2))) if e.size else float("nan"))
    return out


def plate_figures(cloud_path: Path, truth: CellTruth) -> tuple[float, float]:
    """The plate top's fitted tilt against the truth (deg) and its points' noise (mm)."""
    points = cloud_arrays(read_cloud(cloud_path))["positions"]
    plate = next(o for o in truth.objects if o.type == "box")
    n = np.asarray(plate.params["top_plane"]["normal"], dtype=np.float64)
    d = float(plate.params["top_plane"]["d"])
    q = points[np.abs(points @ n + d) < 0.5]
    c = q.mean(axis=0)
    normal = np.linalg.svd(q - c, full_matrices=False)[2][2]
    res = (q - c) @ normal
    sigma = 1.4826 * float(np.median(np.abs(res - np.median(res))))
    return float(np.degrees(np.arccos(min(1.0, abs(normal @ n))))), sigma


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_stretch_ends"))
    ap.add_argument("--end-lines", type=int, nargs="*", default=[3, 6])
    ap.add_argument("--rescan", action="store_true", help="scan again (clouds are cached)")
    args = ap.parse_args()
    cells = {
        "modern": load_cell("modern"),
        "randomised 0": randomised_cell(load_cell("modern"), np.random.default_rng(10_000)),
    }
    for name, cell in cells.items():
        folder = args.work / name.replace(" ", "-")
        sim = folder / "sim"
        if not (sim / "truth.json").is_file():
            stages.simulate(cell, sim, seed=0, sessions=("sweep",), workers=2)
        truth = read_truth(sim / "truth.json")
        lines = args.end_lines[0] if args.end_lines else 3
        print(
            f"\n{name}: precise mode, every 4th sweep frame, {lines} end lines flagged, "
            "error along the scan line"
        )
        print("| points | count | RMS px |\n|---|---:|---:|")
        for kind, (count, rms) in image_errors(sim, lines).items():
            print(f"| {kind} | {count} | {rms:.3f} |")
        figures = {}
        for k in [0, *args.end_lines]:
            cloud = folder / f"cloud_end{k}.ply"
            if args.rescan or not cloud.is_file():
                options = ScanOptions(stripe=StripeOptions(end_lines=k))
                stages.scan([sim / "sweep"], sim / "calibration_true.json", cloud, options=options)
            f = cloud_sphere_figures(cloud, truth)
            f["plate tilt deg"], f["plate noise sigma"] = plate_figures(cloud, truth)
            figures[f"end_lines {k}"] = f
        runs = list(figures)
        print(f"\n{name}: the cloud as written (default scan, true calibration)")
        print("| figure | " + " | ".join(runs) + " |\n|---|" + "---:|" * len(runs))
        for key in figures[runs[0]]:
            if "noise alone" in key:
                continue
            fmt = "{:.0f}" if key.endswith("points") else "{:+.4f}"
            print(f"| {key} | " + " | ".join(fmt.format(figures[r][key]) for r in runs) + " |")


if __name__ == "__main__":
    main()
