"""The paper's EF check: measure the target's known diameter with the calibrated sensor.

In each laser image of a ``check`` session the stripe crosses the target centre O. E and F are
where the stripe meets the largest ring: in the image, the stripe's sub-pixel centre line
against the ring's conic (both after undistortion, where the stripe on the flat target is a
straight line and the ring's image an exact conic). E and F are triangulated through the light
plane and moved into the base frame with the robot pose; ``|EF|`` is compared with the nominal
diameter (the paper's Table III). Stripe centres on a printed diameter line are left out of the
line (the ink pulls them sideways); a view whose stripe runs along such a line, with too few
centres beside it, is refused with that reason.

``|EF|`` is invariant to the rigid transform ``base_from_cam``, so it tests intrinsics and the
light plane but not the hand-eye. The check therefore also reports the spread of O's base-frame
position across the session's poses (the target stays fixed, so every view must put O at the
same place): O comes from the target's pose in each view (all detected features, calibrated
camera) chained through ``base_from_flange @ flange_from_cam``.

Result file (contract, ``shared/spec/interfaces.md`` section 3, extended with more keys)::

    {"nominal_mm": 160.0,
     "measurements": [{"id": 0, "length_mm": 159.98, "error_mm": -0.02, ...}, ...],
     "mean_abs_error_mm": 0.02, "mean_rel_error": 0.000125, ...}
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from calibration.detection.conics import fit_conic, fit_line, line_conic_intersections
from calibration.detection.detect import detect_target
from calibration.extrinsics import estimate_pose
from metrology.budget import Contribution, Uncertainty
from scanner.core.camera import CameraModel, intersect_rays_with_plane
from scanner.core.conventions import invert_transform, transform_points
from scanner.core.fileio import InputError
from scanner.core.targets import ConcentricCirclesTarget
from scanner.core.tolerance import RowCounts, ToleranceRow
from scanner.formats.calibration_file import Calibration
from scanner.formats.session import Frame, Session
from scanner.stripe.extract import StripeFlag, extract_stripe, orientation_from_calibration

__all__ = [
    "EFCheckResult",
    "EFMeasurement",
    "EFTolerances",
    "ef_uncertainties",
    "measure_ef",
    "run_ef_check",
]

logger = logging.getLogger(__name__)

# A stripe point further than this from the fitted line (undistorted px) is not on the target.
_LINE_INLIER_PX = 1.0
_CLEAN = ~np.uint8(StripeFlag.SATURATED | StripeFlag.AMBIGUOUS | StripeFlag.SECONDARY)


@dataclass
class EFMeasurement:
    """One laser image of the check: ``|EF|`` or the reason it could not be measured."""

    id: int
    ok: bool
    reason: str = ""
    length_mm: float = math.nan
    error_mm: float = math.nan
    e_px: NDArray | None = None
    f_px: NDArray | None = None
    e_base: NDArray | None = None
    f_base: NDArray | None = None
    o_base: NDArray | None = None
    offset_from_o_mm: float = math.nan
    stripe_points: int = 0
    stripe_line_rms_px: float = math.nan
    uncertainty: Uncertainty | None = None
    """Of ``length_mm``: see :func:`ef_uncertainties`."""

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"id": self.id}
        if self.ok:
            out.update(length_mm=self.length_mm, error_mm=self.error_mm)
            if self.uncertainty is not None:
                out.update(
                    u_mm=self.uncertainty.u,
                    U_mm=self.uncertainty.U,
                    uncertainty=self.uncertainty.to_json(),
                )
        else:
            out.update(reason=self.reason)

        def vec(v: NDArray | None) -> list[float] | None:
            return None if v is None else [float(x) for x in v]

        out.update(
            e_base_mm=vec(self.e_base),
            f_base_mm=vec(self.f_base),
            o_base_mm=vec(self.o_base),
            stripe_offset_from_o_mm=None
            if math.isnan(self.offset_from_o_mm)
            else self.offset_from_o_mm,
            stripe_points=self.stripe_points,
            stripe_line_rms_px=None
            if math.isnan(self.stripe_line_rms_px)
            else self.stripe_line_rms_px,
        )
        return out


@dataclass(frozen=True)
class EFTolerances:
    """When a recalibration check passes: each figure at most its limit (mm).

    The defaults are those of the PLC service's ``[check]`` (``configs/plc.toml``).
    """

    max_mean_abs_mm: float = 0.10
    max_abs_mm: float = 0.25
    max_o_spread_mm: float = 0.50

    def __post_init__(self) -> None:
        for key in ("max_mean_abs_mm", "max_abs_mm", "max_o_spread_mm"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{key}: expected a positive number, got {value}")


@dataclass
class EFCheckResult(RowCounts):
    """All measurements of a check session, their summary figures and the verdict."""

    nominal_mm: float
    measurements: list[EFMeasurement]
    session: str = ""
    calibration: str = ""
    o_positions_base: NDArray = field(default_factory=lambda: np.zeros((0, 3)))
    tolerances: EFTolerances = field(default_factory=EFTolerances)

    @property
    def rows(self) -> list[ToleranceRow]:
        """The three judged figures, as the reports and the PLC show them."""
        t = self.tolerances
        figures = (
            ("mean absolute EF error", self.mean_abs_error_mm, t.max_mean_abs_mm),
            ("largest absolute EF error", self.max_abs_error_mm, t.max_abs_mm),
            ("spread of O in the base frame", self.o_spread_mm, t.max_o_spread_mm),
        )
        return [
            ToleranceRow(name, 0.0, None if math.isnan(v) else v, None, limit, unit="mm")
            for name, v, limit in figures
        ]

    @property
    def valid(self) -> list[EFMeasurement]:
        return [m for m in self.measurements if m.ok]

    @property
    def errors_mm(self) -> NDArray:
        return np.array([m.error_mm for m in self.valid])

    @property
    def mean_abs_error_mm(self) -> float:
        e = self.errors_mm
        return float(np.mean(np.abs(e))) if e.size else math.nan

    @property
    def max_abs_error_mm(self) -> float:
        e = self.errors_mm
        return float(np.max(np.abs(e))) if e.size else math.nan

    @property
    def mean_rel_error(self) -> float:
        return self.mean_abs_error_mm / self.nominal_mm

    @property
    def mean_length_mm(self) -> float:
        v = self.valid
        return float(np.mean([m.length_mm for m in v])) if v else math.nan

    @property
    def o_spread_mm(self) -> float:
        """Largest distance of a view's O from the mean O, base frame (mm): tests the hand-eye."""
        o = self.o_positions_base
        if len(o) < 2:
            return math.nan
        return float(np.max(np.linalg.norm(o - o.mean(axis=0), axis=1)))

    @property
    def o_std_mm(self) -> NDArray:
        o = self.o_positions_base
        return o.std(axis=0, ddof=1) if len(o) >= 2 else np.full(3, np.nan)

    def to_json(self) -> dict[str, Any]:
        def num(x: float) -> float | None:
            return None if math.isnan(x) else float(x)

        return {
            "nominal_mm": self.nominal_mm,
            "verdict": "pass" if self.passed else "fail",
            "tolerances_mm": {
                "mean_abs_error": self.tolerances.max_mean_abs_mm,
                "max_abs_error": self.tolerances.max_abs_mm,
                "o_spread": self.tolerances.max_o_spread_mm,
            },
            # The contract's list holds measured frames only; the others are listed with why.
            "measurements": [m.to_json() for m in self.valid],
            "failed": [{"id": m.id, "reason": m.reason} for m in self.measurements if not m.ok],
            "mean_abs_error_mm": num(self.mean_abs_error_mm),
            "mean_rel_error": num(self.mean_rel_error),
            "max_abs_error_mm": num(self.max_abs_error_mm),
            "mean_length_mm": num(self.mean_length_mm),
            "measured_count": len(self.valid),
            "o_spread_mm": num(self.o_spread_mm),
            "o_std_mm": [num(float(x)) for x in self.o_std_mm],
            "o_mean_base_mm": (
                self.o_positions_base.mean(axis=0).tolist() if len(self.o_positions_base) else None
            ),
            "session": self.session,
            "calibration": self.calibration,
        }


def _robust_line(points: NDArray, rng: np.random.Generator) -> tuple[NDArray, NDArray] | None:
    """RANSAC then total least squares: ``(line, inlier mask)`` of ``(N, 2)`` points."""
    n = len(points)
    if n < 10:
        return None
    best = None
    best_count = 0
    for _ in range(200):
        i, j = rng.choice(n, size=2, replace=False)
        d = points[j] - points[i]
        norm = float(np.hypot(*d))
        if norm < 5.0:
            continue
        normal = np.array([-d[1], d[0]]) / norm
        dist = np.abs((points - points[i]) @ normal)
        inliers = dist < _LINE_INLIER_PX * 3
        count = int(inliers.sum())
        if count > best_count:
            best, best_count = inliers, count
    if best is None or best_count < 10:
        return None
    mask = best
    line = fit_line(points[mask])
    for threshold in (_LINE_INLIER_PX, _LINE_INLIER_PX):
        dist = np.abs(points @ line[:2] + line[2])
        mask = dist < threshold
        if mask.sum() < 10:
            return None
        line = fit_line(points[mask])
    return line, mask


def _on_ink(
    uv: NDArray,
    width_px: NDArray,
    orientation: str,
    camera: CameraModel,
    pose: Any,
    target: ConcentricCirclesTarget,
) -> NDArray:
    """Which stripe centres ``uv`` ``(N, 2)`` have a printed diameter line under their stripe.

    Ink under a stripe pulls its centre towards the paper beside it when the ink's edge runs
    along the stripe. A stripe through O crosses every ring at right angles, so the rings'
    edges run across it and leave its centre in place; a diameter line the stripe meets at a
    small angle runs along it over a long stretch (a view whose stripe lies on the printed
    A-O-B line measured |EF| 0.38 mm short). Each centre and the end of its stripe's width
    (``width_px`` along the scan line of the ``orientation``) are taken onto the target plane
    with ``pose``; a centre is on ink when a diameter line (``line_width_mm`` wide) comes within
    that half-width of it inside the largest ring.
    """
    if len(uv) == 0:
        return np.zeros(0, bool)
    cam_from_target = pose.cam_from_target
    rot, t = cam_from_target[:3, :3], cam_from_target[:3, 3]
    normal = rot[:, 2]

    def on_target(pixels: NDArray) -> NDArray:
        rays = camera.rays(pixels)
        depth = (normal @ t) / (rays @ normal)
        return (rays * depth[:, None] - t) @ rot  # target frame, z = 0

    step = np.array([1.0, 0.0]) if orientation == "rows" else np.array([0.0, 1.0])
    centre = on_target(uv)[:, :2]
    reach = np.linalg.norm(on_target(uv + step)[:, :2] - centre, axis=1) * 0.5 * width_px
    half = 0.5 * target.line_width_mm + reach
    radius = np.hypot(centre[:, 0], centre[:, 1])
    near_axis = (np.abs(centre[:, 0]) < half) | (np.abs(centre[:, 1]) < half)
    return near_axis & (radius <= target.radius_mm + half)


def measure_ef(
    laser_image: NDArray,
    observation: Any,
    target: ConcentricCirclesTarget,
    calibration: Calibration,
    base_from_flange: NDArray,
    frame_id: int = 0,
    background: NDArray | None = None,
    mode: str = "precise",
) -> EFMeasurement:
    """Measure ``|EF|`` in one laser image (see the module docstring).

    Parameters
    ----------
    laser_image : ndarray, shape (H, W)
        Laser-on frame; the stripe crosses the target near O.
    observation : TargetObservation
        The target detected in the same pose (target image, or the laser image itself).
    target : ConcentricCirclesTarget
    calibration : Calibration
    base_from_flange : ndarray, shape (4, 4)
        Robot pose of the frame.

    Returns
    -------
    EFMeasurement
        Falsy-``ok`` with a reason when E and F cannot be found.
    """
    if not observation:
        return EFMeasurement(frame_id, False, f"target not found: {observation.reason}")
    camera = CameraModel(calibration.width, calibration.height, calibration.K, calibration.dist)
    radius = target.radius_mm
    ring = next((r for r in observation.rings if abs(r.radius_mm - radius) < 1e-6), None)
    if ring is None or len(ring.edge_points_px) < 20:
        return EFMeasurement(frame_id, False, "largest ring not detected")

    # Undistort everything first: there the flat target's stripe is a line and the ring a conic.
    ring_px = camera.undistort_pixels(ring.edge_points_px)
    conic = fit_conic(ring_px)
    o_px = observation.center_px
    if o_px is None:
        return EFMeasurement(frame_id, False, "target centre O not detected")
    o_und = camera.undistort_pixels(np.asarray(o_px, dtype=np.float64)[None])[0]
    o_h = np.array([o_und[0], o_und[1], 1.0])
    inside_sign = math.copysign(1.0, float(o_h @ conic @ o_h))

    prof = extract_stripe(
        laser_image,
        mode=mode,
        orientation=orientation_from_calibration(calibration),
        background=background,
        flatten_background=False,  # a lit printed target is no smooth background
    )
    clean = (prof.flags & _CLEAN) == prof.flags
    stripe_und = camera.undistort_pixels(prof.uv[clean]) if clean.any() else np.zeros((0, 2))
    xh = np.column_stack([stripe_und, np.ones(len(stripe_und))])
    inside = np.einsum("ij,jk,ik->i", xh, conic, xh) * inside_sign > 0
    pose = estimate_pose(observation.points_px, observation.points_target, camera)
    if pose:
        # A stripe centre on a printed diameter line is pulled towards the paper beside it:
        # keep only the points whose stripe lies beside the lines.
        on_ink = _on_ink(
            prof.uv[clean], prof.width_px[clean], prof.orientation, camera, pose, target
        )
        paper = inside & ~on_ink
        if paper.sum() < max(10, 0.25 * inside.sum()):
            return EFMeasurement(
                frame_id,
                False,
                f"the stripe runs along a printed diameter line: {int(paper.sum())} of "
                f"{int(inside.sum())} stripe points inside the largest ring lie beside it",
            )
        inside = paper
    stripe_in = stripe_und[inside]
    fit = _robust_line(stripe_in, np.random.default_rng(frame_id))
    if fit is None:
        return EFMeasurement(
            frame_id, False, f"no straight stripe inside the largest ring ({len(stripe_in)} points)"
        )
    line, mask = fit
    rms = float(np.sqrt(np.mean((stripe_in[mask] @ line[:2] + line[2]) ** 2)))
    ef_und = line_conic_intersections(line, conic)
    if len(ef_und) != 2:
        return EFMeasurement(frame_id, False, "the stripe does not cross the largest ring twice")

    # Triangulate through the light plane: rays of the undistorted pixels (ideal camera).
    rays = np.column_stack(
        [(ef_und - calibration.K[:2, 2]) @ np.linalg.inv(calibration.K[:2, :2]).T, np.ones(2)]
    )
    ef_cam = intersect_rays_with_plane(
        rays, calibration.light_plane.normal, calibration.light_plane.d
    )
    if not np.all(np.isfinite(ef_cam)):
        return EFMeasurement(
            frame_id, False, "E or F does not meet the light plane in front of the camera"
        )
    base_from_cam = base_from_flange @ calibration.flange_from_cam
    e_base, f_base = transform_points(base_from_cam, ef_cam)
    length = float(np.linalg.norm(e_base - f_base))

    # O in the base frame from the full target pose (tests the hand-eye), and how far the
    # stripe passed from O on the target (|EF| is a chord, 2 sqrt(R^2 - h^2), not 2R, when h > 0).
    o_base = None
    offset = math.nan
    if pose:
        base_from_target = base_from_cam @ pose.cam_from_target
        o_base = base_from_target[:3, 3].copy()
        target_from_cam = invert_transform(pose.cam_from_target)
        ef_target = transform_points(target_from_cam, ef_cam)
        mid = ef_target.mean(axis=0)
        offset = float(np.hypot(mid[0], mid[1]))
    e_px, f_px = camera.project(ef_cam)
    return EFMeasurement(
        id=frame_id,
        ok=True,
        length_mm=length,
        error_mm=length - 2 * radius,
        e_px=e_px,
        f_px=f_px,
        e_base=e_base,
        f_base=f_base,
        o_base=o_base,
        offset_from_o_mm=offset,
        stripe_points=int(mask.sum()),
        stripe_line_rms_px=rms,
    )


def _load_check_session(session: Session) -> ConcentricCirclesTarget:
    if session.kind != "check":
        raise InputError(
            session.root / "session.json",
            f"kind: expected 'check' for the EF check, got {session.kind!r}",
        )
    if not isinstance(session.target, ConcentricCirclesTarget):
        raise InputError(
            session.root / "session.json",
            "target: the EF check needs the concentric_circles target (its largest ring is EF)",
        )
    laser_rows = [f for f in session.frames if f.laser_image is not None]
    if not laser_rows:
        raise InputError(
            session.root / "frames.csv", "no laser_image in any row: nothing to measure"
        )
    unposed = [f.id for f in laser_rows if not f.has_pose]
    if unposed:
        raise InputError(
            session.root / "frames.csv",
            f"rows without a robot pose: ids {unposed[:10]} (the check needs base-frame points)",
        )
    return session.target


def check_frame(
    session: Session, frame: Frame, calibration: Calibration, mode: str = "precise"
) -> EFMeasurement:
    """Detect the target and measure ``|EF|`` in one row of a check session."""
    target = _load_check_session(session)
    laser, background = session.load_laser_pair(frame)
    detect_image = session.load_target_image(frame) if frame.target_image is not None else laser
    observation = detect_target(detect_image, target)
    return measure_ef(
        laser, observation, target, calibration, frame.base_from_flange, frame.id, background, mode
    )


def run_ef_check(
    session: Session,
    calibration: Calibration,
    progress: bool = False,
    mode: str = "precise",
    calibration_source: str = "",
    tolerances: EFTolerances | None = None,
    check_cancelled: Callable[[], None] | None = None,
) -> EFCheckResult:
    """Run the EF check on a ``check`` session with a calibration; write nothing.

    Parameters
    ----------
    session : Session
        A ``check`` session with a concentric-circles target.
    calibration : Calibration
    progress : bool
        tqdm progress bar on standard error.
    mode : {"precise", "fast"}
        Stripe extractor.
    calibration_source : str
        Where the calibration came from (its file), recorded in the result.
    tolerances : EFTolerances, optional
        What the verdict judges against (default :class:`EFTolerances`).
    check_cancelled : callable, optional
        Called after each laser frame's measurement: whatever it raises stops the check and
        comes out of this function (a PLC job's cancellation).

    Raises
    ------
    InputError
        Bad session, image size not matching the calibration, or no frame where EF could be
        measured (the reasons of the first frames are given).
    """
    target = _load_check_session(session)
    if (session.width, session.height) != (calibration.width, calibration.height):
        raise InputError(
            session.root / "session.json",
            f"camera: images are {session.width}x{session.height}, the calibration is for "
            f"{calibration.width}x{calibration.height}",
        )
    frames = [f for f in session.frames if f.laser_image is not None]
    iterator: Any = frames
    if progress:
        iterator = tqdm(frames, desc="EF check", unit="img", leave=False)
    measurements = []
    for f in iterator:
        measurements.append(check_frame(session, f, calibration, mode))
        if check_cancelled is not None:
            check_cancelled()
    o_positions = np.array(
        [m.o_base for m in measurements if m.ok and m.o_base is not None]
    ).reshape(-1, 3)
    result = EFCheckResult(
        nominal_mm=2 * target.radius_mm,
        measurements=measurements,
        session=str(session.root.resolve()),
        calibration=calibration_source,
        o_positions_base=o_positions,
        tolerances=tolerances or EFTolerances(),
    )
    if not result.valid:
        reasons = "; ".join(f"frame {m.id}: {m.reason}" for m in measurements[:3])
        raise InputError(session.root, f"EF could not be measured in any laser image ({reasons})")
    ef_uncertainties(result.valid, calibration)
    return result


def _length_with(calibration: Calibration, e_px: NDArray, f_px: NDArray) -> float:
    """``|EF|`` (mm) that ``calibration`` gives for the distorted pixels of E and F."""
    camera = CameraModel(calibration.width, calibration.height, calibration.K, calibration.dist)
    plane = calibration.light_plane
    ef_cam = intersect_rays_with_plane(camera.rays(np.array([e_px, f_px])), plane.normal, plane.d)  # type: ignore[union-attr]
    return float(np.linalg.norm(ef_cam[0] - ef_cam[1]))


def ef_uncertainties(measurements: list[EFMeasurement], calibration: Calibration) -> None:
    """Give each measured ``|EF|`` its uncertainty (in place).

    ``|EF|`` does not depend on the robot or the hand-eye (a rigid motion keeps lengths), so
    two sources remain: the calibration (intrinsics and light plane, from the file's
    covariance, linearised along its principal directions: E and F re-triangulated from the
    same pixels) and the image (where the stripe and the ring were found, the stripe's
    passage beside O): the scatter of ``|EF|`` over the session's images, a type A
    evaluation of one image's repeatability (at least 3 images).
    """
    ok = [m for m in measurements if m.ok and m.e_px is not None and m.f_px is not None]
    if not ok:
        return
    lengths = np.array([m.length_mm for m in ok])
    image_u = float(np.std(lengths, ddof=1)) if len(ok) >= 3 else math.nan
    cov = calibration.covariance
    dirs = cov.principal_directions() if cov is not None else np.zeros((0, 18))
    for m in ok:
        budget: list[Contribution] = []
        missing: list[str] = []
        if cov is not None:
            base = _length_with(calibration, m.e_px, m.f_px)  # type: ignore[arg-type]
            deltas = [
                _length_with(calibration.corrected(s), m.e_px, m.f_px) - base  # type: ignore[arg-type]
                for s in dirs
            ]
            budget.append(
                Contribution(
                    "calibration",
                    float(np.sqrt(np.sum(np.square(deltas)))),
                    f"linearised over {len(dirs)} principal directions of the covariance",
                )
            )
        else:
            missing.append("calibration (the calibration file has no covariance)")
        if math.isfinite(image_u):
            budget.append(
                Contribution(
                    "image (stripe, ring, passage beside O)",
                    image_u,
                    f"standard deviation of |EF| over the session's {len(ok)} images",
                )
            )
        else:
            missing.append("image repeatability (fewer than 3 images measured)")
        if budget:
            u = float(np.sqrt(sum(c.u**2 for c in budget)))
            m.uncertainty = Uncertainty(u, tuple(budget), not_included=tuple(missing))
