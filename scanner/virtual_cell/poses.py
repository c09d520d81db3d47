"""Where the target and the robot go: random but realistic views, aimed stripes, sweep paths.

All views are ``cam_from_target`` transforms with the camera on the printed side of the target
(target +z towards the camera). Robot poses are ``base_from_flange``; the *actual* pose of a
robot stop differs from the commanded (reported) one by the repeatability error.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from scanner.core.conventions import invert_transform, make_transform, transform_points
from scanner.core.targets import ConcentricCirclesTarget, TargetSpec
from scanner.virtual_cell.cell import CellConfig

__all__ = [
    "aimed_view",
    "hand_held_view",
    "light_plane_view",
    "perturb_pose",
    "posed_view",
    "stripe_offset_mm",
    "sweep_poses",
    "target_extent_mm",
]

_MAX_TRIES = 2000


def perturb_pose(
    base_from_flange: NDArray, rng: np.random.Generator, sigma_mm: float, sigma_deg: float
) -> NDArray:
    """The actual pose of a robot stop commanded to ``base_from_flange``.

    The repeatability error is a small rigid motion in the flange frame: a translation with
    per-axis standard deviation ``sigma_mm`` and a rotation vector with per-axis standard
    deviation ``sigma_deg``.
    """
    rot = Rotation.from_rotvec(np.radians(sigma_deg) * rng.standard_normal(3))
    err = make_transform(rot, sigma_mm * rng.standard_normal(3))
    return base_from_flange @ err


def target_extent_mm(target: TargetSpec) -> tuple[NDArray, float]:
    """Centre (3,) and radius of the region of the target that carries the marks."""
    if isinstance(target, ConcentricCirclesTarget):
        return np.zeros(3), target.radius_mm
    pts = target.object_points()
    c = pts.mean(axis=0)
    return c, float(np.linalg.norm(pts - c, axis=1).max())


def _look_from(position_t: NDArray, aim_t: NDArray, roll: float) -> NDArray:
    """``cam_from_target`` of a camera at ``position_t`` looking at ``aim_t`` (target frame)."""
    z = aim_t - position_t
    z /= np.linalg.norm(z)
    x0 = np.cross([0.0, 1.0, 0.0], z) if abs(z[1]) < 0.9 else np.cross([1.0, 0.0, 0.0], z)
    x0 /= np.linalg.norm(x0)
    y0 = np.cross(z, x0)
    x = np.cos(roll) * x0 + np.sin(roll) * y0
    y = np.cross(z, x)
    target_from_cam = make_transform(np.column_stack([x, y, z]), position_t)
    return invert_transform(target_from_cam)


def stripe_offset_mm(cell: CellConfig, cam_from_target: NDArray) -> float:
    """Distance from the target centre O to the laser line on the target plane, mm (inf: none)."""
    n = cell.laser.normal
    rot, t = cam_from_target[:3, :3], cam_from_target[:3, 3]
    n_t = rot.T @ n
    d_t = cell.laser.d + n @ t
    g = float(np.hypot(n_t[0], n_t[1]))
    return abs(d_t) / g if g > 1e-9 else np.inf


def _in_view(
    cell: CellConfig, cam_from_target: NDArray, points_t: NDArray, margin_px: float
) -> bool:
    pc = transform_points(cam_from_target, points_t)
    if np.any(pc[:, 2] <= 10.0):
        return False
    cam = cell.camera_model()
    return bool(np.all(cam.in_image(cam.project(pc), margin_px)))


def hand_held_view(
    cell: CellConfig, rng: np.random.Generator, target: TargetSpec | None = None
) -> NDArray:
    """A target held by hand for the intrinsics, the way a calibration guide asks for it.

    Tilt up to ``capture.max_tilt_deg``, any in-plane rotation, at a distance drawn from
    ``capture.hand_held_distance`` (times the working distance), and the target's centre at a
    random place of the image: with probability ``capture.partial_view_fraction`` the card may
    run out of the image (at least half of its largest ring stays in view), so that ring
    edges reach the image's corners, where the distortion is strongest and otherwise only
    extrapolated; the other views show the whole target (the paper's method needs the
    diameters' end points). The centre O and the orientation marker always stay in view, and
    the laser line crosses the target.
    """
    spec = cell.target_spec() if target is None else target
    centre, radius = target_extent_mm(spec)
    wd = cell.capture.working_distance_mm
    near, far = cell.capture.hand_held_distance
    cam = cell.camera_model()
    needed = [centre]
    if isinstance(spec, ConcentricCirclesTarget):
        mx, my = spec.orientation_marker.center_mm
        needed.append(np.array([mx, my, 0.0]))
    needed_t = np.vstack(needed)
    angles = np.linspace(0.0, 2.0 * np.pi, 48, endpoint=False)
    outline_t = centre + radius * np.column_stack([np.cos(angles), np.sin(angles), 0.0 * angles])
    for _ in range(_MAX_TRIES):
        partial = rng.random() < cell.capture.partial_view_fraction
        tilt = np.radians(cell.capture.max_tilt_deg) * np.sqrt(rng.uniform(0.02, 1.0))
        az = rng.uniform(0, 2 * np.pi)
        dist = wd * rng.uniform(near, far)
        aim = centre + np.array([*rng.uniform(-0.3, 0.3, 2) * radius, 0.0])
        pos = aim + dist * np.array(
            [np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)]
        )
        c_t = _look_from(pos, aim, rng.uniform(0, 2 * np.pi))
        # Turn the camera about its centre so that the aimed point lands on a random pixel:
        # the target's tilt against its line of sight stays, its place in the image changes.
        u = rng.uniform(0.05, 0.95) * cam.width
        v = rng.uniform(0.05, 0.95) * cam.height
        ray = np.linalg.solve(cam.K, [u, v, 1.0])
        turn, _ = Rotation.align_vectors([ray], [[0.0, 0.0, 1.0]])
        c_t = make_transform(turn, np.zeros(3)) @ c_t
        if not _in_view(cell, c_t, needed_t, 40.0):
            continue
        outline_c = transform_points(c_t, outline_t)
        seen = cam.in_image(cam.project(outline_c), 2.0) & (outline_c[:, 2] > 10.0)
        if np.mean(seen) < (0.5 if partial else 1.0):
            continue
        if stripe_offset_mm(cell, c_t) > 0.75 * radius:
            continue
        return c_t
    raise RuntimeError("hand_held_view: no acceptable view found (check the cell geometry)")


def _point_on_plane(cell: CellConfig, rng: np.random.Generator, spread: float = 0.3) -> NDArray:
    """A random point of the light plane in the central part of the view, at working distance."""
    n, d = cell.laser.normal, cell.laser.d
    cam = cell.camera
    wd = cell.capture.working_distance_mm
    for _ in range(_MAX_TRIES):
        z = wd * rng.uniform(0.9, 1.1)
        u = cam.cx + rng.uniform(-spread, spread) * cam.width
        v = cam.cy + rng.uniform(-spread, spread) * cam.height
        p0 = np.array([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z])
        g = n[0] ** 2 + n[1] ** 2
        if g < 1e-6:
            continue
        f = n @ p0 + d
        p = p0 - f / g * np.array([n[0], n[1], 0.0])
        if cell.camera_model().in_image(cell.camera_model().project(p[None]), 60.0)[0]:
            return p
    raise RuntimeError("no point of the light plane in view at working distance")


def light_plane_view(cell: CellConfig, rng: np.random.Generator) -> NDArray:
    """The paper's light-plane stage: the diameter A-O-B lies in the light plane."""
    spec = cell.target_spec()
    _, radius = target_extent_mm(spec)
    n = cell.laser.normal
    for _ in range(_MAX_TRIES):
        o = _point_on_plane(cell, rng, 0.15)
        v = o / np.linalg.norm(o)
        x = np.cross(n, v)
        x /= np.linalg.norm(x)
        x = Rotation.from_rotvec(n * np.radians(rng.uniform(-20, 20))).apply(x)
        if rng.random() < 0.5:
            x = -x
        z = -v - (-v @ x) * x
        z /= np.linalg.norm(z)
        z = Rotation.from_rotvec(x * np.radians(rng.uniform(-40, 40))).apply(z)
        y = np.cross(z, x)
        c_t = make_transform(np.column_stack([x, y, z]), o)
        if -v @ z < np.cos(np.radians(60)):
            continue
        ends = np.array([[radius, 0, 0], [-radius, 0, 0], [0, 0, 0]])
        if _in_view(cell, c_t, ends, 15.0):
            return c_t
    raise RuntimeError("light_plane_view: no acceptable view found")


def posed_view(cell: CellConfig, rng: np.random.Generator) -> NDArray:
    """A robot view of the fixed target: tilt in ``capture.posed_tilt_deg``, stripe across it."""
    spec = cell.target_spec()
    centre, radius = target_extent_mm(spec)
    lo, hi = cell.capture.posed_tilt_deg
    wd = cell.capture.working_distance_mm
    for _ in range(_MAX_TRIES):
        tilt = np.radians(rng.uniform(lo, hi))
        az = rng.uniform(0, 2 * np.pi)
        dist = wd * rng.uniform(0.9, 1.1)
        aim = centre + np.array([*rng.uniform(-0.3, 0.3, 2) * radius, 0.0])
        pos = aim + dist * np.array(
            [np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)]
        )
        c_t = _look_from(pos, aim, rng.uniform(-np.pi, np.pi))
        if (
            _in_view(cell, c_t, centre[None, :], 60.0)
            and stripe_offset_mm(cell, c_t) < 0.7 * radius
        ):
            return c_t
    raise RuntimeError("posed_view: no acceptable view found")


def aimed_view(
    cell: CellConfig,
    rng: np.random.Generator,
    point_t: NDArray,
    tilt_range_deg: tuple[float, float] = (5.0, 30.0),
    ring_crossings_in_view: bool = False,
) -> NDArray:
    """A view whose light plane contains the target point ``point_t`` (e.g. O, A or C).

    The orientation is random (tilt in ``tilt_range_deg``, any roll); the translation puts the
    point on the light plane at a random place of the stripe in view; the centre O stays in view.
    ``ring_crossings_in_view`` also keeps the points E, F where the stripe meets the largest
    ring in view (the EF check).
    """
    spec = cell.target_spec()
    centre, radius = target_extent_mm(spec)
    lo, hi = tilt_range_deg
    point_t = np.asarray(point_t, dtype=np.float64)
    for _ in range(_MAX_TRIES):
        tilt = np.radians(rng.uniform(lo, hi))
        az = rng.uniform(0, 2 * np.pi)
        pos = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
        rot = _look_from(pos, np.zeros(3), rng.uniform(-np.pi, np.pi))[:3, :3]
        q = _point_on_plane(cell, rng, 0.3)
        c_t = make_transform(rot, q - rot @ point_t)
        needed = [centre, point_t]
        if isinstance(spec, ConcentricCirclesTarget):
            # The operator keeps the orientation disc in view: without it a view is labelled
            # only up to the quarter turns, and the paper's hand-eye needs views of O, A and C
            # labelled by the disc.
            mx, my = spec.orientation_marker.center_mm
            needed.append(np.array([mx, my, 0.0]))
        if ring_crossings_in_view:
            n_t = rot.T @ cell.laser.normal
            along = np.array([n_t[1], -n_t[0], 0.0])
            along /= np.linalg.norm(along)
            needed += [centre + radius * along, centre - radius * along]
        if _in_view(cell, c_t, np.vstack(needed), 40.0):
            return c_t
    raise RuntimeError("aimed_view: no acceptable view found")


def sweep_poses(cell: CellConfig, frames: int | None = None) -> tuple[NDArray, NDArray]:
    """Commanded ``base_from_cam`` of a linear sweep and its unit direction (base frame).

    ``frames`` (default the cell's) spreads that many frames over the cell's path.

    The camera looks straight down at the table from ``sweep.standoff_mm``; it is turned so
    that the laser line on the table is perpendicular to the travel (then yawed by
    ``sweep.yaw_deg``), and the path is centred so that the middle frame's line passes through
    ``sweep.center_mm``.

    Returns
    -------
    base_from_cam : ndarray, shape (F, 4, 4)
    direction : ndarray, shape (3,)
    """
    sw = cell.sweep
    count = sw.frames if frames is None else frames
    n = cell.laser.normal
    line_c = np.array([n[1], -n[0], 0.0])
    if np.linalg.norm(line_c) < 1e-6:
        raise ValueError(
            "sweep: the light plane is parallel to the image plane, no line on the table"
        )
    line_c /= np.linalg.norm(line_c)
    z_c = np.array([0.0, 0.0, 1.0])
    travel_c = np.cross(line_c, z_c)  # in the table plane, perpendicular to the line
    src = np.column_stack([travel_c, line_c, z_c])
    dst = np.column_stack([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    yaw = Rotation.from_euler("z", sw.yaw_deg, degrees=True).as_matrix()
    rot = yaw @ dst @ src.T
    h = sw.standoff_mm
    g = n[0] ** 2 + n[1] ** 2
    foot = np.array([0.0, 0.0, h]) - (n[2] * h + cell.laser.d) / g * np.array([n[0], n[1], 0.0])
    centre = np.asarray(sw.center_mm, dtype=np.float64)
    centre[2] = sw.table_z_mm
    c_mid = centre - rot @ foot
    direction = rot @ travel_c
    # Another frame count thins or densifies the cell's sweep over the same path: the objects
    # stay inside it (a shorter path would leave them out of the cloud).
    half_length = (sw.frames - 1) / 2 * sw.step_mm
    s = np.linspace(-half_length, half_length, count) if count > 1 else np.zeros(1)
    out = np.tile(np.eye(4), (count, 1, 1))
    out[:, :3, :3] = rot
    out[:, :3, 3] = c_mid + s[:, None] * direction
    return out, direction
