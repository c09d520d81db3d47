"""``scanner scan`` on PNG frames against the time it takes just to decode them (issue #16).

    python benchmarks/bench_scan_decode.py --session SWEEP --calibration CAL.json [--repeat 3]
        [--mode fast|precise]

``SWEEP`` is a sweep session of PNG frames (for example ``sim/sweep`` of a seed cached by
``benchmarks/bench_uncertainty.py``, or ``scanner simulate``'s output) and ``CAL.json`` its
calibration. Three wall times, best of ``--repeat``:

- the decode floor on one thread: ``cv2.imread`` of every laser image;
- the decode floor on the scan's workers: the same images split into the scan's chunks and
  decoded by as many threads as the scan uses (its extraction runs on threads:
  :func:`scanner.core.parallel.thread_pool`);
- the scan: :func:`scanner.app.stages.scan` into a temporary folder (no resumed chunks),
  session and calibration read, stripes extracted, points triangulated and the cloud written.

Target: the scan within 1.5x the decode floor (both floors are printed; the one thread's is
the stricter test of the scan's overlap of decoding and extraction).
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import cv2

from scanner.app import stages
from scanner.core.parallel import thread_pool
from scanner.formats.session import read_session
from scanner.scanning.pipeline import ScanOptions


def _decode(paths: list[str]) -> int:
    """Worker: decode the images; returns how many."""
    for p in paths:
        if cv2.imread(p, cv2.IMREAD_UNCHANGED) is None:
            raise OSError(f"{p}: not decodable")
    return len(paths)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--session", type=Path, required=True)
    parser.add_argument("--calibration", type=Path, required=True)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--mode", choices=("fast", "precise"), default="fast")
    args = parser.parse_args(argv)
    options = ScanOptions(mode=args.mode)
    session = read_session(args.session)
    paths = [str(f.laser_image) for f in session.frames if f.laser_image is not None]
    size = options.chunk_frames
    chunks = [paths[i : i + size] for i in range(0, len(paths), size)]

    def best(run) -> float:
        times = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            run()
            times.append(time.perf_counter() - t0)
        return min(times)

    one = best(lambda: _decode(paths))

    def pooled() -> None:
        with thread_pool(options.workers) as pool:
            if sum(pool.map(_decode, chunks)) != len(paths):
                raise RuntimeError("the workers decoded fewer images than given")

    pooled_s = best(pooled)
    with tempfile.TemporaryDirectory() as tmp:
        counter = iter(range(10**6))
        scan_s = best(
            lambda: stages.scan(
                [args.session],
                args.calibration,
                Path(tmp) / f"cloud{next(counter)}.ply",
                options=options,
                work_dir=Path(tmp) / f"work{next(counter)}",
            )
        )
    n = len(paths)
    print(f"{n} PNG frames, {options.workers} workers, chunks of {size}, best of {args.repeat}")
    print("| run | wall s | ms per frame | against decoding on one thread | on the workers |")
    print("|---|---:|---:|---:|---:|")
    for name, s in (
        ("decode, one thread", one),
        (f"decode, {options.workers} threads", pooled_s),
        (f"`scanner scan` ({options.mode} mode)", scan_s),
    ):
        print(f"| {name} | {s:.2f} | {1000 * s / n:.1f} | {s / one:.2f}x | {s / pooled_s:.2f}x |")
    print(f"{platform.node()} ({platform.machine()})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
