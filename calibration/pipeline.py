"""``scanner calibrate`` as a function: a calibration session in, a calibration file out.

Stages, each reported in the result's ``quality``:

1. detection on every target image (:func:`calibration.detection.detect.detect_target`);
2. intrinsics on every target image, posed and unposed (:mod:`calibration.intrinsics`);
3. stripe extraction on every laser image (:mod:`scanner.stripe.extract`);
4. light plane (:mod:`calibration.light_plane`);
5. extrinsics of every view (:mod:`calibration.extrinsics`);
6. hand-eye (:mod:`calibration.hand_eye`).

``method="default"`` uses every target feature and the robust, jointly adjusted solutions;
``method="paper"`` runs the paper's stages (III.A-D), available only with the
concentric-circles target.
"""

from __future__ import annotations

import csv
import logging
import time
from collections.abc import Callable, Iterator
from contextlib import closing
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from calibration.covariance import estimate_covariance
from calibration.detection.detect import detect_target
from calibration.detection.observations import TargetObservation
from calibration.extrinsics import estimate_pose, paper_pose, project_target
from calibration.hand_eye import (
    HandEyeResult,
    PosedView,
    StripePointView,
    calibrate_hand_eye,
    paper_hand_eye,
)
from calibration.intrinsics import calibrate_intrinsics
from calibration.intrinsics_paper import view_vanishing_points
from calibration.laser_origin import LaserOriginResult, estimate_laser_origin, shadow_lines
from calibration.light_plane import (
    LaserView,
    LightPlaneResult,
    PaperPlaneView,
    calibrate_light_plane,
    paper_light_plane,
)
from calibration.symmetry import relabel, resolve_quarter_turns, turn
from scanner.core.camera import CameraModel, intersect_rays_with_plane
from scanner.core.images import load_gray_image
from scanner.core.parallel import process_map
from scanner.core.targets import ChessboardTarget, ConcentricCirclesTarget, TargetSpec
from scanner.formats.calibration_file import Calibration, CalibrationQuality, LightPlane
from scanner.formats.session import Frame, Session
from scanner.stripe.extract import extract_stripe
from scanner.stripe.profile import StripeOptions

__all__ = ["CalibrationResult", "calibrate_session", "stripe_pixel_at", "target_extent_mm"]

logger = logging.getLogger(__name__)

METHODS = ("default", "paper")
#: Rows with a robot pose and a target image that a hand-eye calibration needs at least.
MIN_POSED_VIEWS = 3
MAX_ORIGIN_STD_MM = 10.0
"""An estimated laser origin less certain than this is reported, not written to the file."""
# A lit printed target is no smooth background: the frames are searched as they are
# (scanner.stripe.background).
_TARGET_FRAMES = StripeOptions(flatten_background=False)
_ORIGIN_PEAKS = StripeOptions(min_relative_peak=0.02, flatten_background=False)


@dataclass(frozen=True)
class Rejection:
    """A frame left out of a calibration stage, and why."""

    frame_id: int
    stage: str
    reason: str

    def to_json(self) -> dict[str, Any]:
        return {"frame_id": self.frame_id, "stage": self.stage, "reason": self.reason}


@dataclass
class CalibrationResult:
    """Everything ``scanner calibrate`` found, and the calibration file it writes.

    Attributes
    ----------
    calibration : Calibration
        The file's content; ``calibration.quality`` is the rich quality record.
    observations : dict of int to TargetObservation
        Detection per frame id (target images only).
    stripes : dict of int to ndarray, shape (N, 2)
        Stripe centres per frame id (laser images only).
    cam_from_target : dict of int to ndarray, shape (4, 4)
        Extrinsics per frame id.
    light_plane : LightPlaneResult or None
        ``None`` for a session without laser images (a camera-only calibration).
    hand_eye : HandEyeResult
    intrinsics : object
        The :class:`calibration.intrinsics.IntrinsicsResult`.
    session : Session
    hand_eye_views : list of PosedView
        The posed views the default hand-eye adjusted (empty for the paper's method), kept so
        that a study can rerun the hand-eye alone.
    laser_origin : LaserOriginResult or None
        The laser origin from the shadow edges; ``None`` without laser images.
    """

    calibration: Calibration
    observations: dict[int, TargetObservation]
    stripes: dict[int, NDArray]
    cam_from_target: dict[int, NDArray]
    light_plane: LightPlaneResult | None
    hand_eye: HandEyeResult
    intrinsics: Any
    session: Session
    hand_eye_views: list[PosedView] = field(default_factory=list)
    rejected: list[Rejection] = field(default_factory=list)
    per_view_rms_px: dict[int, float] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    laser_origin: LaserOriginResult | None = None

    @property
    def quality(self) -> CalibrationQuality:
        return self.calibration.quality


def target_extent_mm(target: TargetSpec) -> tuple[float, float, float, float]:
    """``(xmin, xmax, ymin, ymax)`` of the part of the target known to be flat and printed."""
    if isinstance(target, ConcentricCirclesTarget):
        r = target.radius_mm * 1.05
        return (-r, r, -r, r)
    if isinstance(target, ChessboardTarget):
        cols, rows = target.inner_corners
        s = target.square_mm
        return (-s, cols * s, -s, rows * s)
    pts = target.object_points()
    p = target.pitch_mm
    return (
        float(pts[:, 0].min() - p),
        float(pts[:, 0].max() + p),
        float(pts[:, 1].min() - p),
        float(pts[:, 1].max() + p),
    )


def stripe_pixel_at(
    stripe_px: NDArray, point_px: NDArray, reach_px: float = 30.0
) -> tuple[NDArray, float] | None:
    """The stripe's pixel nearest ``point_px`` and their distance (the stripe's local line).

    A line is fitted to the stripe points within ``reach_px`` of the point and the point is
    projected onto it. None when fewer than 5 stripe points lie that close.
    """
    if len(stripe_px) == 0:
        return None
    d = np.linalg.norm(stripe_px - point_px, axis=1)
    near = stripe_px[d < reach_px]
    if len(near) < 5:
        return None
    c = near.mean(axis=0)
    _, _, vt = np.linalg.svd(near - c)
    direction = vt[0]
    foot = c + direction * float((point_px - c) @ direction)
    return foot, float(np.linalg.norm(point_px - foot))


def _read_aims(session: Session) -> dict[int, str]:
    """The optional ``aim`` column of frames.csv (O, A, C: where the stripe was aimed)."""
    path = session.root / "frames.csv"
    out: dict[int, str] = {}
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            for row in csv.DictReader(fh):
                aim = (row.get("aim") or "").strip().upper()
                if aim:
                    out[int(row["id"])] = aim
    except (OSError, ValueError, KeyError):
        return {}
    return out


def _progress(iterable: Any, enabled: bool, desc: str, total: int | None = None) -> Any:
    if not enabled:
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, desc=desc, total=total, unit="img", leave=False)


def _extract(session: Session, frame: Frame) -> NDArray:

    image, background = session.load_laser_pair(frame)
    prof = extract_stripe(image, mode="precise", background=background, options=_TARGET_FRAMES)
    # Every peak is kept: the light-plane fit keeps, per frame, only the points on the target
    # that lie on one straight line, which drops print edges and reflections.
    return np.column_stack([prof.u, prof.v])


def _detect_one(args: tuple[str, TargetSpec]) -> TargetObservation:

    return detect_target(load_gray_image(args[0]), args[1])


def _detect_all(
    frames: list[Frame],
    target: TargetSpec,
    workers: int,
    check_cancelled: Callable[[], None],
) -> Iterator[TargetObservation]:
    """Detections of the frames' target images, in order (a process pool when workers > 1);
    ``check_cancelled`` after each (:func:`~scanner.core.parallel.process_map`)."""
    jobs = [(str(f.target_image), target) for f in frames]
    return process_map(_detect_one, jobs, workers, chunksize=2, check_cancelled=check_cancelled)


def _paper_plane_views(
    frames: list[Frame],
    observations: dict[int, TargetObservation],
    stripes: dict[int, NDArray],
    max_dist_px: float = 2.0,
) -> list[PaperPlaneView]:
    """Unposed rows whose stripe lies along the diameter A-O-B (the paper's light-plane rows)."""
    views = []
    for f in frames:
        obs = observations.get(f.id)
        st = stripes.get(f.id)
        if f.has_pose or obs is None or not obs or st is None or len(st) < 20:
            continue
        if not all(k in obs.named_px for k in ("A", "O", "B")):
            continue
        snapped = []
        for name in ("A", "O", "B"):
            hit = stripe_pixel_at(st, np.asarray(obs.named_px[name], float))
            if hit is None or hit[1] > max_dist_px:
                break
            snapped.append(hit[0])
        if len(snapped) == 3:
            views.append(PaperPlaneView(f.id, snapped[0], snapped[1], snapped[2]))
    return views


def calibrate_session(
    session: Session,
    method: Literal["default", "paper"] = "default",
    progress: bool = True,
    refine_intrinsics: bool = False,
    on_stage: Callable[[str], None] | None = None,
    observations: dict[int, TargetObservation] | None = None,
    workers: int = 2,
    check_cancelled: Callable[[], None] | None = None,
) -> CalibrationResult:
    """Calibrate intrinsics, light plane and hand-eye from one calibration session.

    Parameters
    ----------
    session : Session
        A ``calibration`` session with a target; unposed rows (target moved by hand) and posed
        rows (target fixed in the base), each with a target image and/or a laser image.
    method : {"default", "paper"}
        ``"paper"`` needs the concentric-circles target.
    progress : bool
        Show progress bars (stderr).
    refine_intrinsics : bool
        Let the hand-eye adjustment refine the intrinsics too.
    on_stage : callable, optional
        Called with the name of each stage as it starts.
    observations : dict of int to TargetObservation, optional
        Detections from an earlier run on the same session (frame id -> observation), to
        skip the detection stage.
    workers : int
        Processes detecting the target in parallel (1: in this process), and threads for the
        distortion model's fold fits.
    check_cancelled : callable, optional
        Called as each stage starts, after each image's detection and each laser frame's
        stripe, before each fold of the intrinsics' distortion-model choice and each re-solve
        of the uncertainty: whatever it raises stops the calibration and comes out of this
        function (a PLC job's cancellation).

    Returns
    -------
    CalibrationResult

    Raises
    ------
    ValueError
        Saying what is missing: wrong session kind, the paper method on a standard target, too
        few target images found, no usable laser frames, degenerate robot motion.
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    if session.kind != "calibration":
        raise ValueError(f"session kind: expected 'calibration', got {session.kind!r}")
    target = session.target
    if target is None:
        raise ValueError("session: a calibration session needs a target")
    if method == "paper" and not isinstance(target, ConcentricCirclesTarget):
        raise ValueError(
            f"method 'paper' needs the concentric-circles target; this session uses a {target.kind} "
            "(use --method default)"
        )
    # What cannot give a file is refused here, before the detection's minutes of work.
    camera_only = not any(f.laser_image is not None for f in session.frames)
    posed_targets = sum(f.has_pose and f.target_image is not None for f in session.frames)
    if posed_targets < MIN_POSED_VIEWS:
        raise ValueError(
            f"hand-eye: expected at least {MIN_POSED_VIEWS} rows with a robot pose and a target "
            f"image, got {posed_targets}"
        )
    if method == "paper" and camera_only:
        raise ValueError(
            "method 'paper' needs laser images (its light plane and hand-eye follow the stripe); "
            "this session has none (the default method gives a camera-only calibration)"
        )
    check = check_cancelled or (lambda: None)
    announce = on_stage or (lambda name: logger.info("stage: %s", name))

    def stage(name: str) -> None:
        check()
        announce(name)

    timings: dict[str, float] = {}
    t0 = time.perf_counter()

    # 1. detection
    stage("detect")
    given = observations or {}
    observations = {}
    rejected: list[Rejection] = []
    with_target = [f for f in session.frames if f.target_image is not None]
    todo = [f for f in with_target if f.id not in given]
    with closing(_detect_all(todo, target, workers, check)) as detections:
        found_now = dict(
            zip([f.id for f in todo], _progress(detections, progress, "detect", len(todo)))
        )
    for f in with_target:
        # A given observation may be a falsy "not found": never fall through on it.
        obs = given[f.id] if f.id in given else found_now[f.id]
        observations[f.id] = obs
        if not obs:
            rejected.append(Rejection(f.id, "detect", obs.reason))
    found = [f for f in with_target if observations[f.id]]
    if not found:
        raise ValueError(f"target not found in any of the {len(with_target)} target images")
    timings["detect_s"] = time.perf_counter() - t0

    # 2. intrinsics
    stage("intrinsics")
    t1 = time.perf_counter()

    intr = calibrate_intrinsics(
        [observations[f.id] for f in found],
        (session.width, session.height),
        method=method,
        target=target,
        check_cancelled=check_cancelled,
        workers=workers,
    )
    for idx, why in intr.rejected:
        rejected.append(Rejection(found[idx].id, "intrinsics", why))
    camera = CameraModel(session.width, session.height, intr.K, intr.dist)
    timings["intrinsics_s"] = time.perf_counter() - t1

    # 3. extrinsics of every view with the target found
    stage("extrinsics")
    t1 = time.perf_counter()
    cam_from_target: dict[int, NDArray] = {}
    extrinsics_q: list[dict[str, Any]] = []
    # The intrinsics adjustment refines every view's pose with all its features (ring edges
    # and diameter lines of the concentric target): better than PnP on the named points.
    intr_pose = {
        found[i].id: np.asarray(p) for i, p in zip(intr.view_indices, intr.cam_from_target)
    }
    intr_pose_cov = {found[i].id: c for i, c in zip(intr.view_indices, intr.pose_covariance)}
    for f in found:
        obs = observations[f.id]
        pose = estimate_pose(obs.points_px, obs.points_target, camera)
        if not pose:
            rejected.append(Rejection(f.id, "extrinsics", pose.reason))
            continue
        cam_from_target[f.id] = intr_pose.get(f.id, pose.cam_from_target)  # type: ignore[arg-type]
        extrinsics_q.append(
            {
                "frame_id": f.id,
                "rms_px": pose.rms_px,
                "std_rotation_deg": pose.std_rotation_deg.tolist(),
                "std_translation_mm": pose.std_translation_mm.tolist(),
            }
        )
    timings["extrinsics_s"] = time.perf_counter() - t1

    # 4. stripes
    stage("stripes")
    t1 = time.perf_counter()
    stripes: dict[int, NDArray] = {}
    with_laser = [f for f in session.frames if f.laser_image is not None]
    for f in _progress(with_laser, progress, "stripes"):
        stripes[f.id] = _extract(session, f)
        check()
    timings["stripes_s"] = time.perf_counter() - t1

    # 5. light plane (none from a session without laser images: a camera-only calibration)
    plane_res: LightPlaneResult | None = None
    origin: LaserOriginResult | None = None
    laser_views: list[LaserView] = []
    plane_paper = None
    skipped: list[dict[str, Any]] = []
    if not camera_only:
        stage("light plane")
        t1 = time.perf_counter()
        extent = target_extent_mm(target)
        along_ink: set[int] = set()
        if isinstance(target, ConcentricCirclesTarget):
            pviews = _paper_plane_views(session.frames, observations, stripes)
            plane_paper = paper_light_plane(pviews, camera, target.radius_mm)
            # A stripe lying along a printed diameter line runs on ink its whole length, which
            # biases its centre: those rows serve the paper's method, not the default fit.
            along_ink = {v.frame_id for v in pviews}
        laser_views = [
            LaserView(f.id, stripes[f.id], cam_from_target[f.id], extent)
            for f in with_laser
            if f.id in cam_from_target and len(stripes[f.id]) and f.id not in along_ink
        ]
        plane_default = calibrate_light_plane(laser_views, camera)
        skipped = [
            {
                "frame_id": i,
                "reason": "stripe along a printed diameter line (paper light-plane row)",
            }
            for i in sorted(along_ink)
        ]
        plane_res = plane_paper if method == "paper" else plane_default
        if plane_res is None or not plane_res:
            why = plane_res.reason if plane_res is not None else "no light-plane views"
            raise ValueError(f"light plane ({method}): {why}")
        for r in plane_res.rejected:
            rejected.append(Rejection(int(r["frame_id"]), "light plane", r["reason"]))
        timings["light_plane_s"] = time.perf_counter() - t1

        stage("laser origin")
        t1 = time.perf_counter()
        origin = _laser_origin(session, with_laser, camera, plane_res.plane)  # type: ignore[arg-type]
        timings["laser_origin_s"] = time.perf_counter() - t1

    # 6. hand-eye
    stage("hand-eye")
    t1 = time.perf_counter()
    posed = [f for f in found if f.has_pose and f.id in cam_from_target]
    # Views labelled up to the target's symmetry (no marker seen) wait until the uniquely
    # labelled ones give a first hand-eye, which resolves their labelling.
    pending = [f for f in posed if observations[f.id].labelling == "symmetry"]
    posed = [f for f in posed if observations[f.id].labelling != "symmetry"]
    views: list[PosedView] = []
    labelling: dict[str, Any] = {
        "symmetry": sorted(f.id for f in found if observations[f.id].labelling == "symmetry"),
        "resolved": {},
        "unresolved": {},
    }
    if method == "paper":
        he = _paper_hand_eye(session, posed, observations, stripes, camera, plane_res, target)  # type: ignore[arg-type]
    else:
        pp_std = (intr.std["cx"], intr.std["cy"]) if {"cx", "cy"} <= intr.std.keys() else None

        def hand_eye(frames: list[Frame]) -> tuple[HandEyeResult, list[PosedView]]:
            views: list[PosedView] = []
            for f in frames:
                obs = observations[f.id]
                px, pose_cov = obs.points_px, None
                if isinstance(target, ConcentricCirclesTarget) and f.id in intr_pose_cov:
                    # The concentric target's few named points are noisier than the view's
                    # pose from the intrinsics adjustment (every ring edge and line point):
                    # the hand-eye sees the features where that pose puts them, with that
                    # pose's covariance (their PnP residuals are nil). Where the adjustment
                    # gave no covariance the detected points stay, for honest PnP residuals.
                    px = project_target(camera, intr_pose[f.id], obs.points_target)
                    pose_cov = intr_pose_cov[f.id]
                views.append(
                    PosedView(
                        f.id,
                        f.base_from_flange,
                        px,
                        obs.points_target,
                        cam_from_target[f.id],
                        pose_cov,
                    )  # type: ignore[arg-type]
                )
            result = calibrate_hand_eye(
                views,
                camera,
                "default",
                refine_intrinsics=refine_intrinsics,
                principal_point_std_px=pp_std,
            )
            return result, views

        he, views = hand_eye(posed)
        if he and pending:
            resolved = []
            for f in pending:
                predicted = (
                    np.linalg.inv(f.base_from_flange @ he.flange_from_cam) @ he.base_from_target
                )  # type: ignore[operator]
                q = resolve_quarter_turns(cam_from_target[f.id], predicted)
                if not q:
                    labelling["unresolved"][str(f.id)] = q.reason
                    rejected.append(Rejection(f.id, "hand-eye", f"no marker, {q.reason}"))
                    continue
                labelling["resolved"][str(f.id)] = {
                    "quarter_turns": q.quarter_turns,
                    "angle_deg": q.angle_deg,
                }
                observations[f.id] = relabel(observations[f.id], q.quarter_turns)  # type: ignore[arg-type]
                cam_from_target[f.id] = cam_from_target[f.id] @ turn(q.quarter_turns)  # type: ignore[arg-type]
                if f.id in intr_pose:  # its covariance, in the camera's turns, stays
                    intr_pose[f.id] = intr_pose[f.id] @ turn(q.quarter_turns)  # type: ignore[arg-type]
                resolved.append(f)
            if resolved:
                posed = sorted(posed + resolved, key=lambda f: f.id)
                he, views = hand_eye(posed)
    if method == "paper" or not he:
        why = (
            "the paper's hand-eye needs the marker"
            if method == "paper"
            else "no first hand-eye from uniquely labelled views"
        )
        for f in pending:
            if str(f.id) not in labelling["resolved"] and str(f.id) not in labelling["unresolved"]:
                labelling["unresolved"][str(f.id)] = why
                rejected.append(Rejection(f.id, "hand-eye", f"no marker, {why}"))
    if not he:
        raise ValueError(f"hand-eye ({method}): {he.reason}")
    if he.camera is not None and refine_intrinsics:
        camera = he.camera
    timings["hand_eye_s"] = time.perf_counter() - t1

    # 7. the joint uncertainty the file carries (the default method's chain only)
    covariance = None
    covariance_warnings: list[str] = []
    if method == "default":
        stage("uncertainty")
        t1 = time.perf_counter()
        plane_frames = set() if plane_res is None else {p["frame_id"] for p in plane_res.per_frame}
        try:
            covariance = estimate_covariance(
                camera,
                intr,
                {
                    f.id: (observations[f.id].points_px, observations[f.id].points_target)
                    for f in found
                    if f.id in cam_from_target
                },
                [v for v in laser_views if v.frame_id in plane_frames],
                plane_res,
                views,
                he,
                check_cancelled=check_cancelled,
            )
        except (ValueError, np.linalg.LinAlgError) as exc:
            # optional: the calibration stands without it, and says so
            covariance_warnings.append(f"no covariance estimated: {exc}")
        timings["uncertainty_s"] = time.perf_counter() - t1
    timings["total_s"] = time.perf_counter() - t0

    warnings = list(intr.warnings) + list(he.warnings) + covariance_warnings
    verdict, check = _verdict(intr, plane_res, he, rejected)
    per_view = {found[i].id: float(r) for i, r in zip(intr.view_indices, intr.per_view_rms_px)}
    quality: dict[str, Any] = {
        "method": method,
        "verdict": verdict,
        "check_frames": check,
        "target_kind": target.kind,
        "frames": len(session.frames),
        "intrinsics": {
            "method": intr.method,
            "rms_px": float(intr.rms_px),
            "std": {k: float(v) for k, v in intr.std.items()},
            "per_view_rms_px": {str(k): v for k, v in per_view.items()},
            **{
                k: v
                for k, v in intr.quality().items()
                if k in ("distortion_model", "model_selection", "projection_uncertainty_px")
            },
        },
        "extrinsics": extrinsics_q,
        "labelling": labelling,
        "light_plane": None if plane_res is None else plane_res.quality(),
        "laser_origin": None if origin is None else origin.quality(),
        "hand_eye": he.quality(),
        "rejected": [r.to_json() for r in rejected],
        "skipped": skipped if method == "default" else [],
        "warnings": warnings,
        "timings": timings,
    }
    if method == "default" and plane_paper is not None and plane_paper:
        quality["light_plane_paper"] = {
            "normal": plane_paper.plane.normal.tolist(),  # type: ignore[union-attr]
            "d": plane_paper.plane.d,  # type: ignore[union-attr]
            "rms_mm": plane_paper.rms_mm,
        }
    written_origin = origin if origin is not None and origin.std_mm <= MAX_ORIGIN_STD_MM else None
    if covariance is not None and written_origin is not None:
        covariance = replace(covariance, laser_origin_mm2=written_origin.covariance_mm2)
    calib = Calibration(
        width=session.width,
        height=session.height,
        K=camera.K,
        dist=camera.dist,
        light_plane=None if plane_res is None else plane_res.plane,
        flange_from_cam=he.flange_from_cam,  # type: ignore[arg-type]
        laser_origin_cam=None if written_origin is None else written_origin.origin_cam,
        quality=quality,
        covariance=covariance,
    )
    return CalibrationResult(
        calib,
        observations,
        stripes,
        cam_from_target,
        plane_res,
        he,
        intr,
        session,
        hand_eye_views=views,
        rejected=rejected,
        per_view_rms_px=per_view,
        timings=timings,
        laser_origin=origin,
    )


def _laser_origin(
    session: Session, frames: list[Frame], camera: CameraModel, plane: LightPlane
) -> LaserOriginResult:
    """The laser origin from the shadow edges in every laser frame (:mod:`calibration.laser_origin`).

    The frames are read again with a low threshold for further peaks on a scan line: a faint
    stripe on the background sharing columns with the bright one on the target is kept, so
    that a stretch ends where the light ends, not where a brighter one starts.
    """
    lines = []
    for f in frames:
        image, background = session.load_laser_pair(f)
        prof = extract_stripe(image, mode="precise", background=background, options=_ORIGIN_PEAKS)
        lines += shadow_lines(prof.uv, camera, plane, f.id, prof.contrast)
    return estimate_laser_origin(lines, plane)


def _paper_hand_eye(
    session: Session,
    posed: list[Frame],
    observations: dict[int, TargetObservation],
    stripes: dict[int, NDArray],
    camera: CameraModel,
    plane: LightPlaneResult,
    target: ConcentricCirclesTarget,
    max_dist_px: float = 3.0,
) -> HandEyeResult:
    """Collect the views with the stripe on O, A, C and run :func:`paper_hand_eye`."""
    aims = _read_aims(session)
    lp = plane.plane
    if lp is None:
        return HandEyeResult(False, "paper hand-eye: no light plane", method="paper")
    views: list[StripePointView] = []
    sources: list[str] = []  # how each view's reference pose was found ("": none)
    for f in posed:
        obs = observations[f.id]
        st = stripes.get(f.id)
        if st is None:
            continue
        candidates = [aims[f.id]] if f.id in aims else ["O", "A", "C"]
        best = None
        for name in candidates:
            if name not in obs.named_px:
                continue
            hit = stripe_pixel_at(st, np.asarray(obs.named_px[name], float))
            if hit is not None and hit[1] <= max_dist_px and (best is None or hit[1] < best[2]):
                best = (name, hit[0], hit[1])
        if best is None:
            continue
        name, px, _ = best
        p_cam = intersect_rays_with_plane(camera.rays(px.reshape(1, 2)), lp.normal, lp.d)[0]
        if not np.all(np.isfinite(p_cam)):
            continue
        ct, source = _paper_reference_pose(obs, camera, px, lp) if name == "O" else (None, "")
        views.append(StripePointView(f.id, name, f.base_from_flange, p_cam, ct))  # type: ignore[arg-type]
        sources.append(source)
    ref = _choose_paper_reference(views, sources)
    he = paper_hand_eye(views, target.radius_mm)
    if he and ref is not None and sources[ref] == "all_rings":
        he.warnings.append(
            f"the reference view aimed at O (frame {views[ref].frame_id}) does not show both ends "
            "of both diameters: its vanishing points come from every ring's ends along them"
        )
    return he


def _choose_paper_reference(views: list[StripePointView], sources: list[str]) -> int | None:
    """Index of the view whose pose :func:`paper_hand_eye` takes as the paper's T_cwO (the
    first view with a ``cam_from_target``), or None.

    The paper's own reference (``sources[i] == "diameter_ends"``: the largest ring's ends in
    view) is taken wherever a view gives one: the poses of the views whose vanishing points
    came from every ring's ends (``"all_rings"``) are then dropped (set to None, in place).
    """
    if "diameter_ends" in sources:
        for v, source in zip(views, sources, strict=True):
            if source != "diameter_ends":
                v.cam_from_target = None
    return next((i for i, v in enumerate(views) if v.cam_from_target is not None), None)


def _paper_reference_pose(
    obs: TargetObservation, camera: CameraModel, stripe_o_px: NDArray, plane: LightPlane
) -> tuple[NDArray | None, str]:
    """The paper's ``T_cwO`` of a view with the stripe on O (:func:`paper_pose`), and which
    rings gave it.

    Parameters
    ----------
    obs : TargetObservation
        The view's concentric-target observation.
    camera : CameraModel
    stripe_o_px : ndarray, shape (2,)
        The stripe's pixel on O.
    plane : LightPlane
        The light plane, camera frame.

    Returns
    -------
    ndarray, shape (4, 4), or None; and str
        ``cam_from_target`` and ``"diameter_ends"`` (the paper's: A, B, C and D in view) or
        ``"all_rings"`` (:func:`view_vanishing_points`; and, for the sign of an axis whose
        end A or C is missing, the outermost ring end found on that diameter); ``(None, "")``
        where the view gives no pose.
    """
    vps = view_vanishing_points(obs)
    if vps is None or "O" not in obs.named_px:
        return None, ""
    p, q, source = vps
    ends = []
    for name, col in (("A", 0), ("C", 1)):
        if name in obs.named_px:
            ends.append(np.asarray(obs.named_px[name], dtype=np.float64))
            continue
        # The outermost point found on the axis; one on its negative half (the stripe may
        # hide the positive one) mirrored through O, which keeps it on the same image line.
        along = obs.points_target[:, col]
        on_axis = (np.abs(obs.points_target[:, 1 - col]) < 1e-9) & (along != 0)
        if not on_axis.any():
            return None, ""
        far = np.flatnonzero(on_axis)[np.argmax(np.abs(along[on_axis]))]
        o_px = np.asarray(obs.named_px["O"], dtype=np.float64)
        ends.append(obs.points_px[far] if along[far] > 0 else 2 * o_px - obs.points_px[far])
        source = "all_rings"
    pose = paper_pose(camera, p, q, obs.named_px["O"], ends[0], ends[1], stripe_o_px, plane)
    return (pose.cam_from_target, source) if pose else (None, "")


def _verdict(
    intr: Any, plane: LightPlaneResult | None, he: HandEyeResult, rejected: list[Rejection]
) -> tuple[str, list[int]]:
    """``"good"`` or ``"check these frames: ..."`` with the frames to look at."""
    check: set[int] = {r.frame_id for r in rejected}
    rms = [p["rms_px"] for p in he.per_pose if "rms_px" in p]
    if rms:
        med = float(np.median(rms))
        check |= {int(p["frame_id"]) for p in he.per_pose if p.get("rms_px", 0) > max(3 * med, 1.0)}
    per = [p["rms_mm"] for p in plane.per_frame] if plane is not None else []
    if per:
        med = float(np.median(per))
        check |= {int(p["frame_id"]) for p in plane.per_frame if p["rms_mm"] > max(3 * med, 0.05)}
    if not check:
        return "good", []
    ids = sorted(check)
    return "check these frames: " + ", ".join(str(i) for i in ids), ids
