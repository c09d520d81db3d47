"""Simulate a whole cell: calibration, check and sweep sessions plus the ground truth.

:func:`simulate_cell` plans every robot stop first (cheap, deterministic from the seed), then
renders and writes the images in worker processes, then writes the sessions
(``scan-session/1``) and ``truth.json``. Each frame draws its noise from its own generator
(spawned from the seed), so the images do not depend on the number of workers.
"""

from __future__ import annotations

import csv
import io
import logging
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from scanner.core.conventions import invert_transform, make_transform
from scanner.core.fileio import write_json_atomic, write_text_atomic
from scanner.core.parallel import process_map
from scanner.core.targets import ConcentricCirclesTarget, TargetSpec
from scanner.formats.calibration_file import LightPlane, write_calibration
from scanner.formats.session import Frame, write_session
from scanner.virtual_cell.capture import (
    hand_held_scene,
    posed_target_scene,
    render_image_pair,
    render_scene_image,
    sweep_scene,
)
from scanner.virtual_cell.cell import CellConfig, load_cell, load_target
from scanner.virtual_cell.poses import (
    aimed_view,
    hand_held_view,
    light_plane_view,
    perturb_pose,
    posed_view,
    sweep_poses,
    target_extent_mm,
)
from scanner.virtual_cell.render import Laser, Scene, ray_map, stripe_truth
from scanner.virtual_cell.scene import object_from_euler
from scanner.virtual_cell.truth import (
    CellTruth,
    FrameTruth,
    ObjectTruth,
    SessionTruth,
    StripeTable,
    truth_to_json,
)

__all__ = ["FramePlan", "plan_cell", "resolve_target", "simulate_cell"]

log = logging.getLogger(__name__)

TARGET_ALIASES = {"chessboard": "chessboard_11x8", "circle_grid": "circle_grid_7x5"}


@dataclass(frozen=True)
class FramePlan:
    """One robot stop to render: the true geometry and what to capture."""

    session: str
    id: int
    stage: str
    aim: str
    seed: int
    target_image: bool
    laser_image: bool
    cam_from_target: NDArray | None = None
    """True placement of a hand-held target (no robot pose)."""
    base_from_flange_reported: NDArray | None = None
    base_from_flange_true: NDArray | None = None
    base_from_cam_true: NDArray | None = None
    sweep: int = 0
    """Which sweep of a multi-sweep session the frame belongs to."""


def resolve_target(cell: CellConfig, name: str | None) -> tuple[TargetSpec, NDArray]:
    """The printed target and ``concentric_from_printed`` (where its frame sits on the card).

    ``None`` or ``"concentric"`` is the cell's own target; ``chessboard`` and ``circle_grid``
    are the shipped standard targets, centred on the same card position; anything else is a
    ``configs/targets`` name or path.
    """
    if name in (None, "", "concentric"):
        return cell.target_spec(), np.eye(4)
    spec = load_target(TARGET_ALIASES.get(name, name))
    if isinstance(spec, ConcentricCirclesTarget):
        return spec, np.eye(4)
    centre, _ = target_extent_mm(spec)
    return spec, make_transform(np.eye(3), -centre)


def plan_cell(
    cell: CellConfig,
    seed: int,
    sweep_frames: int | None = None,
    sweep_paths: Sequence[NDArray] | None = None,
) -> dict[str, list[FramePlan]]:
    """Every frame of the three sessions, deterministic from ``seed``.

    ``sweep_paths`` (commanded ``base_from_flange`` of each sweep, ``(F_k, 4, 4)``, as a
    planner writes them) replaces the cell's one linear sweep.
    """
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0]))
    session_keys = {"calibration": 1, "check": 2, "sweep": 3}

    def noise_seed(session: str, fid: int) -> int:
        return int(np.random.SeedSequence([seed, session_keys[session], fid]).generate_state(1)[0])

    cap, rob = cell.capture, cell.robot
    f_c = rob.flange_from_cam_matrix()
    c_f = invert_transform(f_c)
    b_t = rob.base_from_target()
    spec = cell.target_spec()
    named = (
        spec.named_points()
        if isinstance(spec, ConcentricCirclesTarget)
        else {"O": target_extent_mm(spec)[0]}
    )

    def robot(base_from_cam_cmd: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        reported = base_from_cam_cmd @ c_f
        actual = perturb_pose(reported, rng, rob.repeatability_mm, rob.repeatability_deg)
        return reported, actual, actual @ f_c

    def posed(session: str, fid: int, stage: str, aim: str, c_t: NDArray) -> FramePlan:
        reported, actual, b_c = robot(b_t @ invert_transform(c_t))
        return FramePlan(
            session,
            fid,
            stage,
            aim,
            noise_seed(session, fid),
            True,
            True,
            None,
            reported,
            actual,
            b_c,
        )

    calib: list[FramePlan] = []
    # Frames without pose (the target held in front of the camera), stage by stage.
    unposed = (
        ("hand_held", cap.hand_held_frames, hand_held_view),
        ("light_plane", cap.light_plane_frames, light_plane_view),
    )
    for stage, count, view in unposed:
        for _ in range(count):
            c_t = view(cell, rng)
            fid = len(calib)
            calib.append(
                FramePlan(
                    "calibration", fid, stage, "", noise_seed("calibration", fid), True, True, c_t
                )
            )
    for _ in range(cap.posed_frames):
        calib.append(posed("calibration", len(calib), "posed", "", posed_view(cell, rng)))
    aims = [a for a in ("O", "A", "C") if a in named]
    for aim in aims:
        for _ in range(cap.aim_frames_each):
            calib.append(
                posed("calibration", len(calib), "aim", aim, aimed_view(cell, rng, named[aim]))
            )
    check = [
        posed(
            "check",
            k,
            "check",
            "O",
            aimed_view(cell, rng, named["O"], (5.0, 35.0), ring_crossings_in_view=True),
        )
        for k in range(cap.check_frames)
    ]
    if sweep_paths is None:
        paths = [sweep_poses(cell, sweep_frames)[0]]
    else:
        paths = [np.asarray(path, dtype=np.float64) @ f_c for path in sweep_paths]
    sweep = []
    for index, b_cams in enumerate(paths):
        for b_c in b_cams:
            k = len(sweep)
            reported, actual, b_c_true = robot(b_c)
            sweep.append(
                FramePlan(
                    "sweep",
                    k,
                    "sweep",
                    "",
                    noise_seed("sweep", k),
                    False,
                    True,
                    None,
                    reported,
                    actual,
                    b_c_true,
                    index,
                )
            )
    return {"calibration": calib, "check": check, "sweep": sweep}


# ---------------------------------------------------------------------------------------------
# Rendering (in worker processes)


@dataclass(frozen=True)
class _Job:
    cell: CellConfig
    plan: FramePlan
    out: Path
    target: TargetSpec
    concentric_from_printed: NDArray
    fast_sweep: bool = True


def _scene(job: _Job) -> Scene:
    p, cell = job.plan, job.cell
    if p.session == "sweep":
        return sweep_scene(cell, p.base_from_cam_true)
    if p.cam_from_target is not None:
        return hand_held_scene(cell, p.cam_from_target @ job.concentric_from_printed, job.target)
    b_t = cell.robot.base_from_target() @ job.concentric_from_printed
    return posed_target_scene(cell, p.base_from_cam_true, job.target, b_t)


def _write_png(path: Path, image: NDArray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    if not cv2.imwrite(str(tmp), image, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise OSError(f"{path}: cannot write PNG")
    os.replace(tmp, path)


def _render(job: _Job) -> tuple[str, int, NDArray, NDArray, NDArray, tuple[str, ...]]:
    p, cell = job.plan, job.cell
    rng = np.random.default_rng(p.seed)
    scene = _scene(job)
    uv = np.zeros((0, 2))
    sid = np.zeros(0, dtype=np.int32)
    pts = np.zeros((0, 3))
    ids: tuple[str, ...] = ()
    images = job.out / p.session / "images"
    if p.target_image and p.laser_image:
        target_img, laser_img = render_image_pair(cell, scene, rng)
        _write_png(images / f"target_{p.id:04d}.png", target_img)
        _write_png(images / f"laser_{p.id:04d}.png", laser_img)
    elif p.target_image:
        _write_png(images / f"target_{p.id:04d}.png", render_scene_image(cell, scene, rng, False))
    elif p.laser_image:
        img = render_scene_image(cell, scene, rng, True, coarse_ambient=job.fast_sweep)
        _write_png(images / f"laser_{p.id:04d}.png", img)
    if p.laser_image:
        st = stripe_truth(cell.camera, scene, Laser.from_cell(cell, scene.world_from_cam))
        uv, sid, pts, ids = st.uv, st.surface, st.points_world, st.surface_ids
    return p.session, p.id, uv, sid, pts, ids


def _run_jobs(
    jobs: list[_Job], workers: int, check_cancelled: Callable[[], None] | None = None
) -> Iterator[tuple]:
    """Each job's rendered frame, in order; ``check_cancelled`` before the first and after
    each (:func:`~scanner.core.parallel.process_map`)."""
    return process_map(_render, jobs, workers, chunksize=4, check_cancelled=check_cancelled)


# ---------------------------------------------------------------------------------------------


def _objects_truth(cell: CellConfig) -> tuple[list[ObjectTruth], dict]:
    objs = [ObjectTruth("table", "plane", {"normal": [0.0, 0.0, 1.0], "d": -cell.sweep.table_z_mm})]

    spheres = []
    for ob in cell.sweep.objects:
        if ob.type == "sphere":
            objs.append(
                ObjectTruth(
                    ob.id,
                    "sphere",
                    {"center_mm": list(ob.center_mm), "diameter_mm": ob.diameter_mm},
                )
            )
            spheres.append(ob)
        elif ob.type == "cylinder":
            objs.append(
                ObjectTruth(
                    ob.id,
                    "cylinder",
                    {
                        "p0_mm": list(ob.p0_mm),
                        "p1_mm": list(ob.p1_mm),
                        "diameter_mm": ob.diameter_mm,
                    },
                )
            )
        elif ob.type == "mesh":
            m = object_from_euler(np.array(ob.center_mm), np.array(ob.euler_xyz_deg))
            objs.append(ObjectTruth(ob.id, "mesh", {"path": ob.path, "base_from_part": m.tolist()}))
        else:
            m = object_from_euler(np.array(ob.center_mm), np.array(ob.euler_xyz_deg))
            top_n = m[:3, 2]
            top_p = m[:3, 3] + top_n * ob.size_mm[2] / 2
            objs.append(
                ObjectTruth(
                    ob.id,
                    "box",
                    {
                        "base_from_box": m.tolist(),
                        "size_mm": list(ob.size_mm),
                        "top_plane": {"normal": top_n.tolist(), "d": float(-top_n @ top_p)},
                    },
                )
            )
    pairs = [
        {
            "a": a.id,
            "b": b.id,
            "distance_mm": float(np.linalg.norm(np.subtract(a.center_mm, b.center_mm))),
        }
        for i, a in enumerate(spheres)
        for b in spheres[i + 1 :]
    ]
    return objs, {"sphere_pairs": pairs}


def _add_columns(csv_path: Path, columns: dict[str, dict[int, str]]) -> None:
    """Append extension columns (readers ignore unknown columns) to a written frames.csv."""
    rows = list(csv.reader(io.StringIO(csv_path.read_text(encoding="utf-8"))))
    header = rows[0]
    id_col = header.index("id")
    out = [[*header, *columns]]
    for row in rows[1:]:
        fid = int(row[id_col])
        out.append([*row, *(columns[c].get(fid, "") for c in columns)])
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(out)
    write_text_atomic(csv_path, buf.getvalue())


def simulate_cell(
    cell: CellConfig | str,
    out_dir: str | os.PathLike[str],
    seed: int = 0,
    target: str | None = None,
    sweep_frames: int | None = None,
    workers: int = 2,
    sessions: tuple[str, ...] = ("calibration", "check", "sweep"),
    progress: bool = False,
    fast_sweep: bool = True,
    sweep_paths: Sequence[NDArray] | None = None,
    check_cancelled: Callable[[], None] | None = None,
) -> CellTruth:
    """Render the cell's calibration, check and sweep sessions and write the truth.

    Parameters
    ----------
    cell : CellConfig or str
        A cell or the name of ``configs/cells/<name>.toml``.
    out_dir : path
        Gets ``calibration/``, ``check/``, ``sweep/`` (``scan-session/1``), ``truth.json``,
        ``<session>_stripes.npz`` and ``calibration_true.json``.
    seed : int
        Everything (poses, repeatability errors, noise) follows from it.
    target : str, optional
        Print another target at the same poses: ``chessboard``, ``circle_grid``, a
        ``configs/targets`` name or path; default the cell's own.
    sweep_frames : int, optional
        Override ``sweep.frames``.
    workers : int
        Processes rendering images (each frame has its own noise generator: results do not
        depend on this).
    sessions : tuple of str
        Which sessions to write.
    progress : bool
        Show a progress bar on standard error.
    fast_sweep : bool
        Render sweep images with the dim ambient light shaded every other pixel (the laser
        line exactly): about three times faster; False shades every pixel fully.
    sweep_paths : sequence of ndarray, each shape (F_k, 4, 4), optional
        Commanded ``base_from_flange`` of each sweep (a planned scan): a multi-sweep session
        (its ``sweep`` column) instead of the cell's one linear sweep.
    check_cancelled : callable, optional
        Called before the first frame is rendered and after each: whatever it raises stops
        the rendering and comes out of this function (a PLC job's cancellation). The frames
        rendered so far stay in ``out_dir``, with no ``session.json`` beside them.

    Returns
    -------
    CellTruth
    """
    cell = load_cell(cell)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    spec, c_from_p = resolve_target(cell, target)
    plans = plan_cell(cell, seed, sweep_frames, sweep_paths)
    plans = {k: v for k, v in plans.items() if k in sessions}
    ray_map(cell.camera)  # compute once before the workers fork
    jobs = [_Job(cell, p, out, spec, c_from_p, fast_sweep) for name in plans for p in plans[name]]
    stripes: dict[str, list[tuple]] = {name: [] for name in plans}
    bar = tqdm(
        total=len(jobs),
        desc=f"simulate {cell.name}",
        unit="frame",
        file=sys.stderr,
        disable=not progress,
    )
    with bar, closing(_run_jobs(jobs, workers, check_cancelled)) as rendered:
        for name, fid, uv, sid, pts, ids in rendered:
            stripes[name].append((fid, uv, sid, pts, ids))
            bar.update(1)

    f_c = cell.robot.flange_from_cam_matrix()
    b_t = cell.robot.base_from_target() @ c_from_p
    session_truths: dict[str, SessionTruth] = {}
    for name, plan in plans.items():
        root = out / name
        frames = [
            Frame(
                id=p.id,
                target_image=(root / "images" / f"target_{p.id:04d}.png")
                if p.target_image
                else None,
                laser_image=(root / "images" / f"laser_{p.id:04d}.png") if p.laser_image else None,
                base_from_flange=p.base_from_flange_reported,
                sweep=p.sweep,
            )
            for p in plan
        ]
        any_pose = any(p.base_from_flange_reported is not None for p in plan)
        write_session(
            root,
            name,
            cell.camera.width,
            cell.camera.height,
            frames,
            rotation=cell.robot.rotation if any_pose else None,
            target=None if name == "sweep" else spec,
            extra={"simulated": {"cell": cell.name, "seed": seed}},
        )
        if name != "sweep":
            _add_columns(root / "frames.csv", {"aim": {p.id: p.aim for p in plan}})
        truth_frames = []
        for p in plan:
            if p.cam_from_target is not None:
                c_t = p.cam_from_target @ c_from_p
            elif name != "sweep":
                c_t = invert_transform(p.base_from_cam_true) @ b_t
            else:
                c_t = None
            truth_frames.append(
                FrameTruth(
                    p.id,
                    p.stage,
                    p.aim,
                    p.base_from_flange_reported,
                    p.base_from_flange_true,
                    p.base_from_cam_true,
                    c_t,
                )
            )
        rows = sorted(stripes[name], key=lambda r: r[0])
        ids = next((r[4] for r in rows if r[4]), ())
        # Surface ids differ between hand-held and posed scenes: map them onto one list.
        all_ids: list[str] = []
        for r in rows:
            for s in r[4]:
                if s not in all_ids:
                    all_ids.append(s)
        ids = tuple(all_ids) if all_ids else ids
        remap = [np.array([ids.index(s) for s in r[4]], dtype=np.int32) for r in rows]
        table = StripeTable(
            frame_id=np.concatenate([np.full(len(r[1]), r[0], dtype=np.int32) for r in rows])
            if rows
            else np.zeros(0, np.int32),
            uv=np.concatenate([r[1] for r in rows]) if rows else np.zeros((0, 2)),
            surface=np.concatenate(
                [m[r[2]] if len(r[2]) else np.zeros(0, np.int32) for m, r in zip(remap, rows)]
            )
            if rows
            else np.zeros(0, np.int32),
            points=np.concatenate([r[3] for r in rows]) if rows else np.zeros((0, 3)),
            surface_ids=ids,
        )
        stripe_path = out / f"{name}_stripes.npz"
        table.save(stripe_path)
        session_truths[name] = SessionTruth(name, truth_frames, stripe_path)

    objects, extra = _objects_truth(cell)
    extra["concentric_from_printed"] = c_from_p.tolist()
    truth = CellTruth(
        cell=cell.name,
        seed=seed,
        camera=cell.camera_model(),
        light_plane=LightPlane(cell.laser.normal, cell.laser.d),
        laser_origin_cam=cell.laser.origin,
        flange_from_cam=f_c,
        base_from_target=b_t,
        target=spec,
        objects=objects,
        sessions=session_truths,
        extra=extra,
    )
    write_json_atomic(out / "truth.json", truth_to_json(truth))
    write_calibration(out / "calibration_true.json", truth.calibration())
    log.info("simulated %s into %s", cell.name, out)
    return truth
