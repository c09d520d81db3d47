"""Sweep planning from CAD: which straight sweeps measure a part's surface.

Set cover over candidate sweeps, scored by the sensor model of :mod:`scanner.scanning.coverage`
on points sampled uniformly by area over the part (as view-planning research does, e.g. KIT's
agiprobot planner, and as PC-DMIS UniScan paints what its sweeps miss):

1. the reference: the surface visible from above the table (:func:`visible_from_above`);
2. candidates: the sensor looking down, tilted by each of ``tilts_deg`` about its travel and
   about its line, turned to each of ``yaws`` azimuths, aimed at the part's centre at the
   sensor's working distance, travelling across the part's bounding sphere; candidates whose
   flange leaves the reach or whose camera comes closer to the part than the clearance are
   dropped;
3. greedy cover: the candidate that adds most measured area, until the target share is
   reached, no candidate adds ``min_gain``, or ``max_sweeps`` are chosen;
4. each chosen sweep trimmed to the stretch of travel over which it measures points.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from scanner.formats.meshes import MeshRaycaster, TriangleMesh
from scanner.scanning.coverage import (
    CoverageLimits,
    LinearSweep,
    SensorGeometry,
    sweep_coverage,
    visible_from_above,
)

__all__ = [
    "PlanConfig",
    "SweepPlan",
    "candidate_sweeps",
    "nadir_rotation",
    "place_on_table",
    "plan_sweeps",
]


@dataclass(frozen=True)
class PlanConfig:
    """How sweeps are planned.

    Attributes
    ----------
    target_coverage : float
        Share of the surface visible from above to measure.
    max_sweeps : int
    step_mm : float
        Travel between profiles.
    tilts_deg : tuple of float
        Tilts of the sensor from looking straight down.
    yaws : int
        Azimuths per tilt, evenly spaced over 360 deg.
    margin_mm : float
        Travel beyond the stretch over which a chosen sweep measures points.
    samples : int
        Surface points the coverage is counted on.
    min_gain : float
        A sweep adding less than this share of the visible surface is not worth its time.
    reach_mm : tuple of float
        Horizontal distance of the flange from the robot's base axis, min and max.
    clearance_mm : float
        The camera stays this far above the part's top.
    limits : CoverageLimits
    seed : int
        Of the surface sampling.
    """

    target_coverage: float = 0.95
    max_sweeps: int = 12
    step_mm: float = 0.5
    tilts_deg: tuple[float, ...] = (0.0, 20.0, 35.0, 50.0)
    yaws: int = 8
    margin_mm: float = 3.0
    samples: int = 20_000
    min_gain: float = 0.002
    reach_mm: tuple[float, float] = (0.0, np.inf)
    clearance_mm: float = 50.0
    limits: CoverageLimits = field(default_factory=CoverageLimits)
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0 < self.target_coverage <= 1:
            raise ValueError(f"target_coverage: expected (0, 1], got {self.target_coverage}")
        if self.max_sweeps < 1 or self.yaws < 1 or self.samples < 100:
            raise ValueError(
                "expected max_sweeps >= 1, yaws >= 1 and samples >= 100, got "
                f"{self.max_sweeps}, {self.yaws}, {self.samples}"
            )
        if self.step_mm <= 0 or self.margin_mm < 0:
            raise ValueError(f"expected step_mm > 0, margin_mm >= 0, got {self.step_mm}")
        if not all(0 <= t < 80 for t in self.tilts_deg) or not self.tilts_deg:
            raise ValueError(f"tilts_deg: expected values in [0, 80), got {self.tilts_deg}")


@dataclass(frozen=True)
class SweepPlan:
    """Planned sweeps and the coverage they are predicted to give.

    Truthy when the target coverage is reached; else ``reason`` says why not.

    Attributes
    ----------
    sweeps : tuple of LinearSweep
        In the order chosen (largest gain first).
    gains : tuple of float
        Share of the visible surface each sweep adds.
    coverage : float
        Predicted share of the visible surface measured.
    visible_share : float
        Share of the whole surface visible from above the table.
    points_base, normals_base : ndarray, shape (M, 3)
        The surface samples, base frame.
    visible : ndarray, shape (M,), bool
    measured_by : ndarray, shape (M,), int
        The first chosen sweep measuring each sample, -1 for none.
    candidates, reachable : int
        Candidate sweeps generated and those within reach.
    target_coverage : float
    reason : str
    """

    sweeps: tuple[LinearSweep, ...]
    gains: tuple[float, ...]
    coverage: float
    visible_share: float
    points_base: NDArray[np.float64]
    normals_base: NDArray[np.float64]
    visible: NDArray[np.bool_]
    measured_by: NDArray[np.int64]
    candidates: int
    reachable: int
    target_coverage: float
    reason: str = ""

    def __bool__(self) -> bool:
        return self.coverage >= self.target_coverage

    @property
    def frames(self) -> int:
        return sum(s.frames for s in self.sweeps)


def place_on_table(
    part: TriangleMesh, at_mm: tuple[float, float, float], yaw_deg: float = 0.0
) -> NDArray[np.float64]:
    """``base_from_part`` standing the part on its lowest face: the middle of its footprint
    at ``at_mm`` (base frame; z is the table), turned by ``yaw_deg`` about the vertical."""
    lo, hi = part.bounds()
    bottom_centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    out[:3, 3] = np.asarray(at_mm, dtype=np.float64) - out[:3, :3] @ bottom_centre
    return out


def nadir_rotation(sensor: SensorGeometry) -> NDArray[np.float64]:
    """``base_from_cam`` rotation looking straight down, travel along base +x."""
    travel, line = sensor.travel_direction_cam(), sensor.line_direction_cam()
    src = np.column_stack([travel, line, [0.0, 0.0, 1.0]])
    dst = np.column_stack([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    return dst @ src.T


def candidate_sweeps(
    sensor: SensorGeometry, part_base: TriangleMesh, config: PlanConfig
) -> list[LinearSweep]:
    """Sweeps over the whole part from every tilt and azimuth of ``config`` (not yet trimmed).

    Each crosses the part's bounding sphere with the light plane, the camera aimed at the
    part's centre at the sensor's working distance.
    """
    lo, hi = part_base.bounds()
    centre = (lo + hi) / 2
    radius = float(np.linalg.norm(hi - lo)) / 2
    wd = sensor.working_distance_mm()
    nadir = nadir_rotation(sensor)
    travel_c = sensor.travel_direction_cam()
    out: list[LinearSweep] = []
    for tilt in config.tilts_deg:
        axes = ("x",) if tilt == 0 else ("x", "y")
        for axis in axes:
            tilted = Rotation.from_euler(axis, tilt, degrees=True).as_matrix() @ nadir
            for k in range(config.yaws):
                yaw = Rotation.from_euler("z", 360.0 * k / config.yaws, degrees=True)
                rot = yaw.as_matrix() @ tilted
                direction = rot @ travel_c
                rate = float((rot @ sensor.plane_normal_cam) @ direction)
                if abs(rate) < 0.2:
                    continue
                half = (radius + config.margin_mm) / abs(rate)
                start = np.eye(4)
                start[:3, :3] = rot
                start[:3, 3] = centre - wd * rot[:, 2] - half * direction
                out.append(LinearSweep(start, direction, 2 * half, config.step_mm))
    return out


def _reachable(
    sweep: LinearSweep, sensor: SensorGeometry, top_z: float, config: PlanConfig
) -> bool:
    poses = sweep.base_from_cam()[[0, -1]]
    flange = poses @ np.linalg.inv(sensor.flange_from_cam)
    horizontal = np.linalg.norm(flange[:, :2, 3], axis=1)
    lo, hi = config.reach_mm
    return bool(
        np.all((horizontal >= lo) & (horizontal <= hi))
        and np.all(poses[:, 2, 3] >= top_z + config.clearance_mm)
    )


def _trimmed(
    sweep: LinearSweep, sensor: SensorGeometry, points: NDArray, margin_mm: float
) -> LinearSweep:
    """The sweep cut down to the travel over which it passes ``points`` (plus a margin)."""
    rot = sweep.base_from_cam_start[:3, :3]
    n_b = rot @ sensor.plane_normal_cam
    c0 = sweep.base_from_cam_start[:3, 3]
    s = (points @ n_b + sensor.plane_d_cam_mm - n_b @ c0) / float(n_b @ sweep.direction)
    s0 = max(0.0, float(s.min()) - margin_mm)
    s1 = min(sweep.length_mm, float(s.max()) + margin_mm)
    start = sweep.base_from_cam_start.copy()
    start[:3, 3] = c0 + s0 * sweep.direction
    return replace(sweep, base_from_cam_start=start, length_mm=s1 - s0)


def plan_sweeps(
    sensor: SensorGeometry, part_base: TriangleMesh, config: PlanConfig | None = None
) -> SweepPlan:
    """Choose sweeps that measure ``config.target_coverage`` of the part's visible surface.

    Parameters
    ----------
    sensor : SensorGeometry
    part_base : TriangleMesh
        The part where it stands, base frame, mm.
    config : PlanConfig, optional

    Returns
    -------
    SweepPlan
        Falsy with a reason when the target is not reached.
    """
    config = config or PlanConfig()
    rng = np.random.default_rng(config.seed)
    points, normals = part_base.sample_surface(config.samples, rng)
    caster = MeshRaycaster(part_base)
    visible = visible_from_above(points, normals, caster, config.limits.max_view_incidence_deg)
    if not np.any(visible):
        raise ValueError("part: no surface is visible from above the table")
    top_z = float(part_base.bounds()[1][2])
    candidates = candidate_sweeps(sensor, part_base, config)
    usable = [c for c in candidates if _reachable(c, sensor, top_z, config)]
    covers = np.array(
        [
            sweep_coverage(sensor, c, points, normals, caster, config.limits) & visible
            for c in usable
        ]
    ).reshape(len(usable), len(points))
    n_visible = int(visible.sum())
    measured_by = np.full(len(points), -1, dtype=np.int64)
    chosen: list[LinearSweep] = []
    gains: list[float] = []
    reason = ""
    while True:
        coverage = float(np.count_nonzero(measured_by >= 0)) / n_visible
        if coverage >= config.target_coverage:
            break
        if len(chosen) >= config.max_sweeps:
            reason = f"max_sweeps ({config.max_sweeps}) reached at {100 * coverage:.1f} %"
            break
        if not len(usable):
            reason = "no candidate sweep within reach"
            break
        new = covers & (measured_by < 0)
        counts = new.sum(axis=1)
        best = int(np.argmax(counts))
        gain = counts[best] / n_visible
        if gain < config.min_gain:
            reason = (
                f"no sweep adds {100 * config.min_gain:.1f} % more: the rest "
                f"({100 * (1 - coverage):.1f} % of the visible surface) is out of the sensor's "
                "reach (deep pockets, bores, shadowed walls)"
            )
            break
        measured_by[new[best]] = len(chosen)
        chosen.append(_trimmed(usable[best], sensor, points[covers[best]], config.margin_mm))
        gains.append(float(gain))
    coverage = float(np.count_nonzero(measured_by >= 0)) / n_visible
    return SweepPlan(
        sweeps=tuple(chosen),
        gains=tuple(gains),
        coverage=coverage,
        visible_share=n_visible / len(points),
        points_base=points,
        normals_base=normals,
        visible=visible,
        measured_by=measured_by,
        candidates=len(candidates),
        reachable=len(usable),
        target_coverage=config.target_coverage,
        reason=reason,
    )
