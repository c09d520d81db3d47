"""Sweep sessions to a stitched cloud on disk: the ``scanner scan`` job.

Frames stream through worker threads in chunks (decoding and the stripe kernels release the
GIL); each chunk's stripe profiles are saved as one ``.npz`` under a work folder named after a
hash of the sessions, the calibration and the extraction options, so an interrupted run
resumes where it stopped. The profiles are then triangulated in one batch (pixels to base
frame), stitched into an Open3D tensor cloud with per-point ``intensity``, ``width_px``,
``flags``, ``frame_id``, ``sweep_id`` and written atomically.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from scanner.core.fileio import InputError, atomic_output
from scanner.core.images import load_laser_images
from scanner.core.parallel import thread_pool
from scanner.formats.calibration_file import Calibration, read_calibration
from scanner.formats.clouds import _check_format, write_cloud
from scanner.formats.session import Frame, Session, read_session
from scanner.scanning.stitch import build_cloud, filter_cloud, incidence_cosines, refine_sweeps
from scanner.scanning.triangulate import Triangulator
from scanner.stripe.background import take_out_uneven_background, wants_flattening
from scanner.stripe.extract import (
    MODES,
    StripeFlag,
    StripeOptions,
    auto_half_window,
    estimate_noise,
    extract_stripe,
    orientation_from_calibration,
)

__all__ = [
    "ScanOptions",
    "ScanResult",
    "check_scan_inputs",
    "flag_counts",
    "scan_profiles",
    "scan_session",
]

log = logging.getLogger(__name__)

_PROFILE_KEYS = ("u", "v", "intensity", "width_px", "flags", "line")


@dataclass(frozen=True)
class ScanOptions:
    """What ``scan_session`` does between frames and cloud.

    Attributes
    ----------
    mode : {"fast", "precise"}
        Stripe estimator.
    orientation : {"calibration", "auto", "rows", "cols"}
        Scan-line direction: from the light plane's image (default), the image, or fixed.
    stripe : StripeOptions
        Thresholds and windows of the extractor.
    use_laser_off : bool
        Subtract a frame's ``laser_image_off`` when the session gives one.
    voxel_mm : float or None
        Voxel downsampling of the final cloud.
    outlier_neighbors, outlier_std_ratio
        Statistical outlier removal (0 neighbours: off).
    keep_flagged : bool
        Keep the flagged points (saturated, ambiguous, low contrast, border, secondary,
        grazing, stretch end) in the cloud, with their ``flags``; by default the cloud holds only
        trusted points (``flags == 0``), so that any tool that opens it sees those only.
    max_incidence_deg : float or None
        Flag points whose surface (normal from the cloud) is seen, or lit when
        ``laser_origin_mm`` is given, more obliquely than this. Grazing stripes are wide, dim
        and skewed and their centres biased; on a sphere those points sit at the rim of the
        cap, where they bias the fitted radius most. ``None``: keep every point.
    laser_origin_mm : (float, float, float) or None
        Where the laser fan is emitted, camera frame, mm (the sensor's drawing); enables the
        illumination angle. The cloud carries ``cos_view`` and ``cos_laser`` whenever
        ``max_incidence_deg`` is set.
    incidence_radius_mm : float
        Neighbourhood radius of the normals behind the incidence angles.
    normals_radius_mm : float or None
        Estimate normals with this search radius.
    isolated_radius_mm : float or None
        Points with fewer than ``isolated_min_neighbors`` others within this radius are left
        out (single strays far from any surface); ``None``: off.
    table_z_mm : float or None
        Height of the table a part stands on (base frame): its points are left out, before
        the sweeps are refined against each other. The cut is the table's own measured level
        plus five robust sigmas of its points' heights (at least 0.5 mm above ``table_z_mm``),
        so a sensor that sees the table noisier or offset still loses all of it.
    region_mm : ((x, y, z), (x, y, z)) or None
        Lower and upper corners of a base-frame box: points outside it are left out (a job
        that knows where its part stands ignores the rest of the cell).
    icp : bool
        Refine overlapping sweeps against each other (reports the corrections).
    icp_max_distance_mm, icp_warn_translation_mm, icp_warn_rotation_deg
        ICP correspondence distance and the corrections that trigger a warning.
    workers : int
        Worker threads for the extraction (1: in the calling thread).
    chunk_frames : int
        Frames per saved chunk (the unit of resumption).
    """

    mode: str = "fast"
    orientation: str = "calibration"
    stripe: StripeOptions = field(default_factory=StripeOptions)
    use_laser_off: bool = True
    voxel_mm: float | None = None
    outlier_neighbors: int = 0
    outlier_std_ratio: float = 2.0
    keep_flagged: bool = False
    max_incidence_deg: float | None = None
    laser_origin_mm: tuple[float, float, float] | None = None
    incidence_radius_mm: float = 1.5
    normals_radius_mm: float | None = None
    isolated_radius_mm: float | None = None
    isolated_min_neighbors: int = 3
    table_z_mm: float | None = None
    region_mm: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    icp: bool = False
    icp_max_distance_mm: float = 1.0
    icp_warn_translation_mm: float = 0.2
    icp_warn_rotation_deg: float = 0.1
    workers: int = 2
    chunk_frames: int = 32

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode: expected one of {', '.join(MODES)}, got {self.mode!r}")
        if self.orientation not in ("calibration", "auto", "rows", "cols"):
            raise ValueError(
                f"orientation: expected calibration, auto, rows or cols, got {self.orientation!r}"
            )
        if self.voxel_mm is not None and self.voxel_mm < 0:
            raise ValueError(f"voxel_mm: expected >= 0, got {self.voxel_mm}")
        if self.voxel_mm and self.keep_flagged:
            # A voxel averages its points' attributes: flag bits would mix into wrong ones.
            raise ValueError("voxel_mm with keep_flagged: a voxel cannot keep its points' flags")
        if self.max_incidence_deg is not None and not 0 < self.max_incidence_deg <= 90:
            raise ValueError(
                f"max_incidence_deg: expected 0 < angle <= 90, got {self.max_incidence_deg}"
            )
        if self.laser_origin_mm is not None and len(self.laser_origin_mm) != 3:
            raise ValueError(f"laser_origin_mm: expected (x, y, z), got {self.laser_origin_mm!r}")
        if self.incidence_radius_mm <= 0:
            raise ValueError(f"incidence_radius_mm: expected > 0, got {self.incidence_radius_mm}")
        if self.workers < 1 or self.chunk_frames < 1:
            raise ValueError(
                f"workers, chunk_frames: expected >= 1, got {self.workers}, {self.chunk_frames}"
            )

    def extraction_key(self) -> dict[str, Any]:
        """The options that change the saved profiles (part of the work-folder hash)."""
        return {
            "mode": self.mode,
            "orientation": self.orientation,
            "stripe": asdict(self.stripe),
            "use_laser_off": self.use_laser_off,
        }


@dataclass
class ScanResult:
    """What a scan produced, for the command line's summary and for callers."""

    out_path: Path | None
    n_points: int
    n_frames: int
    n_sweeps: int
    seconds: float
    cloud: Any  # open3d.t.geometry.PointCloud
    corrections: list = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    chunks_resumed: int = 0
    frames_without_stripe: int = 0
    timings: dict[str, float] = field(default_factory=dict)
    removed: dict[str, int] = field(default_factory=dict)
    """Points left out of the cloud per flag (a point may count under several)."""


# --------------------------------------------------------------------------------------------
# inputs


def _as_sessions(session_or_sessions: Any) -> list[Session]:
    items = (
        list(session_or_sessions)
        if isinstance(session_or_sessions, (list, tuple))
        else [session_or_sessions]
    )
    if not items:
        raise ValueError("sessions: expected at least one sweep session, got none")
    out = []
    for item in items:
        out.append(item if isinstance(item, Session) else read_session(item, check_images=True))
    return out


def check_scan_inputs(sessions: Sequence[Session], calibration: Calibration) -> None:
    """Refuse what cannot give a cloud, before any work, with a one-line reason.

    Raises
    ------
    InputError
        A session that is not a sweep, a frame without a pose or laser image, or an image
        size other than the calibration's.
    """
    for s in sessions:
        where = s.root / "session.json"
        if s.kind != "sweep":
            raise InputError(where, f"kind: expected 'sweep' for scanning, got {s.kind!r}")
        if (s.width, s.height) != (calibration.width, calibration.height):
            raise InputError(
                where,
                f"camera: images are {s.width}x{s.height}, the calibration is for "
                f"{calibration.width}x{calibration.height}",
            )
        for f in s.frames:
            if f.base_from_flange is None:
                raise InputError(
                    s.root / "frames.csv", f"frame {f.id}: a sweep frame needs a robot pose"
                )
            if f.laser_image is None:
                raise InputError(s.root / "frames.csv", f"frame {f.id}: no laser_image")


def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _work_key(sessions: Sequence[Session], calibration: Calibration, options: ScanOptions) -> str:
    h = hashlib.sha256()
    for s in sessions:
        h.update(str(s.root.resolve()).encode())
        for name in ("session.json", "frames.csv"):
            p = s.root / name
            if p.is_file():
                h.update(_file_digest(p).encode())
    h.update(json.dumps(calibration.to_json(), sort_keys=True, default=str).encode())
    h.update(json.dumps(options.extraction_key(), sort_keys=True, default=str).encode())
    return h.hexdigest()


# --------------------------------------------------------------------------------------------
# extraction (workers)


@dataclass(frozen=True)
class _FrameJob:
    index: int  # position in the global frame list
    laser_image: str
    laser_off_image: str | None


@dataclass(frozen=True)
class _ChunkJob:
    chunk: int
    path: str
    frames: tuple[_FrameJob, ...]
    mode: str
    orientation: str
    stripe: StripeOptions
    key: str


def _extract_chunk(job: _ChunkJob) -> tuple[int, int, int]:
    """Worker: extract every frame of a chunk and save the profiles. Returns (chunk, points, empty)."""
    parts: dict[str, list[NDArray]] = {k: [] for k in (*_PROFILE_KEYS, "frame")}
    empty = 0
    for fj in job.frames:
        image, background = load_laser_images(fj.laser_image, fj.laser_off_image)
        prof = extract_stripe(
            image,
            mode=job.mode,
            orientation=job.orientation,
            background=background,
            options=job.stripe,
        )
        if len(prof) == 0:
            empty += 1
        for k in _PROFILE_KEYS:
            parts[k].append(getattr(prof, k))
        parts["frame"].append(np.full(len(prof), fj.index, np.int32))
    arrays = {k: np.concatenate(v) for k, v in parts.items()}
    with atomic_output(job.path, suffix=".npz") as tmp:
        np.savez(tmp, key=np.array(job.key), **arrays)
    return job.chunk, int(arrays["u"].size), empty


def _pool(workers: int) -> Executor:
    """Worker threads: a frame's decoding and its stripe kernels run without the GIL, and
    threads start at once where spawned processes take a second (see
    :mod:`scanner.core.parallel`)."""
    return thread_pool(workers)


def _load_chunk(path: Path, key: str) -> dict[str, NDArray] | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
            return {k: z[k] for k in (*_PROFILE_KEYS, "frame")}
    except (OSError, ValueError, KeyError, EOFError):
        return None


def _sweep_stripe_options(
    frames: Sequence[Frame], options: ScanOptions, orientation: str, probes: int = 5
) -> StripeOptions:
    """Fix the centre-of-gravity window, the noise level and whether an uneven background is
    taken out once for the scan, from a few frames spread over it (all its sessions).

    One window keeps the estimator identical from frame to frame. The background is taken
    out of every frame without a laser-off frame where any probe's is uneven
    (:func:`scanner.stripe.background.background_is_uneven`), before the probes' window and
    noise are measured."""
    stripe = options.stripe
    fixed = stripe.half_window_px is not None and stripe.noise is not None
    if (fixed and stripe.flatten_background is not None) or not frames:
        return stripe
    step = max(1, len(frames) // probes)
    loaded = []  # (frame as searched, whether it has no laser-off frame)
    for f in frames[::step][:probes]:
        off_path = f.laser_off_image if options.use_laser_off else None
        img, off = load_laser_images(f.laser_image, off_path)  # type: ignore[arg-type]
        loaded.append((img, True) if off is None else (cv2.subtract(img, off), False))
    flatten = stripe.flatten_background
    if flatten is None:
        flatten = any(wants_flattening(img, stripe) for img, bare in loaded if bare)
    decided = replace(stripe, flatten_background=flatten)
    windows, noises = [], []
    for img, bare in loaded:
        if bare:
            img, _ = take_out_uneven_background(img, decided)
        work = img if orientation == "rows" else cv2.transpose(img)
        noise = estimate_noise(work)
        noises.append(noise)
        windows.append(auto_half_window(work, noise))
    hw = stripe.half_window_px if stripe.half_window_px is not None else int(np.median(windows))
    noise = stripe.noise if stripe.noise is not None else float(np.median(noises))
    log.info(
        "sweep constants: half-window %d px, noise %.2f, background %s (from %d frames)",
        hw,
        noise,
        "taken out" if flatten else "as it is",
        len(noises),
    )
    return replace(stripe, half_window_px=hw, noise=noise, flatten_background=flatten)


def _resolve_orientation(options: ScanOptions, calibration: Calibration) -> str:
    if options.orientation == "calibration":
        return orientation_from_calibration(calibration)
    return options.orientation


def scan_profiles(
    frames: Sequence[Frame],
    calibration: Calibration,
    options: ScanOptions,
    work_dir: Path,
    key: str,
    progress: bool = True,
    check_cancelled: Callable[[], None] | None = None,
) -> tuple[dict[str, NDArray], int, int]:
    """Stripe profiles of ``frames`` (resuming saved chunks), concatenated.

    ``check_cancelled`` is called after each chunk: whatever it raises stops the extraction
    (the chunks not started are dropped, the running ones finish) and goes to the caller.

    Returns
    -------
    profiles : dict of ndarray
        ``u, v, intensity, width_px, flags, line`` and ``frame`` (index into ``frames``).
    chunks_resumed, frames_without_stripe : int
    """
    work_dir.mkdir(parents=True, exist_ok=True)
    orientation = _resolve_orientation(options, calibration)
    stripe_options = _sweep_stripe_options(frames, options, orientation)
    n = len(frames)
    size = options.chunk_frames
    jobs: list[_ChunkJob] = []
    loaded: dict[int, dict[str, NDArray]] = {}
    for c, start in enumerate(range(0, n, size)):
        path = work_dir / f"chunk_{c:05d}.npz"
        if path.is_file():
            arrays = _load_chunk(path, key)
            if arrays is not None:
                loaded[c] = arrays
                continue
        fjobs = tuple(
            _FrameJob(
                i,
                str(frames[i].laser_image),
                str(frames[i].laser_off_image)
                if options.use_laser_off and frames[i].laser_off_image is not None
                else None,
            )
            for i in range(start, min(n, start + size))
        )
        jobs.append(_ChunkJob(c, str(path), fjobs, options.mode, orientation, stripe_options, key))
    resumed = len(loaded)
    if resumed:
        log.info(
            "resuming: %d of %d chunks already extracted in %s",
            resumed,
            resumed + len(jobs),
            work_dir,
        )

    empty = 0
    bar = None
    if progress:
        from tqdm import tqdm

        done = sum(min(size, n - c * size) for c in loaded)
        bar = tqdm(total=n, initial=done, unit="frame", desc="stripes", leave=False)
    try:
        if options.workers > 1 and len(jobs) > 1:
            pool = _pool(options.workers)
            try:
                for c, _, e in pool.map(_extract_chunk, jobs):
                    empty += e
                    if bar is not None:
                        bar.update(min(size, n - c * size))
                    if check_cancelled is not None:
                        check_cancelled()
            finally:
                # On an error, a cancellation or an interrupt: the queued chunks are dropped
                # (threads cannot be killed; they finish the chunk they are on).
                pool.shutdown(wait=True, cancel_futures=True)
        else:
            for job in jobs:
                c, _, e = _extract_chunk(job)
                empty += e
                if bar is not None:
                    bar.update(min(size, n - c * size))
                if check_cancelled is not None:
                    check_cancelled()
    finally:
        if bar is not None:
            bar.close()
    for job in jobs:
        arrays = _load_chunk(Path(job.path), key)
        if arrays is None:  # pragma: no cover - just written
            raise OSError(f"{job.path}: chunk written but not readable")
        loaded[job.chunk] = arrays
    ordered = [loaded[c] for c in sorted(loaded)]
    profiles = {k: np.concatenate([a[k] for a in ordered]) for k in (*_PROFILE_KEYS, "frame")}
    if resumed:
        # Frames of resumed chunks without any point count as empty too.
        have = np.zeros(n, bool)
        have[profiles["frame"]] = True
        empty = int(n - np.count_nonzero(have))
    return profiles, resumed, empty


# --------------------------------------------------------------------------------------------
# the job


def _limit_incidence(
    points: NDArray,
    attributes: dict[str, NDArray],
    frame_pos: NDArray,
    base_from_cam: NDArray,
    options: ScanOptions,
) -> tuple[NDArray, dict[str, NDArray]]:
    """Add ``cos_view``, ``cos_laser`` and flag the points seen or lit beyond the limit
    (:attr:`StripeFlag.GRAZING`).

    Points without a normal (isolated) are not flagged: nothing says they are grazing.
    """

    cos_view, cos_laser = incidence_cosines(
        points, frame_pos, base_from_cam, options.laser_origin_mm, options.incidence_radius_mm
    )
    limit = np.cos(np.radians(float(options.max_incidence_deg)))  # type: ignore[arg-type]
    grazing = (cos_view < limit) | (cos_laser < limit)  # NaN compares False: kept
    log.info(
        "incidence limit %.0f deg: %d of %d points grazing (%s)",
        options.max_incidence_deg,
        np.count_nonzero(grazing),
        len(points),
        "view and laser" if options.laser_origin_mm is not None else "view only",
    )
    attributes = dict(attributes)
    attributes["flags"] = attributes["flags"] | np.where(grazing, StripeFlag.GRAZING, 0).astype(
        np.uint8
    )
    attributes["cos_view"] = cos_view.astype(np.float32)
    attributes["cos_laser"] = cos_laser.astype(np.float32)
    return points, attributes


def flag_counts(flags: NDArray) -> dict[str, int]:
    """How many points carry each :class:`StripeFlag` (a point may carry several)."""
    return {
        f.name.lower(): int(np.count_nonzero(flags & f.value))
        for f in StripeFlag
        if f.value and np.any(flags & f.value)
    }


def _drop_flagged(
    points: NDArray, attributes: dict[str, NDArray]
) -> tuple[NDArray, dict[str, NDArray], dict[str, int]]:
    """Only the points without any flag, and how many each reason removed."""
    flags = attributes["flags"]
    flagged = flags != 0
    removed = flag_counts(flags[flagged])
    keep = ~flagged
    return points[keep], {k: v[keep] for k, v in attributes.items()}, removed


#: Heights within this of the given table level are taken as the table's candidates.
_TABLE_BAND_MM = 3.0


def table_cut_mm(z_mm: NDArray, table_z_mm: float) -> float:
    """Height below which points are the table: its measured level (median of the heights
    within 3 mm of ``table_z_mm``) plus five robust sigmas (1.4826 MAD), at least 0.5 mm
    above ``table_z_mm``."""
    near = z_mm[np.abs(z_mm - table_z_mm) < _TABLE_BAND_MM]
    floor = table_z_mm + 0.5
    if len(near) < 50:
        return floor
    level = float(np.median(near))
    sigma = 1.4826 * float(np.median(np.abs(near - level)))
    return max(floor, level + 5.0 * sigma)


def scan_session(
    session_or_sessions: Any,
    calibration: Calibration | str | os.PathLike[str],
    options: ScanOptions | None = None,
    out_path: str | os.PathLike[str] | None = None,
    work_dir: str | os.PathLike[str] | None = None,
    progress: bool = True,
    keep_work: bool | None = None,
    calibration_path: str | os.PathLike[str] | None = None,
    check_cancelled: Callable[[], None] | None = None,
) -> ScanResult:
    """Scan one or several sweep sessions into one base-frame cloud (mm), written to ``out_path``.

    Parameters
    ----------
    session_or_sessions : Session, path, or a list of them
        Sweep sessions; frames carrying a ``sweep`` column split a session into sweeps.
    calibration : Calibration or path
    options : ScanOptions, optional
    out_path : path, optional
        ``.ply`` (binary), ``.pcd`` or ``.e57``; ``None``: return the cloud without writing.
    work_dir : path, optional
        Where the per-chunk profiles go (a sub-folder per input hash). Default: a hidden folder
        beside ``out_path`` (or the system's temporary folder), removed after success.
    progress : bool
        tqdm progress bar on standard error.
    keep_work : bool, optional
        Keep the saved profiles after success (default: keep only when ``work_dir`` is given).
    calibration_path : path, optional
        The file ``calibration`` was read from, for the cloud's provenance (a path given as
        ``calibration`` is recorded by itself).
    check_cancelled : callable, optional
        Called after each chunk of frames is extracted, after the triangulation and after
        the sweeps' ICP; what it raises stops the scan.

    Returns
    -------
    ScanResult

    Raises
    ------
    InputError
        Bad input, before any extraction (see :func:`check_scan_inputs`); or, after it, a
        sweep that leaves no point to keep (none found, all flagged or filtered out), before
        anything is written.
    """

    t0 = time.perf_counter()
    options = options or ScanOptions()
    cal_path = None if calibration_path is None else Path(calibration_path)
    if not isinstance(calibration, Calibration):
        cal_path = Path(calibration)
        calibration = read_calibration(cal_path)
    sessions = _as_sessions(session_or_sessions)
    check_scan_inputs(sessions, calibration)
    if out_path is not None:
        _check_format(Path(out_path))

    # Global frame list and sweep ids: (session, sweep column) pairs numbered in order.
    frames: list[Frame] = []
    sweep_of: list[int] = []
    sweep_ids: dict[tuple[int, int], int] = {}
    for si, s in enumerate(sessions):
        for f in s.frames:
            sweep_of.append(sweep_ids.setdefault((si, f.sweep), len(sweep_ids)))
            frames.append(f)
    key = _work_key(sessions, calibration, options)
    if keep_work is None:
        keep_work = work_dir is not None
    if work_dir is None:
        base = (
            Path(out_path).parent
            if out_path is not None
            else Path(os.environ.get("TMPDIR", "/tmp"))
        )
        work_root = base / ".scanner-work"
    else:
        work_root = Path(work_dir)
    chunk_dir = work_root / key[:16]

    # The saved profiles go with the run unless kept on purpose (--workdir): after success,
    # and after a failure too, so that a failed run leaves no work folder behind.
    try:
        t1 = time.perf_counter()
        profiles, resumed, empty = scan_profiles(
            frames,
            calibration,
            options,
            chunk_dir,
            key,
            progress=progress,
            check_cancelled=check_cancelled,
        )
        t2 = time.perf_counter()

        poses = np.stack([f.base_from_flange for f in frames])  # type: ignore[misc]
        tri = Triangulator(calibration)
        uv = np.column_stack([profiles["u"], profiles["v"]])
        points = tri.points_base(uv, profiles["frame"], poses)
        ok = np.all(np.isfinite(points), axis=1)
        n_triangulated = int(np.count_nonzero(ok))
        if options.region_mm is not None:
            lo, hi = (np.asarray(c, dtype=np.float64) for c in options.region_mm)
            inside = np.all((points >= lo) & (points <= hi), axis=1)
            ok &= np.where(ok, inside, False)
        if options.table_z_mm is not None:
            z = np.where(ok, points[:, 2], -np.inf)
            ok &= z > table_cut_mm(z[ok], options.table_z_mm)
        frame_pos = profiles["frame"][ok]
        sweep_arr = np.asarray(sweep_of, dtype=np.int32)[frame_pos]
        points = points[ok]
        t3 = time.perf_counter()

        if check_cancelled is not None:
            check_cancelled()
        warnings: list[str] = []
        corrections = []
        if options.icp and len(sweep_ids) > 1:
            points, corrections = refine_sweeps(
                points,
                sweep_arr,
                max_distance_mm=options.icp_max_distance_mm,
                warn_translation_mm=options.icp_warn_translation_mm,
                warn_rotation_deg=options.icp_warn_rotation_deg,
            )
            for c in corrections:
                if c.applied and (
                    c.translation_mm > options.icp_warn_translation_mm
                    or c.rotation_deg > options.icp_warn_rotation_deg
                ):
                    warnings.append(
                        f"sweep {c.sweep}: ICP correction {c.translation_mm:.3f} mm, "
                        f"{c.rotation_deg:.3f} deg (calibration or robot poses off?)"
                    )
                elif not c.applied:
                    warnings.append(f"sweep {c.sweep}: not refined ({c.note})")

        if check_cancelled is not None:
            check_cancelled()
        frame_ids = np.array([f.id for f in frames], dtype=np.int32)
        attributes = {
            "intensity": profiles["intensity"][ok].astype(np.float32),
            "width_px": profiles["width_px"][ok].astype(np.float32),
            "flags": profiles["flags"][ok].astype(np.uint8),
            "frame_id": frame_ids[frame_pos],
            "sweep_id": sweep_arr,
        }
        if options.max_incidence_deg is not None:
            points, attributes = _limit_incidence(
                points, attributes, frame_pos, poses @ calibration.flange_from_cam, options
            )
        removed: dict[str, int] = {}
        n_stripe_points = len(points)
        if not options.keep_flagged:
            points, attributes, removed = _drop_flagged(points, attributes)
        cloud = build_cloud(points, attributes)
        cloud = filter_cloud(
            cloud,
            voxel_mm=options.voxel_mm,
            outlier_neighbors=options.outlier_neighbors,
            outlier_std_ratio=options.outlier_std_ratio,
            normals_radius_mm=options.normals_radius_mm,
            isolated_radius_mm=options.isolated_radius_mm,
            isolated_min_neighbors=options.isolated_min_neighbors,
        )
        t4 = time.perf_counter()
        n_points = len(cloud.point.positions)
        if n_points == 0:
            # Nothing to hand on: refused like bad input, before anything is written.
            n_found = len(profiles["u"])
            if not n_found:
                why = f"no stripe points found in any of the {len(frames)} frames"
            elif not n_triangulated:
                why = f"none of the {n_found} stripe points meets the light plane in front"
            elif not n_stripe_points:
                why = (
                    f"none of the {n_triangulated} stripe points lies in the region or "
                    "above the table cut"
                )
            elif not len(points):
                reasons = ", ".join(f"{n} {k}" for k, n in removed.items())
                why = (
                    f"all {n_stripe_points} stripe points are flagged ({reasons}); "
                    "--keep-flagged keeps them"
                )
            else:
                why = (
                    f"the cloud's filters (voxel, outliers, isolated points) removed all "
                    f"{len(points)} points"
                )
            where = sessions[0].root if len(sessions) == 1 else None
            if where is None:
                why = f"{len(sessions)} sessions ({sessions[0].root}, ...): {why}"
            raise InputError(where, f"{why}; nothing written")

        written = None
        if out_path is not None:
            meta = {
                "format": "robot-line-scanner cloud/1",
                "frame": "base",
                "units": "mm",
                "calibration": str(cal_path.resolve()) if cal_path else None,
                "calibration_sha256": hashlib.sha256(
                    json.dumps(calibration.to_json(), sort_keys=True, default=str).encode()
                ).hexdigest(),
                "sessions": [str(s.root.resolve()) for s in sessions],
                "frames": len(frames),
                "sweeps": len(sweep_ids),
                "mode": options.mode,
                "icp": [
                    {
                        "sweep": c.sweep,
                        "translation_mm": round(c.translation_mm, 4),
                        "rotation_deg": round(c.rotation_deg, 4),
                        "applied": c.applied,
                    }
                    for c in corrections
                ],
            }
            written = write_cloud(out_path, cloud, meta)
        t5 = time.perf_counter()
    finally:
        if not keep_work:
            shutil.rmtree(chunk_dir, ignore_errors=True)
            with contextlib.suppress(OSError):
                work_root.rmdir()
    for w in warnings:
        log.warning(w)
    return ScanResult(
        out_path=written,
        n_points=n_points,
        n_frames=len(frames),
        n_sweeps=len(sweep_ids),
        seconds=time.perf_counter() - t0,
        cloud=cloud,
        corrections=corrections,
        warnings=warnings,
        chunks_resumed=resumed,
        removed=removed,
        frames_without_stripe=empty,
        timings={
            "prepare_s": t1 - t0,
            "extract_s": t2 - t1,
            "triangulate_s": t3 - t2,
            "stitch_s": t4 - t3,
            "write_s": t5 - t4,
        },
    )
