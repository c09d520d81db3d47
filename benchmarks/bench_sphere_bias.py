"""Where the spheres' diameter errors come from: a diagnosis on rendered sweeps (issues #16, #19).

The modern cell's sphere_2 comes out 0.02-0.03 mm too large where sphere_1, the same sphere
on the same bar, is within 0.01 mm. This benchmark takes the sweep (seed 0, true calibration)
apart, case by case:

* ``modern``: the cell as shipped;
* ``clean``: no speckle, no robot pose error, no sensor noise (what is left is the geometry:
  the stripe's own shape on a curved surface, and which part of each sphere is seen);
* ``clean, no bar``: the same without the bar and post joining the spheres;
* ``clean, long sweep``: the same with 380 frames instead of 300 (sphere_2 lies at the
  sweep's end);
* ``randomised 0``: randomised sensor 0 as :mod:`bench_stretch_ends` draws it;
* ``clean, sigma 0.1`` and ``clean, sigma 0.4``: the clean case with the laser line half and
  twice as wide (sigma 0.2 mm): an error of the stripe's width on a curved surface grows
  with it, one of what each sphere's view leaves uncancelled does not.

Four tables per case:

1. in the image, each extracted centre's error along its scan line against the rendered
   stripe, per surface, for the points with no flag and for the saturated ones, both modes:
   the median (a bias) and the RMS (the frames extracted again with the default options and
   ``orientation="auto"``, not the scan's per-sweep ones: the same points, as the counts
   show);
2. in the cloud (true calibration, the laser origin from the truth, ``keep_flagged``), each
   sphere's least-squares diameter error (:func:`bench_laser_origin.sphere_figures`) for the
   points the default cloud holds (flags 0), for those and the saturated ones, each without and
   with the 65 deg incidence limit;
3. the default cloud's (fast mode, flags 0) radial error against each true sphere, by the
   point's elevation above the sphere's equator;
4. the same by elevation and azimuth about the vertical (:func:`view_map`, the saturated
   points included): which part of each sphere the sweep sees, and how each part errs.

    python benchmarks/bench_sphere_bias.py [--work /tmp/bench_sphere_bias]
        [--cases modern clean clean-no-bar clean-long-sweep randomised-0 clean-sigma-0.1
                 clean-sigma-0.4] [--rescan]
    python benchmarks/bench_sphere_bias.py --coverage-cache /work/unc_cache [--work ...] [--rescan]

The second form takes the second table over every randomised seed a coverage run of
``bench_uncertainty.py --randomised`` rendered (fast mode only): which points to keep, judged
over the randomised domain instead of one sensor, with one more row: each cap trimmed to the
part seen on both sides of its axis (:func:`symmetric_cap_errors`), and the third table
averaged over the seeds.

The sweeps are rendered once into ``--work`` (about 4 min each with two processes on this
machine's two cores); the clouds are kept too, so after a change to the scan pass
``--rescan``.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
from pathlib import Path

import numpy as np
from bench_laser_origin import fit_sphere, sphere_figures, sphere_points
from bench_stretch_ends import sweep_centre_errors
from scipy.spatial import cKDTree

from scanner.app import stages
from scanner.formats.clouds import cloud_arrays, read_cloud
from scanner.scanning.pipeline import ScanOptions
from scanner.stripe.profile import StripeFlag
from scanner.virtual_cell.cell import CellConfig, load_cell
from scanner.virtual_cell.random_cell import randomised_cell
from scanner.virtual_cell.truth import CellTruth, read_truth

SAT = int(StripeFlag.SATURATED)
GRAZING = int(StripeFlag.GRAZING)
INCIDENCE_DEG = 65.0


def _clean(cell: CellConfig) -> CellConfig:
    """The cell without speckle, robot pose error or sensor noise."""
    return dataclasses.replace(
        cell,
        laser=dataclasses.replace(cell.laser, speckle_contrast=0.0),
        robot=dataclasses.replace(cell.robot, repeatability_mm=0.0, repeatability_deg=0.0),
        imaging=dataclasses.replace(cell.imaging, read_noise_e=0.0, full_well_e=1e9),
    )


def cases() -> dict[str, CellConfig]:
    """The cases by name, each also the name of its folder under ``--work``."""
    modern = load_cell("modern")
    clean = _clean(modern)
    no_bar = tuple(o for o in clean.sweep.objects if o.id not in ("bar", "post"))
    return {
        "modern": modern,
        "clean": clean,
        "clean-no-bar": dataclasses.replace(
            clean, sweep=dataclasses.replace(clean.sweep, objects=no_bar)
        ),
        "clean-long-sweep": dataclasses.replace(
            clean, sweep=dataclasses.replace(clean.sweep, frames=380)
        ),
        "randomised-0": randomised_cell(modern, np.random.default_rng(10_000)),
        **{
            f"clean-sigma-{sigma:g}": dataclasses.replace(
                clean, laser=dataclasses.replace(clean.laser, sigma_mm=sigma)
            )
            for sigma in (0.1, 0.4)
        },
    }


def image_errors(sim: Path, mode: str) -> dict[tuple[str, str], np.ndarray]:
    """Along-line errors (px) of every sweep frame's centres, keyed (surface, kind)."""
    out: dict[tuple[str, str], list[np.ndarray]] = {}
    for fe in sweep_centre_errors(sim, mode=mode):
        flags = fe.profile.flags
        for kind, sel in (("no flag", flags == 0), ("saturated", flags == SAT)):
            for name in np.unique(fe.surface[fe.matched & sel]):
                pick = fe.matched & sel & (fe.surface == name)
                out.setdefault((str(name), kind), []).append(fe.error_px[pick])
    return {k: np.concatenate(v) for k, v in out.items()}


def _radial_and_elevation(
    near: np.ndarray, centre: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points ``(N, 3)`` about a true sphere: their offsets from its centre ``(N, 3)``, radial
    errors (mm) and elevations above its equator (deg), ``(N,)`` each."""
    q = near - centre
    r = np.linalg.norm(q, axis=1)
    return q, r - radius, np.degrees(np.arcsin(np.clip(q[:, 2] / r, -1.0, 1.0)))


def elevation_errors(
    points: np.ndarray, truth: CellTruth
) -> dict[str, list[tuple[str, int, float]]]:
    """Per sphere: (band, count, mean radial error mm) by elevation above its equator, of its
    points as :func:`bench_laser_origin.sphere_points` takes them; a band without points has
    a NaN mean."""
    bands = [(-91, 0), (0, 20), (20, 35), (35, 50), (50, 65), (65, 91)]
    out: dict[str, list[tuple[str, int, float]]] = {}
    for obj, near in sphere_points(points, truth):
        _, radial, elev = _radial_and_elevation(
            near,
            np.asarray(obj.params["center_mm"], dtype=np.float64),
            0.5 * float(obj.params["diameter_mm"]),
        )
        out[obj.id] = [
            (f"{a}-{b}", int(m.sum()), float(radial[m].mean()) if m.any() else np.nan)
            for a, b in bands
            for m in [(elev >= a) & (elev < b)]
        ]
    return out


def view_map(points: np.ndarray, truth: CellTruth) -> str:
    """Per sphere, a Markdown table of the mean radial error against the true sphere (mm, with
    the points' count) by elevation above its equator and azimuth about the vertical, azimuth 0
    toward the other sphere (cells with fewer than 5 points: '-'; points below the equator,
    which these sweeps barely see, are left out of the table, not of the fit); and the least-squares
    diameter's error with the fitted centre's shift. ``points`` (N, 3), base frame, mm."""
    spheres = sphere_points(points, truth)
    centres = [np.asarray(o.params["center_mm"], dtype=np.float64) for o, _ in spheres]
    azimuths = np.arange(-180, 181, 45)
    elevations = [0, 20, 35, 50, 65, 91]
    out = []
    for k, (obj, near) in enumerate(spheres):
        c0, r0 = centres[k], 0.5 * float(obj.params["diameter_mm"])
        q, radial, el = _radial_and_elevation(near, c0, r0)
        toward = centres[1 - k] - c0 if len(centres) == 2 else np.array([1.0, 0.0, 0.0])
        toward = toward[:2] / np.linalg.norm(toward[:2])
        az = np.degrees(np.arctan2(q[:, 1] * toward[0] - q[:, 0] * toward[1], q[:, :2] @ toward))
        x, _ = fit_sphere(near, np.append(c0, r0))
        out.append(
            f"\n{obj.id}: diameter error {2 * (x[3] - r0):+.4f} mm, fitted centre moved "
            f"{np.array2string(x[:3] - c0, precision=4)} mm, {len(near)} points\n"
        )
        out.append(
            "| elevation \\ azimuth, deg | "
            + " | ".join(f"{a}..{b}" for a, b in itertools.pairwise(azimuths))
            + " |"
        )
        out.append("|---|" + "---:|" * (len(azimuths) - 1))
        for lo, hi in itertools.pairwise(elevations):
            cells = []
            for a, b in itertools.pairwise(azimuths):
                m = (az >= a) & (az < b + (b == 180)) & (el >= lo) & (el < hi)
                cells.append(f"{radial[m].mean():+.3f} ({m.sum()})" if m.sum() >= 5 else "-")
            out.append(f"| {lo}-{hi} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def _cloud(
    sim: Path, truth: CellTruth, mode: str, rescan: bool, out: Path | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The sweep's cloud with every point kept and the incidence limit flagged (scanned once
    into ``out``, by default ``sim``): positions (N, 3) mm, base frame, and flags (N,)."""
    cloud = (out or sim) / f"cloud_{mode}.ply"
    cloud.parent.mkdir(parents=True, exist_ok=True)
    if rescan or not cloud.is_file():
        options = ScanOptions(
            mode=mode,
            keep_flagged=True,
            max_incidence_deg=INCIDENCE_DEG,
            laser_origin_mm=tuple(float(x) for x in truth.laser_origin_cam),
        )
        stages.scan([sim / "sweep"], sim / "calibration_true.json", cloud, options=options)
    arrays = cloud_arrays(read_cloud(cloud))
    return arrays["positions"], arrays["flags"].ravel().astype(int)


#: The points the default cloud holds: no flag but the incidence limit these clouds add.
DEFAULT = "flags 0 (the default cloud)"


def selections(flags: np.ndarray) -> dict[str, np.ndarray]:
    """The points each selection keeps, by its label, the default first: (N,) bool."""
    return {
        DEFAULT: (flags & ~GRAZING) == 0,
        "flags 0 or saturated": (flags & ~(GRAZING | SAT)) == 0,
        f"flags 0, incidence <= {INCIDENCE_DEG:g} deg": flags == 0,
        f"flags 0 or saturated, incidence <= {INCIDENCE_DEG:g} deg": (flags & ~SAT) == 0,
    }


SYMMETRIC_CAP = "flags 0, each cap trimmed to its part symmetric about the cap's axis"


def symmetric_cap_errors(
    points: np.ndarray, truth: CellTruth, within_deg: float = 3.0
) -> list[float]:
    """Each true sphere's diameter error (mm) from its cap trimmed to be seen on both sides.

    The points as :func:`bench_laser_origin.sphere_points` takes them are fitted (least
    squares); a point stays if its direction from the fitted centre, turned half a turn about
    the cap's axis (the points' mean direction), lies within ``within_deg`` of another point's
    direction; the kept points are fitted again. A lopsided cap (one side hidden by the bar)
    becomes a symmetric one: does that remove sphere_2's size error?
    """
    out = []
    for obj, near in sphere_points(points, truth):
        r0 = 0.5 * float(obj.params["diameter_mm"])
        x, _ = fit_sphere(near, np.append(np.asarray(obj.params["center_mm"], float), r0))
        u = near - x[:3]
        u /= np.linalg.norm(u, axis=1)[:, None]
        axis = u.mean(axis=0) / np.linalg.norm(u.mean(axis=0))
        turned = 2.0 * (u @ axis)[:, None] * axis - u
        seen, _ = cKDTree(u).query(turned)
        x, _ = fit_sphere(near[seen < np.radians(within_deg)], x)
        out.append(2.0 * (x[3] - r0))
    return out


def run_coverage_seeds(cache: Path, work: Path, rescan: bool) -> None:
    """The cloud table (fast mode) over every randomised seed of a coverage cache
    (``bench_uncertainty.py --randomised --work CACHE``): each seed's rendered sweep scanned
    with its true calibration into ``work``, and per selection the mean, RMS and largest
    absolute diameter error of each sphere over the seeds."""
    sims = sorted(d / "sim" for d in cache.glob("randomised-*") if (d / "result.json").is_file())
    if not sims:
        raise SystemExit(f"{cache}: no randomised-*/result.json (not a coverage cache)")
    errors: dict[str, list[list[float]]] = {}
    bands: dict[tuple[str, str], list[tuple[int, float]]] = {}
    for sim in sims:
        truth = read_truth(sim / "truth.json")
        points, flags = _cloud(sim, truth, "fast", rescan, out=work / sim.parent.name)
        kept = selections(flags)
        default = points[kept[DEFAULT]]
        for sphere, rows in elevation_errors(default, truth).items():
            for band, count, mean in rows:
                bands.setdefault((sphere, band), []).append((count, mean))
        for label, keep in kept.items():
            f = sphere_figures(points[keep], truth)
            row = [f["sphere_1 diameter error"], f["sphere_2 diameter error"]]
            errors.setdefault(label, []).append(row)
            print(f"{sim.parent.name} | {label} | {row[0]:+.4f} | {row[1]:+.4f}", flush=True)
        row = symmetric_cap_errors(default, truth)
        errors.setdefault(SYMMETRIC_CAP, []).append(row)
        print(f"{sim.parent.name} | {SYMMETRIC_CAP} | {row[0]:+.4f} | {row[1]:+.4f}", flush=True)
    print(f"\n### Randomised seeds of {cache} ({len(sims)}), fast mode, true calibration\n")
    print(
        "Sphere diameter error over the seeds (mm): mean / RMS / largest absolute; in how many "
        "seeds the error is smaller than the default cloud's; the mean paired change of the "
        "squared error against the default, with its standard error (um²)\n"
    )
    print(
        "| points kept | sphere_1 | sphere_2 | smaller than default | change of error² |\n"
        "|---|---:|---:|---:|---:|"
    )
    base = np.abs(np.asarray(errors[DEFAULT]))
    for label, rows in errors.items():
        e = np.asarray(rows)
        cells = [
            f"{e[:, j].mean():+.4f} / {np.sqrt(np.mean(e[:, j] ** 2)):.4f} / "
            f"{np.abs(e[:, j]).max():.4f}"
            for j in range(2)
        ]
        closer = " / ".join(f"{int(np.sum(np.abs(e[:, j]) < base[:, j]))}" for j in range(2))
        change = (e**2 - base**2) * 1e6
        se = change.std(axis=0, ddof=1) / np.sqrt(len(change)) if len(change) > 1 else [np.nan] * 2
        paired = " / ".join(f"{change[:, j].mean():+.0f} +- {se[j]:.0f}" for j in range(2))
        print(f"| {label} | {cells[0]} | {cells[1]} | {closer} | {paired} |")
    print(
        "\nThe default cloud (flags 0): radial error against the true sphere (mm) by elevation "
        "above its equator, over the seeds (mean weighted by points; points per seed; '-' where "
        "a band has less than one point per seed)\n"
    )
    names = list(dict.fromkeys(b for _, b in bands))
    print("| sphere | " + " | ".join(f"{b} deg" for b in names) + " |")
    print("|---|" + "---:|" * len(names))
    for sphere in dict.fromkeys(sp for sp, _ in bands):
        cells = []
        for b in names:
            v = np.asarray(bands[(sphere, b)], dtype=np.float64)
            if v[:, 0].mean() < 1.0:
                cells.append("-")
                continue
            seen = v[:, 0] > 0
            mean = np.average(v[seen, 1], weights=v[seen, 0])
            cells.append(f"{mean:+.4f} ({v[:, 0].mean():.0f})")
        print(f"| {sphere} | " + " | ".join(cells) + " |")


def run_case(name: str, cell: CellConfig, work: Path, rescan: bool) -> None:
    """Render the case's sweep (once), scan it in both modes (once, or again with ``rescan``)
    and print its three tables."""
    sim = work / name
    if not (sim / "truth.json").is_file():
        stages.simulate(cell, sim, seed=0, sessions=("sweep",), workers=2)
    truth = read_truth(sim / "truth.json")
    print(f"\n### {name}\n")
    print("In the image: error along the scan line against the rendered stripe (px)\n")
    print("| mode | surface | points | count | median | RMS |\n|---|---|---|---:|---:|---:|")
    for mode in ("fast", "precise"):
        for (surface, kind), e in sorted(image_errors(sim, mode).items()):
            if surface == "table" or e.size < 50:
                continue
            rms = float(np.sqrt(np.mean(e**2)))
            print(f"| {mode} | {surface} | {kind} | {e.size} | {np.median(e):+.3f} | {rms:.3f} |")
    print("\nIn the cloud: sphere diameter error (mm) and points, per selection\n")
    print("| mode | points kept | sphere_1 | sphere_2 | spacing |\n|---|---|---:|---:|---:|")
    for mode in ("fast", "precise"):
        points, flags = _cloud(sim, truth, mode, rescan)
        for label, keep in selections(flags).items():
            f = sphere_figures(points[keep], truth)
            print(
                f"| {mode} | {label} | {f['sphere_1 diameter error']:+.4f} "
                f"({f['sphere_1 points']:.0f}) | {f['sphere_2 diameter error']:+.4f} "
                f"({f['sphere_2 points']:.0f}) | {f['spacing error']:+.4f} |"
            )
    points, flags = _cloud(sim, truth, "fast", rescan=False)
    by_band = elevation_errors(points[selections(flags)[DEFAULT]], truth)
    print("\nThe default cloud (fast, flags 0): mean radial error (mm) by elevation, points\n")
    bands = [b for b, _, _ in next(iter(by_band.values()))]
    print("| sphere | " + " | ".join(f"{b} deg" for b in bands) + " |")
    print("|---|" + "---:|" * len(bands))
    for sphere, rows in by_band.items():
        cells = [f"{m:+.4f} ({n})" if n else "-" for _, n, m in rows]
        print(f"| {sphere} | " + " | ".join(cells) + " |")
    keep = selections(flags)["flags 0 or saturated"]
    print("\nThe same by elevation and azimuth (fast, flags 0 or saturated), mm (points)")
    print(view_map(points[keep], truth))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_sphere_bias"))
    ap.add_argument("--cases", nargs="*", help="case names (default all)")
    ap.add_argument("--rescan", action="store_true", help="scan again (clouds are cached)")
    ap.add_argument(
        "--coverage-cache",
        type=Path,
        help="instead of the cases: the cloud table over the randomised seeds of this "
        "bench_uncertainty cache",
    )
    args = ap.parse_args()
    if args.coverage_cache is not None:
        run_coverage_seeds(args.coverage_cache, args.work / "coverage", args.rescan)
        return
    for name, cell in cases().items():
        if not args.cases or name in args.cases:
            run_case(name, cell, args.work, args.rescan)


if __name__ == "__main__":
    main()
