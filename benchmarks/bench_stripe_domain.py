"""Stripe extraction over a randomised domain of frames: lines found, false points, accuracy (issue #16).

Each frame is drawn by :func:`scanner.virtual_cell.analytic.draw_stripe_conditions` (image
size, stripe width and amplitude from faint to saturated, background level and its slope
along the scan line, noise, slant and curvature, 8 / 16 bits, row or column scan lines) and
rendered with its exact centres. :func:`extract_stripe` runs on each in both modes, with the
default options (an uneven background taken out where the frame's own statistics call for
it) and with ``flatten_background=False`` (the extractor before that). Per condition bin:

* **found**: the share of the lines holding the stripe (its centre at least 3 px inside the
  image) where a point lies within 3 px of it;
* **false**: unflagged points (those a scan would keep) more than 3 px from the stripe, or on
  a line without it, per frame;
* **RMS**: of the unflagged points within 3 px, px (median over the bin's frames).

    python benchmarks/bench_stripe_domain.py [--frames 400] [--seed 0]
"""

from __future__ import annotations

import argparse
import itertools
from dataclasses import dataclass

import numpy as np

from scanner.stripe.extract import extract_stripe
from scanner.virtual_cell.analytic import (
    StripeConditions,
    draw_stripe_conditions,
    render_stripe_conditions,
)

#: The two extractors compared: today's default and the same without the background taken out.
VARIANTS = {"default": {}, "flatten off": {"flatten_background": False}}


@dataclass(frozen=True)
class FrameResult:
    """One frame's figures for one extractor."""

    found: float
    false: int
    rms_px: float


def judge(c: StripeConditions, image: np.ndarray, lines, pos, **options) -> FrameResult:
    """Extract ``image`` (orientation as stored) and compare with its truth."""
    p = extract_stripe(image, orientation=c.orientation, **options)
    extent = c.shape[1]
    truth = np.full(max(c.shape) + 1, np.nan)
    inside = (pos > 3) & (pos < extent - 4)
    truth[lines[inside]] = pos[inside]
    along = p.u if c.orientation == "rows" else p.v
    err = along - truth[p.line]
    near = np.isfinite(err) & (np.abs(err) < 3.0)
    clean = p.flags == 0
    # A point where the truth lies at the image's edge is neither judged right nor wrong.
    edge = np.zeros(len(p), bool)
    at_edge = lines[~inside]
    if at_edge.size:
        edge = np.isin(p.line, at_edge)
    false = int(np.count_nonzero(clean & ~near & ~edge))
    found = float(np.isin(lines[inside], p.line[near]).mean()) if inside.any() else np.nan
    good = near & clean
    rms = float(np.sqrt(np.mean(err[good] ** 2))) if good.any() else np.nan
    return FrameResult(found, false, rms)


def _bin(value: float, edges: list[float]) -> str:
    for lo, hi in itertools.pairwise(edges):
        if lo <= value < hi:
            return f"{lo:g}-{hi:g}"
    return f">= {edges[-1]:g}"


def bins(c: StripeConditions) -> dict[str, str]:
    """Each frame's conditions, binned."""
    saturated = c.amplitude + c.background + 0.5 * c.background_range > 255
    return {
        "all": "all",
        "stripe contrast / noise >= 10": "yes" if c.snr >= 10 else "no",
        "stripe contrast / noise": _bin(c.snr, [0, 10, 30, 100, 1e9]).replace("-1e+09", "+"),
        "background range along a line / stripe amplitude": _bin(
            c.background_range / c.amplitude, [0, 0.25, 0.5, 1, 2, 1e9]
        ).replace("-1e+09", "+"),
        "sigma px": _bin(c.sigma_px, [0, 1, 2, 5.01]),
        "slant px per line": _bin(abs(c.coeffs[1]), [0, 0.3, 0.6, 0.81]),
        "saturated": "yes" if saturated else "no",
        "bit depth": str(c.bit_depth),
        "scan lines": c.orientation,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rows: list[tuple[dict[str, str], dict[tuple[str, str], FrameResult]]] = []
    for i in range(args.frames):
        c = draw_stripe_conditions(np.random.default_rng([args.seed, i]))
        image, lines, pos = render_stripe_conditions(c, seed=i)
        results = {
            (mode, name): judge(c, image, lines, pos, mode=mode, **opts)
            for mode in ("fast", "precise")
            for name, opts in VARIANTS.items()
        }
        rows.append((bins(c), results))
    print(
        f"### {args.frames} randomised stripe frames, seed {args.seed}: lines found (%), "
        "false unflagged points per frame, RMS of the unflagged points (px, median over "
        "frames); each cell default / flatten off\n"
    )
    print(
        "| condition | bin | frames | "
        + " | ".join(f"{m}: found, false, RMS" for m in ("fast", "precise"))
        + " |"
    )
    print("|---|---|---:|---|---|")
    groups: dict[tuple[str, str], list[dict[tuple[str, str], FrameResult]]] = {}
    for b, results in rows:
        for cond, value in b.items():
            groups.setdefault((cond, value), []).append(results)
    order = list(rows[0][0])
    for cond in order:
        for key in sorted(k for k in groups if k[0] == cond):
            g = groups[key]
            cells = []
            for mode in ("fast", "precise"):
                parts = []
                for name in VARIANTS:
                    found = np.nanmean([r[(mode, name)].found for r in g])
                    false = np.mean([r[(mode, name)].false for r in g])
                    rms = np.nanmedian([r[(mode, name)].rms_px for r in g])
                    parts.append((found, false, rms))
                cells.append(
                    f"{100 * parts[0][0]:.1f} / {100 * parts[1][0]:.1f}, "
                    f"{parts[0][1]:.2f} / {parts[1][1]:.2f}, "
                    f"{parts[0][2]:.3f} / {parts[1][2]:.3f}"
                )
            print(f"| {cond} | {key[1]} | {len(g)} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
