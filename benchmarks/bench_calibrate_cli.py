"""`scanner calibrate` end to end on a 20-frame 1280x1024 session (issue #4: under 20 s).

The modern virtual cell's calibration session is cut down to its first N/2 hand-held views
(target moved by hand, no pose) and N/2 posed views (target fixed, robot moving), each with
its target and laser image, then ``scanner calibrate`` runs on it as a user would (a fresh
process, the HTML report included). Prints the wall time and the time of every stage.

    python benchmarks/bench_calibrate_cli.py [--frames 20] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from scanner.formats.session import Frame, read_session, write_session


def cut_session(source: Path, out: Path, n_frames: int) -> Path:
    """Copy the first ``n_frames // 2`` unposed and the rest posed frames of ``source``."""
    session = read_session(source)
    unposed = [f for f in session.frames if not f.has_pose][: n_frames // 2]
    posed = [f for f in session.frames if f.has_pose][: n_frames - len(unposed)]
    if out.exists():
        shutil.rmtree(out)
    (out / "images").mkdir(parents=True)
    frames = []
    for f in unposed + posed:
        copied = []
        for image in (f.target_image, f.laser_image):
            if image is None:
                copied.append(None)
                continue
            shutil.copy2(image, out / "images" / image.name)
            copied.append(out / "images" / image.name)
        frames.append(Frame(f.id, copied[0], copied[1], f.base_from_flange))
    return write_session(
        out,
        session.kind,
        session.width,
        session.height,
        frames,
        rotation=session.rotation,
        target=session.target,
        extra=session.extra,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_calibrate_cli"))
    args = parser.parse_args()
    cell = args.work / "modern"
    if not (cell / "calibration" / "session.json").is_file():
        from scanner.virtual_cell.simulate import simulate_cell

        t0 = time.perf_counter()
        simulate_cell("modern", cell, seed=0, sessions=("calibration",), workers=2)
        print(
            f"simulated the modern cell's calibration session in {time.perf_counter() - t0:.0f} s"
        )
    sub = cut_session(cell / "calibration", args.work / f"calibration_{args.frames}", args.frames)
    calib = args.work / "calib.json"
    command = [
        sys.executable, "-m", "scanner.app.cli", "calibrate", str(sub), "--out", str(calib),
        "--report-dir", str(args.work / "reports"), "--quiet",
    ]  # fmt: skip
    t0 = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        sys.exit(f"scanner calibrate failed: {done.stderr.strip().splitlines()[-1]}")
    timings = json.loads(calib.read_text())["quality"]["timings"]
    size = read_session(sub)
    print(
        f"scanner calibrate, {args.frames} frames {size.width}x{size.height}: {wall:.1f} s wall "
        "(target 20 s), process start and report included"
    )
    for stage, seconds in timings.items():
        print(f"  {stage:16s} {seconds:6.2f} s")


if __name__ == "__main__":
    main()
