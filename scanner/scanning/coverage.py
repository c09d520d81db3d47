"""What a linear sweep of the line sensor sees of a part: the sensor model of sweep planning.

A point of the part's surface is *measured* by a sweep when, at the moment the light plane
passes through it (the sweep is a straight flange motion, so the plane moves with it):

* the laser lights it: the segment from the laser origin is free and the light meets the
  surface within ``max_laser_incidence_deg`` of its normal;
* the camera sees it: inside the image (with a margin), within the depth range, the view
  within ``max_view_incidence_deg`` of the normal, and the line of sight free;
* the sweep's travel reaches that plane position.

Occlusion is tested against the part itself (Open3D's ray casting through
:class:`~scanner.formats.meshes.MeshRaycaster`). The share of a surface a set of sweeps
measures is counted on points sampled uniformly by area, so it is a share of area.

The reference a coverage is given against is the surface *visible from above the table*:
points some line of sight reaches from above the table within the view incidence limit,
whatever the sensor (:func:`visible_from_above`). Pockets and bores deeper than a line
sensor's triangulation angle allows stay in that reference: a plan that cannot reach them
says so in its coverage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from scanner.core.camera import CameraModel
from scanner.core.conventions import check_transform
from scanner.formats.calibration_file import Calibration
from scanner.formats.meshes import MeshRaycaster

__all__ = [
    "CoverageLimits",
    "LinearSweep",
    "SensorGeometry",
    "fibonacci_hemisphere",
    "measured_by_cloud",
    "sweep_coverage",
    "visible_from_above",
]

#: Rays leave a surface point this far along its normal, beyond float32 casting's rounding.
_LIFT_MM = 0.01


@dataclass(frozen=True)
class SensorGeometry:
    """The line sensor as a planner sees it.

    Attributes
    ----------
    camera : CameraModel
    plane_normal_cam : ndarray, shape (3,)
        Unit normal of the light plane ``n . p + d = 0``, camera frame.
    plane_d_cam_mm : float
    laser_origin_cam : ndarray, shape (3,)
        Apex of the laser fan, camera frame, mm.
    flange_from_cam : ndarray, shape (4, 4)
    """

    camera: CameraModel
    plane_normal_cam: NDArray[np.float64]
    plane_d_cam_mm: float
    laser_origin_cam: NDArray[np.float64]
    flange_from_cam: NDArray[np.float64]

    def __post_init__(self) -> None:
        n = np.asarray(self.plane_normal_cam, dtype=np.float64)
        if n.shape != (3,) or abs(np.linalg.norm(n) - 1.0) > 1e-6:
            raise ValueError(f"plane_normal_cam: expected a unit 3-vector, got {n}")
        check_transform(self.flange_from_cam, "flange_from_cam")

    @classmethod
    def from_calibration(
        cls, calibration: Calibration, laser_origin_cam: NDArray | None = None
    ) -> SensorGeometry:
        """The sensor of a calibration file; the laser origin from the file unless given."""
        if calibration.light_plane is None:
            raise ValueError("calibration: expected a light plane, got a camera-only file")
        origin = laser_origin_cam if laser_origin_cam is not None else calibration.laser_origin_cam
        if origin is None:
            raise ValueError(
                "calibration: expected laser_origin_cam (or one given), got none: planning "
                "needs the laser's origin for shadows and incidence"
            )
        return cls(
            CameraModel(calibration.width, calibration.height, calibration.K, calibration.dist),
            np.asarray(calibration.light_plane.normal, dtype=np.float64),
            float(calibration.light_plane.d),
            np.asarray(origin, dtype=np.float64),
            np.asarray(calibration.flange_from_cam, dtype=np.float64),
        )

    def working_distance_mm(self) -> float:
        """Depth at which the light plane crosses the optical axis."""
        nz = float(self.plane_normal_cam[2])
        if abs(nz) < 1e-9:
            raise ValueError("light plane parallel to the optical axis: no working distance")
        return -self.plane_d_cam_mm / nz

    def line_direction_cam(self) -> NDArray[np.float64]:
        """Direction of the laser line in the image plane (camera frame, unit)."""
        n = self.plane_normal_cam
        line = np.array([n[1], -n[0], 0.0])
        norm = np.linalg.norm(line)
        if norm < 1e-9:
            raise ValueError("light plane parallel to the image plane: no line to sweep")
        return line / norm

    def travel_direction_cam(self) -> NDArray[np.float64]:
        """The sweep's travel in the camera frame: across the line, in the image plane."""
        return np.cross(self.line_direction_cam(), [0.0, 0.0, 1.0])


@dataclass(frozen=True)
class LinearSweep:
    """A straight flange motion: the camera at ``base_from_cam_start`` moved along
    ``direction`` over ``length_mm``, one profile every ``step_mm``.

    Attributes
    ----------
    base_from_cam_start : ndarray, shape (4, 4)
    direction : ndarray, shape (3,)
        Unit travel, base frame (the orientation stays fixed).
    length_mm, step_mm : float
    """

    base_from_cam_start: NDArray[np.float64]
    direction: NDArray[np.float64]
    length_mm: float
    step_mm: float

    def __post_init__(self) -> None:
        check_transform(self.base_from_cam_start, "base_from_cam_start")
        if self.length_mm < 0 or self.step_mm <= 0:
            raise ValueError(
                f"sweep: expected length_mm >= 0 and step_mm > 0, got {self.length_mm}, "
                f"{self.step_mm}"
            )

    @property
    def frames(self) -> int:
        return int(np.floor(self.length_mm / self.step_mm + 1e-9)) + 1

    def base_from_cam(self) -> NDArray[np.float64]:
        """Camera pose of every frame, ``(F, 4, 4)``."""
        s = np.arange(self.frames) * self.step_mm
        out = np.tile(self.base_from_cam_start, (self.frames, 1, 1))
        out[:, :3, 3] += s[:, None] * self.direction
        return out

    def base_from_flange(self, flange_from_cam: NDArray) -> NDArray[np.float64]:
        """Flange pose of every frame, ``(F, 4, 4)``: what the robot is sent."""
        return self.base_from_cam() @ np.linalg.inv(flange_from_cam)


@dataclass(frozen=True)
class CoverageLimits:
    """When a point counts as measured.

    Attributes
    ----------
    max_view_incidence_deg, max_laser_incidence_deg : float
        Largest angle between the surface normal and the direction to the camera / laser.
    depth_range_mm : tuple of float
        Depths along the optical axis inside the sensor's depth of field.
    image_margin_px : float
        Points this close to the image border do not count (half a stripe window).
    """

    max_view_incidence_deg: float = 70.0
    max_laser_incidence_deg: float = 70.0
    depth_range_mm: tuple[float, float] = (0.0, np.inf)
    image_margin_px: float = 10.0

    def __post_init__(self) -> None:
        for name in ("max_view_incidence_deg", "max_laser_incidence_deg"):
            value = getattr(self, name)
            if not 0 < value < 90:
                raise ValueError(f"{name}: expected a value in (0, 90), got {value}")
        lo, hi = self.depth_range_mm
        if not 0 <= lo < hi:
            raise ValueError(f"depth_range_mm: expected 0 <= near < far, got {lo}, {hi}")


def sweep_coverage(
    sensor: SensorGeometry,
    sweep: LinearSweep,
    points_base: NDArray[np.float64],
    normals_base: NDArray[np.float64],
    part: MeshRaycaster,
    limits: CoverageLimits,
) -> NDArray[np.bool_]:
    """Which of the surface points ``(M, 3)`` (outward normals ``(M, 3)``) the sweep measures.

    Returns
    -------
    ndarray, shape (M,), bool
    """
    p = np.asarray(points_base, dtype=np.float64)
    nrm = np.asarray(normals_base, dtype=np.float64)
    rot = sweep.base_from_cam_start[:3, :3]
    c0 = sweep.base_from_cam_start[:3, 3]
    n_b = rot @ sensor.plane_normal_cam
    rate = float(n_b @ sweep.direction)
    if abs(rate) < 1e-6:  # the plane slides along itself: it never passes a point
        return np.zeros(len(p), dtype=bool)
    # n_b . x + d_c - n_b . (c0 + s dir) = 0 at x = p.
    s = (p @ n_b + sensor.plane_d_cam_mm - n_b @ c0) / rate
    ok = (s >= -0.5 * sweep.step_mm) & (s <= sweep.length_mm + 0.5 * sweep.step_mm)
    centre = c0 + s[:, None] * sweep.direction
    in_cam = (p - centre) @ rot  # rows: rot.T @ (p - c)
    depth = in_cam[:, 2]
    ok &= (depth > limits.depth_range_mm[0]) & (depth < limits.depth_range_mm[1])
    # Far outside the field a distortion polynomial folds back into the image: only rays
    # within the image's own cone are projected.
    cam = sensor.camera
    corners = cam.normalize(
        np.array(
            [[0, 0], [cam.width, 0], [0, cam.height], [cam.width, cam.height]], dtype=np.float64
        )
    )
    reach = 1.2 * np.abs(corners).max(axis=0)
    xy = in_cam[:, :2] / np.where(depth > 0, depth, 1.0)[:, None]
    ok &= np.all(np.abs(xy) <= reach, axis=1)
    idx = np.flatnonzero(ok)
    uv = cam.project(in_cam[idx])
    ok[idx] = cam.in_image(uv, limits.image_margin_px)
    to_cam = centre - p
    dist_cam = np.linalg.norm(to_cam, axis=1)
    cos_view = np.cos(np.radians(limits.max_view_incidence_deg))
    ok &= np.einsum("ij,ij->i", nrm, to_cam) >= cos_view * dist_cam
    laser = centre + rot @ sensor.laser_origin_cam
    to_laser = laser - p
    dist_laser = np.linalg.norm(to_laser, axis=1)
    cos_laser = np.cos(np.radians(limits.max_laser_incidence_deg))
    ok &= np.einsum("ij,ij->i", nrm, to_laser) >= cos_laser * dist_laser
    idx = np.flatnonzero(ok)
    if len(idx):
        start = p[idx] + _LIFT_MM * nrm[idx]
        t_cam, _ = part.cast(start, centre[idx] - start)
        t_las, _ = part.cast(start, laser[idx] - start)
        ok[idx] = (t_cam >= 1.0) & (t_las >= 1.0)
    return ok


def fibonacci_hemisphere(count: int, min_elevation_deg: float = 5.0) -> NDArray[np.float64]:
    """``count`` nearly uniform unit directions ``(count, 3)`` with ``z >= sin(min_elevation)``."""
    z_min = np.sin(np.radians(min_elevation_deg))
    k = np.arange(count) + 0.5
    z = 1.0 - k / count * (1.0 - z_min)
    r = np.sqrt(1.0 - z * z)
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def visible_from_above(
    points_base: NDArray[np.float64],
    normals_base: NDArray[np.float64],
    part: MeshRaycaster,
    max_incidence_deg: float = 70.0,
    directions: int = 256,
    min_elevation_deg: float = 5.0,
) -> NDArray[np.bool_]:
    """Which surface points some free line of sight reaches from above the table.

    A point counts when its normal, or one of ``directions`` rays (upper hemisphere, at
    least ``min_elevation_deg`` above the table, within ``max_incidence_deg`` of the point's
    normal), leaves the part without meeting it again.

    Returns
    -------
    ndarray, shape (M,), bool
    """
    p = np.asarray(points_base, dtype=np.float64)
    nrm = np.asarray(normals_base, dtype=np.float64)
    dirs = fibonacci_hemisphere(directions, min_elevation_deg)
    cos_max = np.cos(np.radians(max_incidence_deg))
    seen = np.zeros(len(p), dtype=bool)
    # First along each point's own normal (the bottom of a narrow bore escapes only near it).
    up = np.flatnonzero(nrm[:, 2] >= np.sin(np.radians(min_elevation_deg)))
    t, _ = part.cast(p[up] + _LIFT_MM * nrm[up], nrm[up])
    seen[up[~np.isfinite(t)]] = True
    for d in dirs:
        todo = np.flatnonzero(~seen & (nrm @ d >= cos_max))
        if not len(todo):
            continue
        start = p[todo] + _LIFT_MM * nrm[todo]
        t, _ = part.cast(start, np.broadcast_to(d, (len(todo), 3)))
        seen[todo[~np.isfinite(t)]] = True
    return seen


def measured_by_cloud(
    points: NDArray[np.float64], cloud: NDArray[np.float64], radius_mm: float
) -> NDArray[np.bool_]:
    """Which surface samples ``(M, 3)`` a scanned cloud ``(N, 3)`` (same frame) has a point
    within ``radius_mm`` of: the achieved counterpart of :func:`sweep_coverage`."""
    if radius_mm <= 0:
        raise ValueError(f"radius_mm: expected > 0, got {radius_mm}")
    if not len(cloud):
        return np.zeros(len(points), dtype=bool)
    dist, _ = cKDTree(np.asarray(cloud, dtype=np.float64)).query(
        np.asarray(points, dtype=np.float64), distance_upper_bound=radius_mm
    )
    return np.isfinite(dist)
