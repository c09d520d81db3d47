"""Calibration accuracy: the default method against OpenCV's baselines and the paper's method.

Prints tables (Markdown) for:

* the virtual cells (``modern``, ``paper``): light-plane normal and d, hand-eye rotation and
  translation errors against the simulator's truth, for the default, the paper's method and
  the anchor (OpenCV chessboard calibration at the same poses, its five AX=XB solvers and a
  Horus-style plane fit);
* ``kuka_1`` (real, chessboard): whole-chain reprojection RMS and the scatter of the board's
  origin in the base frame, default against OpenCV's solvers with the same intrinsics;
* ``zhaocongyang_linelight`` (real, circle grid): light-plane normal against the authors' and
  the distance of their point cloud to our plane.

Usage::

    python benchmarks/bench_calibration.py [--cells modern paper] [--work /tmp/bench_calib]
        [--skip-real] [--skip-cells] [--robot-draws 50] [--seed 0] [--seeds 1]
        [--randomised]

``--randomised``: each cell's sensor drawn anew per seed (camera, lens, laser geometry, robot
repeatability, noise: :func:`scanner.virtual_cell.random_cell.randomised_cell`), the scene
and poses kept. ``--seeds N``: seeds ``seed .. seed + N - 1``, then a summary per cell and
method over them (mean, and the smallest and largest value). The intrinsics columns compare
each method's camera with the truth: fx relative error, cx and cy errors.

``--robot-draws``: the hand-eye solvers over fresh draws of the robot's repeatability error
(see :func:`robot_draw_study`); one session is one draw, too few to rank solvers that are
within the robot's noise of each other.
"""

from __future__ import annotations

import argparse
import logging
import os
import pickle
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calibration.detection.detect import detect_target
from calibration.extrinsics import estimate_pose
from calibration.hand_eye import PosedView, calibrate_hand_eye, fix_label_flips
from calibration.intrinsics import calibrate_intrinsics
from calibration.light_plane import (
    LaserView,
    calibrate_light_plane,
    fit_plane,
    stripe_points_on_target,
)
from calibration.opencv_adapter import AX_XB_METHODS
from calibration.pipeline import calibrate_session, target_extent_mm
from scanner.core.camera import CameraModel
from scanner.core.conventions import angle_between_rotations_deg
from scanner.core.images import load_gray_image, load_laser_images
from scanner.core.planes import plane_errors
from scanner.core.targets import ChessboardTarget, CircleGridTarget
from scanner.formats.calibration_file import LightPlane
from scanner.formats.session import read_session
from scanner.stripe.extract import extract_stripe
from scanner.virtual_cell.cell import load_cell
from scanner.virtual_cell.poses import perturb_pose
from scanner.virtual_cell.random_cell import randomised_cell
from scanner.virtual_cell.simulate import simulate_cell
from scanner.virtual_cell.truth import read_truth

REPO = Path(__file__).resolve().parents[1]


def real_data_root() -> Path:
    return Path(os.environ.get("SCANNER_REAL_DATA", REPO.parent / "shared" / "data" / "real"))


def flange_plane_errors(
    plane: LightPlane, flange_from_cam: np.ndarray, truth_plane: LightPlane, truth_x: np.ndarray
) -> tuple[float, float]:
    """The light plane carried into the flange frame, against the truth carried the same way.

    Free of the camera frame's gauge: a camera frame turned slightly (e.g. by a principal point
    error) turns the plane and the hand-eye together, and the scanner's points stay right.
    """

    def to_flange(pl: LightPlane, x: np.ndarray) -> LightPlane:
        n = x[:3, :3] @ pl.normal
        return LightPlane(n, pl.d - float(n @ x[:3, 3]))

    return plane_errors(to_flange(plane, flange_from_cam), to_flange(truth_plane, truth_x))


def hand_eye_errors(x: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return angle_between_rotations_deg(x, truth), float(np.linalg.norm(x[:3, 3] - truth[:3, 3]))


# ------------------------------------------------------------------------------- virtual cells


def _cell_config(cell: str, seed: int, randomised: bool) -> Any:
    """The cell ``cell`` (a configs/cells name), its sensor drawn for ``seed`` if randomised."""
    config = load_cell(cell)
    return randomised_cell(config, np.random.default_rng(10_000 + seed)) if randomised else config


def _simulate(cell: Any, out: Path, target: str | None, seed: int) -> Any:
    if not (out / "truth.json").is_file():
        simulate_cell(cell, out, seed=seed, target=target, sessions=("calibration",), workers=2)
    truth = read_truth(out / "truth.json")
    if truth.seed != seed or truth.cell != cell.name:
        raise SystemExit(
            f"{out}: simulated for {truth.cell} seed {truth.seed}, not {cell.name} seed {seed}: "
            "use another --work"
        )
    return truth


@dataclass
class Anchor:
    """The OpenCV anchor's answers, and the posed views its hand-eye solvers saw."""

    plane: LightPlane
    hand_eye: dict[str, np.ndarray]
    rms: float
    views: list[PosedView]
    camera: CameraModel


def opencv_anchor(session_dir: Path) -> Anchor:
    """OpenCV chessboard calibration at the same poses, five AX=XB solvers, Horus plane fit."""
    session = read_session(session_dir)
    target = session.target
    obj = target.object_points().astype(np.float32)  # type: ignore[union-attr]
    pattern = tuple(target.inner_corners)  # type: ignore[union-attr]
    corners: dict[int, np.ndarray] = {}
    for f in session.frames:
        if f.target_image is None:
            continue
        img = load_gray_image(f.target_image)
        if img.dtype != np.uint8:
            img = (img / 257).astype(np.uint8)
        ok, c = cv2.findChessboardCornersSB(img, pattern, flags=cv2.CALIB_CB_ACCURACY)
        if ok:
            corners[f.id] = c.reshape(-1, 2)
    ids = list(corners)
    rms, K, dist, _, _ = cv2.calibrateCamera(
        [obj] * len(ids),
        [corners[i].astype(np.float32) for i in ids],
        (session.width, session.height),
        None,
        None,
    )
    cam = CameraModel(session.width, session.height, K, dist.ravel())
    poses = {}
    for i in ids:
        p = estimate_pose(corners[i], obj.astype(np.float64), cam, refine=False)
        if p:
            poses[i] = p.cam_from_target
    # Horus-style light plane: stripe (row-wise peak) on the board plane, one SVD plane fit.
    pts = []
    for f in session.frames:
        if f.laser_image is None or f.id not in poses:
            continue
        prof = extract_stripe(session.load_laser_image(f), mode="fast")
        ct = poses[f.id]
        p = stripe_points_on_target(np.column_stack([prof.u, prof.v]), cam, ct)
        p = p[np.all(np.isfinite(p), axis=1)]
        pt = (p - ct[:3, 3]) @ ct[:3, :3]
        x0, x1, y0, y1 = target_extent_mm(target)  # type: ignore[arg-type]
        keep = (pt[:, 0] > x0) & (pt[:, 0] < x1) & (pt[:, 1] > y0) & (pt[:, 1] < y1)
        pts.append(p[keep])
    fit = fit_plane(np.vstack(pts))
    plane = LightPlane(fit.normal, fit.d)
    posed = [f for f in session.frames if f.has_pose and f.id in corners]
    views = [
        PosedView(
            f.id, f.base_from_flange, corners[f.id].astype(float), obj.astype(float), poses[f.id]
        )  # type: ignore[arg-type]
        for f in posed
    ]
    views, _ = fix_label_flips(views, cam)
    hand_eye = {}
    for m in AX_XB_METHODS:
        r = calibrate_hand_eye(views, cam, m)
        if r:
            hand_eye[m] = r.flange_from_cam
    return Anchor(plane, hand_eye, float(rms), views, cam)


Row = tuple[str, str, float, float, float, float, float, float, float, float, float, float]


def intrinsics_errors(K: np.ndarray, truth: Any) -> tuple[float, float, float]:
    """fx relative error (%), cx and cy errors (px) of ``K`` against the true camera."""
    Kt = truth.camera.K
    return (
        100.0 * (K[0, 0] / Kt[0, 0] - 1.0),
        float(K[0, 2] - Kt[0, 2]),
        float(K[1, 2] - Kt[1, 2]),
    )


def bench_cell(
    cell: str, work: Path, seed: int = 0, robot_draws: int = 0, randomised: bool = False
) -> tuple[list[Row], list[str]]:
    """Rows (cell, method, normal deg, d mm, he rot deg, he trans mm, plane in flange deg and
    mm, seconds, fx %, cx px, cy px), and the robot-draw study's table lines (none when
    ``robot_draws`` is 0)."""
    rows: list[Row] = []
    own_views: list[PosedView] = []
    own_camera = None
    config = _cell_config(cell, seed, randomised)
    label = f"{cell}-randomised" if randomised else cell
    truth = _simulate(config, work / f"{label}_own", None, seed)
    session = read_session(work / f"{label}_own" / "calibration")
    cache = work / f"{label}_own" / "observations.pkl"
    obs = pickle.loads(cache.read_bytes()) if cache.is_file() else None
    for method in ("default", "paper"):
        t0 = time.perf_counter()
        try:
            res = calibrate_session(session, method=method, progress=False, observations=obs)  # type: ignore[arg-type]
        except ValueError as exc:
            logging.warning("%s %s: %s", cell, method, exc)
            continue
        dt = time.perf_counter() - t0
        if obs is None:
            obs = res.observations
            cache.write_bytes(pickle.dumps(obs))
        na, dd = plane_errors(res.calibration.light_plane, truth.light_plane)
        hr, ht = hand_eye_errors(res.calibration.flange_from_cam, truth.flange_from_cam)
        fa, fd = flange_plane_errors(
            res.calibration.light_plane,
            res.calibration.flange_from_cam,
            truth.light_plane,
            truth.flange_from_cam,
        )
        fx, cx, cy = intrinsics_errors(res.calibration.K, truth)
        rows.append((label, method, na, dd, hr, ht, fa, fd, dt, fx, cx, cy))
        if method == "default":
            c = res.calibration
            own_views, own_camera = res.hand_eye_views, CameraModel(c.width, c.height, c.K, c.dist)
    _simulate(config, work / f"{label}_chess", "chessboard", seed)
    t0 = time.perf_counter()
    anchor = opencv_anchor(work / f"{label}_chess" / "calibration")
    dt = time.perf_counter() - t0
    na, dd = plane_errors(anchor.plane, truth.light_plane)
    for m, x in anchor.hand_eye.items():
        hr, ht = hand_eye_errors(x, truth.flange_from_cam)
        fa, fd = flange_plane_errors(anchor.plane, x, truth.light_plane, truth.flange_from_cam)
        fx, cx, cy = intrinsics_errors(anchor.camera.K, truth)
        name = f"OpenCV chessboard + {m} + Horus plane"
        rows.append((label, name, na, dd, hr, ht, fa, fd, dt, fx, cx, cy))
    study: list[str] = []
    if robot_draws > 0 and own_camera is not None:
        study = robot_draw_study(
            config, own_views, own_camera, anchor, truth, robot_draws, np.random.default_rng(seed)
        )
    return rows, study


def robot_draw_study(
    cell: Any,
    own_views: list[PosedView],
    own_camera: CameraModel,
    anchor: Anchor,
    truth: Any,
    draws: int,
    rng: np.random.Generator,
) -> list[str]:
    """Hand-eye errors over fresh draws of the robot's repeatability error, images kept.

    One simulated session is one draw of the robot's pose errors, and the hand-eye rotation
    error of a good solver is almost all robot error (about 0.001 deg per axis on the modern
    cell): one draw cannot rank two solvers that differ by less. Each draw here keeps the
    images (so the detections, and each view's target pose) and the true stops, and reports
    new poses ``reported = actual @ error`` with the cell's repeatability, the same
    errors for the concentric views and the chessboard views at the same stops. Draw 0 is
    the simulated session itself.

    Returns Markdown table lines: per solver the mean and RMS of the rotation and
    translation errors over the draws, and how often the default does better (paired).
    """
    robot = cell.robot
    actual = {
        f.id: f.base_from_flange_true
        for f in truth.sessions["calibration"].frames
        if f.base_from_flange_true is not None
    }
    solvers = [("default", "concentric", own_views, own_camera)]
    solvers += [(m, "concentric", own_views, own_camera) for m in AX_XB_METHODS]
    solvers += [(m, "chessboard", anchor.views, anchor.camera) for m in AX_XB_METHODS]
    errors = np.full((len(solvers), draws, 2), np.nan)
    ids = sorted({v.frame_id for v in own_views} | {v.frame_id for v in anchor.views})
    for d in range(draws):
        # The simulator's own repeatability draw, taken from the true stop: a zero-mean
        # error is as likely as its inverse, so this is a reported pose for that stop.
        reported = {
            i: perturb_pose(actual[i], rng, robot.repeatability_mm, robot.repeatability_deg)
            for i in ids
        }
        for k, (method, _, views, camera) in enumerate(solvers):
            if d > 0:  # draw 0: the session as simulated
                views = [replace(v, base_from_flange=reported[v.frame_id]) for v in views]
            res = calibrate_hand_eye(views, camera, method)
            if res:
                errors[k, d] = hand_eye_errors(res.flange_from_cam, truth.flange_from_cam)
    lines = [
        f"{cell.name}: {draws} draws of the robot's repeatability error "
        f"({robot.repeatability_deg} deg, {robot.repeatability_mm} mm per axis), images kept:",
        "",
        "| solver | target views | rot mean (deg) | rot RMS | trans mean (mm) | trans RMS "
        "| default better: rot | trans |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for k, (method, target, _, _) in enumerate(solvers):
        e = errors[k]
        better = np.mean(errors[0] < e, axis=0)
        paired = f"{better[0]:.2f} | {better[1]:.2f}" if k else "- | -"
        lines.append(
            f"| {method} | {target} | {np.nanmean(e[:, 0]):.5f} "
            f"| {np.sqrt(np.nanmean(e[:, 0] ** 2)):.5f} | {np.nanmean(e[:, 1]):.4f} "
            f"| {np.sqrt(np.nanmean(e[:, 1] ** 2)):.4f} | {paired} |"
        )
    return lines


# ----------------------------------------------------------------------------------- real data


def bench_kuka(root: Path) -> list[tuple[str, float, float, float, float]]:
    """Rows: (method, chain RMS px, origin std x, y, z mm), same intrinsics for all."""
    folder = root / "kuka_1"
    poses = np.loadtxt(folder / "RobotPosesVec.txt").reshape(-1, 4, 4)
    poses[:, :3, 3] *= 1000.0  # metres -> mm
    target = ChessboardTarget((28, 17), 20.0)
    obs = [detect_target(load_gray_image(folder / f"{i:02d}.png"), target) for i in range(1, 31)]
    intr = calibrate_intrinsics(obs, (1928, 1208), "default", target)
    cam = CameraModel(1928, 1208, intr.K, intr.dist)
    views = [PosedView(i, poses[i], o.points_px, o.points_target) for i, o in enumerate(obs) if o]
    rows = []
    for m in (*AX_XB_METHODS, "shah", "li", "default"):
        r = calibrate_hand_eye(views, cam, m)
        rows.append((m, r.rms_px, *r.target_spread_mm.tolist()))
    return rows


def bench_linelight(root: Path) -> dict[str, float]:
    folder = root / "zhaocongyang_linelight"
    target = CircleGridTarget((7, 7), 37.5)
    obs, laser = [], []
    for i in range(12):
        img = load_gray_image(folder / "calib_picture" / f"calib{i}.jpg")
        obs.append(detect_target(img, target))
        on, off = load_laser_images(
            folder / "light_picture" / f"light{i}.jpg", folder / "calib_picture" / f"calib{i}.jpg"
        )
        prof = extract_stripe(on, mode="precise", background=off)
        laser.append(np.column_stack([prof.u, prof.v]))
    intr = calibrate_intrinsics(obs, (1920, 1080), "default", target)
    cam = CameraModel(1920, 1080, intr.K, intr.dist)
    views = []
    for i, o in enumerate(obs):
        if not o:
            continue
        pose = estimate_pose(o.points_px, o.points_target, cam)
        views.append(LaserView(i, laser[i], pose.cam_from_target, target_extent_mm(target)))  # type: ignore[arg-type]
    res = calibrate_light_plane(views, cam)
    authors = LightPlane(np.array([-0.130517, -6.395953, 1.0]), -304.9186)
    ang, _ = plane_errors(res.plane, authors)  # type: ignore[arg-type]
    cloud = np.loadtxt(folder / "pointcloud.txt")
    dist = res.plane.signed_distance(cloud)  # type: ignore[union-attr]
    return {
        "normal_deg": ang,
        "cloud_mean_mm": float(np.mean(dist)),
        "cloud_rms_mm": float(np.sqrt(np.mean(dist**2))),
        "cloud_max_mm": float(np.abs(dist).max()),
        "plane_rms_mm": res.rms_mm,
        "worst_frame_mean_mm": max(abs(f["mean_mm"]) for f in res.per_frame),
        "frames": len(res.per_frame),
        "rejected": [r["frame_id"] for r in res.rejected],  # type: ignore[dict-item]
    }


def seed_summary(rows: list[Row]) -> str:
    """Per cell and method: each figure's mean |error| over the seeds, with its range."""
    names = [
        "normal (deg)",
        "d (mm)",
        "hand-eye rot (deg)",
        "hand-eye trans (mm)",
        "flange normal (deg)",
        "flange d (mm)",
        "fx (%)",
        "cx (px)",
        "cy (px)",
    ]
    cols = [2, 3, 4, 5, 6, 7, 9, 10, 11]
    groups: dict[tuple[str, str], list[Row]] = {}
    for r in rows:
        groups.setdefault((r[0], r[1]), []).append(r)
    out = [
        "Mean |error| over the seeds (smallest - largest):",
        "",
        "| cell | method | seeds | " + " | ".join(names) + " |",
        "|---|---|---|" + "---|" * len(names),
    ]
    for (cell, method), g in groups.items():
        cells = []
        for c in cols:
            v = np.abs([r[c] for r in g])
            cells.append(f"{v.mean():.4g} ({v.min():.3g} - {v.max():.3g})")
        out.append(f"| {cell} | {method} | {len(g)} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--cells", nargs="*", default=["modern", "paper"])
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_calibration"))
    ap.add_argument("--skip-real", action="store_true")
    ap.add_argument("--skip-cells", action="store_true")
    ap.add_argument(
        "--seed", type=int, default=0, help="the virtual cells' seed (use a --work per seed)"
    )
    ap.add_argument("--seeds", type=int, default=1, help="seeds from --seed on")
    ap.add_argument(
        "--randomised", action="store_true", help="each seed draws the cells' sensor anew"
    )
    ap.add_argument(
        "--robot-draws",
        type=int,
        default=50,
        help="hand-eye study over this many draws of the robot's error (0: none)",
    )
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if not args.skip_cells:
        print(
            "| cell | seed | method | normal err (deg) | d err (mm) | hand-eye rot (deg) "
            "| hand-eye trans (mm) | plane in flange: normal (deg) | d (mm) | time (s) "
            "| fx err (%) | cx err (px) | cy err (px) |"
        )
        print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        studies = []
        all_rows: list[Row] = []
        for seed in range(args.seed, args.seed + args.seeds):
            work = args.work if args.seeds == 1 else args.work / f"seed{seed}"
            for cell in args.cells:
                rows, study = bench_cell(cell, work, seed, args.robot_draws, args.randomised)
                for c, m, na, dd, hr, ht, fa, fd, dt, fx, cx, cy in rows:
                    print(
                        f"| {c} | {seed} | {m} | {na:.5f} | {dd:+.4f} | {hr:.5f} | {ht:.4f} "
                        f"| {fa:.5f} | {fd:+.4f} | {dt:.1f} | {fx:+.4f} | {cx:+.3f} | {cy:+.3f} |",
                        flush=True,
                    )
                all_rows += rows
                studies.append(study)
        print()
        if args.seeds > 1:
            print(seed_summary(all_rows))
            print()
        for study in studies:
            print("\n".join(study))
            print()
    root = real_data_root()
    if args.skip_real or not root.is_dir():
        return
    print("kuka_1 (same intrinsics for every solver):")
    print("| method | chain RMS (px) | origin std x (mm) | y | z | 3-D |")
    print("|---|---|---|---|---|---|")
    for m, rms, sx, sy, sz in bench_kuka(root):
        print(
            f"| {m} | {rms:.3f} | {sx:.3f} | {sy:.3f} | {sz:.3f} | {np.sqrt(sx**2 + sy**2 + sz**2):.3f} |"
        )
    print()
    print("zhaocongyang_linelight:")
    for k, v in bench_linelight(root).items():
        print(f"  {k}: {v}")


if __name__ == "__main__":
    main()
