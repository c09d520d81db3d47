"""Accuracy and speed of the intrinsics: concentric target (default and paper) vs a chessboard.

Renders 20 views of the cell's concentric target with the virtual cell (lens distortion,
blur, noise, vignetting), and a chessboard (11 x 8 inner corners, 14 mm) at the same poses,
detects, calibrates and prints a table method x figure against the cell's true camera:

* fx, fy relative error (%), cx, cy error (px),
* the largest distance over the whole image between pixels mapped through the true and the
  estimated camera (same ray), which judges the distortion model,
* RMS residual and time.

Real data (``../shared/data/real``, or ``SCANNER_REAL_DATA``) is calibrated too when present.

Two view sets: ``whole`` (both targets wholly in view at the same poses) and ``corners`` (near
and far, the concentric target anywhere in the image and allowed to run out of it, so that its
edges reach the corners; the chessboard is then often cut and not found).

Run: ``python benchmarks/bench_intrinsics.py [--cell modern] [--views 20] [--no-real]
[--views-set whole|corners]``.
Rendered images are cached in the system temporary folder (``--fresh`` to re-render).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small dense algebra: threads only contend

import argparse
import logging
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from calibration.detection.detect import detect_target
from calibration.detection.observations import TargetObservation
from calibration.intrinsics import IntrinsicsResult, calibrate_intrinsics
from scanner.core.camera import CameraModel
from scanner.core.conventions import make_transform
from scanner.core.images import load_gray_image
from scanner.core.targets import ChessboardTarget, CircleGridTarget
from scanner.formats.reference_data import ZHANG_MSR_IMAGE_SIZE, zhang_msr_corners

log = logging.getLogger("bench_intrinsics")

CHESSBOARD = ChessboardTarget(inner_corners=(11, 8), square_mm=14.0)


def _random_view(
    cam: CameraModel,
    working_distance_mm: float,
    rng: np.random.Generator,
    image_span: tuple[float, float],
    distance_span: tuple[float, float],
    max_tilt_deg: float,
) -> NDArray:
    """``cam_from_target`` with the target centre on the ray of a random pixel.

    The pixel lies in ``image_span`` (fractions of width and height), the distance in
    ``distance_span`` (times the working distance); tilted up to ``max_tilt_deg`` about a
    random in-plane axis, any in-plane rotation, target z towards the camera.
    """
    lo, hi = image_span
    u = rng.uniform(lo * cam.width, hi * cam.width)
    v = rng.uniform(lo * cam.height, hi * cam.height)
    ray = np.linalg.solve(cam.K, [u, v, 1.0])
    ray /= np.linalg.norm(ray)
    align, _ = Rotation.align_vectors([[0, 0, 1.0]], [ray])
    tilt = np.radians(max_tilt_deg) * np.sqrt(rng.uniform(0.05, 1.0))
    az = rng.uniform(0, 2 * np.pi)
    tilt_rot = Rotation.from_rotvec(tilt * np.array([np.cos(az), np.sin(az), 0.0]))
    roll = Rotation.from_euler("z", rng.uniform(0, 360), degrees=True)
    face = Rotation.from_euler("x", 180, degrees=True)
    rot = align.inv() * tilt_rot * face * roll
    return make_transform(rot, ray * working_distance_mm * rng.uniform(*distance_span))


def spread_poses(cell, n: int, rng: np.random.Generator, max_tilt_deg: float = 45.0) -> list:
    """``cam_from_target`` of n hand-held views spread over the image.

    The target centre goes on the ray of a random pixel at 0.9-1.1 working distances, tilted
    up to ``max_tilt_deg`` about a random in-plane axis, any in-plane rotation; a pose is kept
    only when both the whole chessboard (centred on the target's centre) and the whole
    concentric target with its marker are inside the image with a 15 px margin, so both
    targets are seen completely at the same poses and reach as far out as they can.
    """
    from scanner.core.conventions import transform_points

    cam = cell.camera_model()
    wd = cell.capture.working_distance_mm
    spec = cell.target_spec()
    cols, rows = CHESSBOARD.inner_corners
    half = np.array([(cols + 1) / 2, (rows + 1) / 2]) * CHESSBOARD.square_mm
    outline = [np.array([sx * half[0], sy * half[1], 0.0]) for sx in (-1, 1) for sy in (-1, 1)]
    r_out = (
        max(
            spec.radius_mm,
            np.hypot(*spec.orientation_marker.center_mm) + spec.orientation_marker.diameter_mm,
        )
        if hasattr(spec, "radius_mm")
        else 0.0
    )
    th = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    outline += [np.array([r_out * np.cos(a), r_out * np.sin(a), 0.0]) for a in th]
    outline_t = np.asarray(outline)
    poses: list = []
    while len(poses) < n:
        pose = _random_view(cam, wd, rng, (0.0, 1.0), (0.9, 1.1), max_tilt_deg)
        pc = transform_points(pose, outline_t)
        if np.all(pc[:, 2] > 0) and np.all(cam.in_image(cam.project(pc), 15.0)):
            poses.append(pose)
    return poses


def corner_poses(cell, n: int, rng: np.random.Generator, max_tilt_deg: float = 45.0) -> list:
    """``cam_from_target`` of n views that let the concentric target reach the corners.

    The target centre on the ray of a random pixel (10-90 % of the image), at 0.6-1.1
    working distances, tilted up to ``max_tilt_deg``, any in-plane rotation; the centre O and
    the orientation disc in view with a 40 px margin and at least half of the largest ring
    inside the image. The chessboard at the same pose is often cut by the border there, and
    OpenCV's detector then finds nothing: the anchor uses the views it finds.
    """
    from scanner.core.conventions import transform_points

    cam = cell.camera_model()
    wd = cell.capture.working_distance_mm
    spec = cell.target_spec()
    ring = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    ring_t = spec.radius_mm * np.column_stack([np.cos(ring), np.sin(ring), 0 * ring])
    needed_t = np.array([[0.0, 0.0, 0.0], [*spec.orientation_marker.center_mm, 0.0]])
    poses: list = []
    while len(poses) < n:
        pose = _random_view(cam, wd, rng, (0.1, 0.9), (0.6, 1.1), max_tilt_deg)
        if not np.all(cam.in_image(cam.project(transform_points(pose, needed_t)), 40.0)):
            continue
        if np.mean(cam.in_image(cam.project(transform_points(pose, ring_t)))) < 0.5:
            continue
        poses.append(pose)
    return poses


VIEW_SETS = {
    "whole": "both targets wholly in view at every pose (the same views for both)",
    "corners": "near and far, anywhere in the image, the concentric target may leave it",
}


def render_views(
    cell_name: str, n: int, fresh: bool = False, view_set: str = "whole"
) -> tuple[list, list, list, list]:
    """(poses, concentric images, chessboard images, chessboard poses), cached on disk."""
    from scanner.virtual_cell import load_cell, render_target_image

    cell = load_cell(cell_name)
    tag = "v2" if view_set == "whole" else "corners_v1"
    cache = Path(tempfile.gettempdir()) / f"scanner_bench_intrinsics_{tag}_{cell_name}_{n}"
    cache.mkdir(parents=True, exist_ok=True)
    if view_set == "whole":
        poses = spread_poses(cell, n, np.random.default_rng(2026))
    else:
        poses = corner_poses(cell, n, np.random.default_rng(2026))
    cols, rows = CHESSBOARD.inner_corners
    centre = make_transform(
        np.eye(3),
        [-(cols - 1) / 2 * CHESSBOARD.square_mm, -(rows - 1) / 2 * CHESSBOARD.square_mm, 0],
    )
    ring_imgs, cb_imgs, cb_poses = [], [], []
    for i, pose in enumerate(poses):
        cb_pose = pose @ centre
        cb_poses.append(cb_pose)
        for kind, p, target, out in (
            ("ring", pose, None, ring_imgs),
            ("cb", cb_pose, CHESSBOARD, cb_imgs),
        ):
            path = cache / f"{kind}_{i:02d}.png"
            if fresh or not path.is_file():
                img = render_target_image(
                    cell, p, np.random.default_rng(1000 * (kind == "cb") + i), target=target
                )
                cv2.imwrite(str(path), img)
            out.append(cv2.imread(str(path), cv2.IMREAD_UNCHANGED))
    return poses, ring_imgs, cb_imgs, cb_poses


def max_mapping_error_px(
    truth: CameraModel, K: NDArray, dist: NDArray, step: int = 8, hull: NDArray | None = None
) -> float:
    """Largest pixel distance between truth and estimate for one ray, over the whole image
    (or only the pixels inside ``hull``, a convex polygon (M, 2))."""
    uu, vv = np.meshgrid(np.arange(0, truth.width, step), np.arange(0, truth.height, step))
    uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(np.float64)
    if hull is not None:
        poly = hull.reshape(-1, 1, 2).astype(np.float32)
        keep = [cv2.pointPolygonTest(poly, (float(u), float(v)), False) >= 0 for u, v in uv]
        uv = uv[np.asarray(keep)]
    xy = truth.normalize(uv)
    est = CameraModel(truth.width, truth.height, K, dist)
    back = est.project(np.column_stack([xy, np.ones(len(xy))]))
    return float(np.max(np.linalg.norm(back - uv, axis=1)))


def figures(
    truth: CameraModel, K: NDArray, dist: NDArray, hull: NDArray | None = None
) -> dict[str, float]:
    return {
        "map_in_px": max_mapping_error_px(truth, K, dist, hull=hull)
        if hull is not None
        else float("nan"),
        "fx_%": (K[0, 0] / truth.K[0, 0] - 1) * 100,
        "fy_%": (K[1, 1] / truth.K[1, 1] - 1) * 100,
        "cx_px": K[0, 2] - truth.K[0, 2],
        "cy_px": K[1, 2] - truth.K[1, 2],
        "map_px": max_mapping_error_px(truth, K, dist),
    }


def opencv_chessboard(
    images: list, size: tuple[int, int]
) -> tuple[NDArray, NDArray, float, int, dict[str, float]]:
    """The anchor: findChessboardCornersSB + calibrateCamera (5 distortion terms).

    Returns K, dist, RMS, the number of views found and OpenCV's standard deviations of the
    intrinsics (``calibrateCameraExtended``).
    """
    obj, img = [], []
    for im in images:
        found, corners = cv2.findChessboardCornersSB(
            im, CHESSBOARD.inner_corners, flags=cv2.CALIB_CB_ACCURACY
        )
        if found:
            obj.append(CHESSBOARD.object_points().astype(np.float32))
            img.append(corners.reshape(-1, 2).astype(np.float32))
    if len(obj) < 4:
        return np.full((3, 3), np.nan), np.full(5, np.nan), float("nan"), len(obj), {}
    rms, K, dist, _, _, std_intr, _, _ = cv2.calibrateCameraExtended(obj, img, size, None, None)
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    std = {k: float(v) for k, v in zip(names, std_intr.ravel())}
    return K, dist.ravel()[:5], float(rms), len(obj), std


def row(
    name: str,
    fig: dict[str, float],
    rms: float,
    secs: float,
    views: int,
    std: dict[str, float] | None = None,
) -> str:
    sd = std or {}
    sx, sy = sd.get("cx", float("nan")), sd.get("cy", float("nan"))
    return (
        f"| {name:<34} | {fig['fx_%']:+.5f} | {fig['fy_%']:+.5f} | {fig['cx_px']:+.3f} | "
        f"{fig['cy_px']:+.3f} | {sx:.3f} / {sy:.3f} | {fig['map_px']:.3f} | "
        f"{fig['map_in_px']:.3f} | {rms:.4f} | {views:>2} | {secs:5.1f} |"
    )


def bench_cell(cell_name: str, n: int, fresh: bool, view_set: str = "whole") -> list[str]:
    from scanner.virtual_cell import load_cell

    cell = load_cell(cell_name)
    truth = cell.camera_model()
    size = (truth.width, truth.height)
    t0 = time.perf_counter()
    _, ring_imgs, cb_imgs, _ = render_views(cell_name, n, fresh, view_set)
    log.info("rendered/loaded %d views in %.1f s", n, time.perf_counter() - t0)
    target = cell.target_spec()
    lines = [
        f"\n## Cell `{cell_name}`, views `{view_set}`: {n} views, {size[0]}x{size[1]}, "
        f"true fx {truth.K[0, 0]}, dist {truth.dist.tolist()}\n",
        f"Views: {VIEW_SETS[view_set]}. std: the method's own standard deviation of cx / cy "
        "(ours from the adjustment, OpenCV's from calibrateCameraExtended); an error within "
        "about twice it is noise, not a difference between methods.\n",
        "| method | fx err % | fy err % | cx err px | cy err px | std cx / cy px "
        "| max map err px (image) | max map err px (seen) | RMS px | views | s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    t0 = time.perf_counter()
    obs = [detect_target(im, target) for im in ring_imgs]
    t_det = time.perf_counter() - t0
    seen = np.vstack([r.edge_points_px for o in obs if o for r in o.rings])
    hull = cv2.convexHull(seen.astype(np.float32)).reshape(-1, 2)
    found = sum(bool(o) for o in obs)
    lines.append(
        f"| concentric detection: {found}/{n} found, {t_det / n:.2f} s per image "
        "| | | | | | | | | | |"
    )
    t0 = time.perf_counter()
    c0 = time.process_time()
    res: IntrinsicsResult = calibrate_intrinsics(obs, size, method="default")
    t_cal = time.perf_counter() - t0
    cpu_cal = time.process_time() - c0
    lines.append(
        row(
            "concentric, default (ours)",
            figures(truth, res.K, res.dist, hull),
            res.rms_px,
            t_cal,
            len(res.view_indices),
            res.std,
        )
    )
    for variant, est in res.paper.items():
        if est:
            lines.append(
                row(
                    f"concentric, paper ({variant})",
                    figures(truth, est.K, np.zeros(5), hull),
                    float("nan"),
                    0.0,
                    found,
                )
            )
        else:
            lines.append(
                f"| concentric, paper ({variant}): failed: {est.reason} | | | | | | | | | | |"
            )
    t0 = time.perf_counter()
    K, dist, rms, nv, cv_std = opencv_chessboard(cb_imgs, size)
    if nv >= 4:
        lines.append(
            row(
                "chessboard, OpenCV SB + calibrateCamera",
                figures(truth, K, dist, hull),
                rms,
                time.perf_counter() - t0,
                nv,
                cv_std,
            )
        )
    else:
        lines.append(f"| chessboard, OpenCV SB: found in {nv} views, too few | | | | | | | | | | |")
    cb_obs = [detect_target(im, CHESSBOARD) for im in cb_imgs]
    t0 = time.perf_counter()
    try:
        cres = calibrate_intrinsics(cb_obs, size)
    except ValueError as exc:
        lines.append(f"| chessboard, our detection + default: {exc} | | | | | | | | | | |")
        cres = None
    if cres is not None:
        lines.append(
            row(
                "chessboard, our detection + default",
                figures(truth, cres.K, cres.dist, hull),
                cres.rms_px,
                time.perf_counter() - t0,
                len(cres.view_indices),
                cres.std,
            )
        )
    lines.append(
        f"\ndefault calibration: {t_cal:.1f} s wall, {cpu_cal:.1f} s CPU; std "
        + ", ".join(f"{k} {v:.3g}" for k, v in res.std.items())
    )
    if res.warnings:
        lines.append(f"\nwarnings: {res.warnings}")
    if res.rejected:
        lines.append(f"rejected: {res.rejected}")
    return lines


def real_data_dir() -> Path:
    env = os.environ.get("SCANNER_REAL_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real"


#: Real data sets detected and calibrated whole: folder, image pattern, target, reference.
DETECTED_SETS = (
    (
        "zhaocongyang_linelight/calib_picture",
        "*.jpg",
        CircleGridTarget(grid=(7, 7), pitch_mm=37.5),
        "zhaocongyang circle grid",
        "fx 1144.44, fy 1142.49, 916.06, 522.05",
    ),
    (
        "kuka_1",
        "*.png",
        ChessboardTarget(inner_corners=(28, 17), square_mm=20.0),
        "kuka_1 chessboard",
        "OpenCV: RMS 0.0738, 2057.96, 2058.36, 960.12, 610.09",
    ),
)


def real_rows() -> list[str]:
    """Real data sets against their published or reference results."""
    root = real_data_dir()
    if not root.is_dir():
        return [f"\n(real data not found at {root}: skipped)"]
    out = [
        "\n## Real data\n",
        "| data set | method | fx | fy | cx | cy | k1 | k2 | RMS px | reference | s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def line(name: str, how: str, r: IntrinsicsResult, ref: str, secs: float) -> str:
        return (
            f"| {name} | {how} | {r.fx:.2f} | {r.fy:.2f} | {r.cx:.2f} | {r.cy:.2f} | "
            f"{r.dist[0]:.4f} | {r.dist[1]:.4f} | {r.rms_px:.4f} | {ref} | {secs:.1f} |"
        )

    zhang = root / "zhang_msr"
    if zhang.is_dir():
        model_t, views = zhang_msr_corners(zhang)
        size = ZHANG_MSR_IMAGE_SIZE
        obs = [TargetObservation(True, "", size, "chessboard", uv, model_t) for uv in views]
        ref = "832.5, 832.53, 303.959, 206.585, k -0.2286, 0.1904 (published)"
        for how, fixed in (
            ("default, k1 k2 (Zhang's model)", ("p1", "p2", "k3")),
            ("default, 5 terms", ()),
        ):
            t0 = time.perf_counter()
            r = calibrate_intrinsics(obs, size, fixed=fixed)
            out.append(line("zhang_msr dataN.txt corners", how, r, ref, time.perf_counter() - t0))
        out.append(
            "| zhang_msr images | - | | | | | | | | not detected: the board is 64 separate "
            "squares, not a chessboard (OpenCV finds no X-corners); the given corners are used |"
            " |"
        )
    for folder, pattern, target, label, reference in DETECTED_SETS:
        images = root / folder
        if not images.is_dir():
            continue
        t0 = time.perf_counter()
        obs = [detect_target(load_gray_image(p), target) for p in sorted(images.glob(pattern))]
        r = calibrate_intrinsics(obs, obs[0].image_size)
        name = f"{label} ({sum(map(bool, obs))}/{len(obs)})"
        out.append(line(name, "detect + default", r, reference, time.perf_counter() - t0))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cell", action="append", help="cell name(s), default modern and paper")
    ap.add_argument("--views", type=int, default=20)
    ap.add_argument("--fresh", action="store_true", help="re-render the cached images")
    ap.add_argument("--no-real", action="store_true")
    ap.add_argument(
        "--views-set",
        action="append",
        choices=sorted(VIEW_SETS),
        help="view set(s), default both: " + "; ".join(f"{k}: {v}" for k, v in VIEW_SETS.items()),
    )
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    out = ["# Intrinsics benchmark"]
    for name in args.cell or ["modern", "paper"]:
        for view_set in args.views_set or ["whole", "corners"]:
            out += bench_cell(name, args.views, args.fresh, view_set)
    if not args.no_real:
        out += real_rows()
    print("\n".join(out))


if __name__ == "__main__":
    main()
