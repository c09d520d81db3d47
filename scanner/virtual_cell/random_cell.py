"""Randomised cells: another sensor on the same scene, drawn from a seeded generator.

:func:`randomised_cell` keeps a cell's scene (target, sweep objects, poses) and draws what
differs from sensor to sensor: the camera's focal length, principal point and lens
distortion, the laser's baseline and the tilt of its fan about the line from its origin to
where it crosses the optical axis, the hand-eye mounting, the robot's repeatability and the
sensor and speckle noise. The scene's plans (``configs/plans``) stay valid, so a benchmark can
ask whether what holds on one cell holds on sensors it was not tuned on.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from scanner.virtual_cell.cell import CellConfig

__all__ = ["randomised_cell"]


def _laser_plane(
    origin: np.ndarray, crossing: np.ndarray, in_plane: np.ndarray, tilt_rad: float
) -> tuple[float, float, float, float]:
    """The plane through ``origin`` and ``crossing`` that holds ``in_plane`` turned about their
    line by ``tilt_rad``; oriented so that ``d < 0`` (the camera on its negative side)."""
    axis = (crossing - origin) / np.linalg.norm(crossing - origin)
    e = in_plane - (in_plane @ axis) * axis
    e = Rotation.from_rotvec(tilt_rad * axis).apply(e / np.linalg.norm(e))
    n = np.cross(axis, e)
    n /= np.linalg.norm(n)
    d = -float(n @ origin)
    if d > 0:
        n, d = -n, -d
    return (float(n[0]), float(n[1]), float(n[2]), d)


def randomised_cell(base: CellConfig, rng: np.random.Generator) -> CellConfig:
    """``base`` with another sensor drawn from ``rng`` (see the module docstring).

    Ranges: focal length x0.85-1.15, principal point within 3 % of the image, k1 -0.2 to
    +0.02 with k2 0 to 0.12, laser baseline x0.8-1.2 and fan tilt +-8 deg, hand-eye mounting
    +-3 deg and +-5 mm, robot repeatability x0.5-1.5, read noise x0.7-1.5, speckle contrast
    0.15-0.35.
    """
    cam = base.camera
    f = float(cam.fx * rng.uniform(0.85, 1.15))
    camera = dataclasses.replace(
        cam,
        fx=f,
        fy=f * float(1.0 + rng.normal(0.0, 0.002)),
        cx=float(cam.width / 2 + rng.uniform(-0.03, 0.03) * cam.width),
        cy=float(cam.height / 2 + rng.uniform(-0.03, 0.03) * cam.height),
        dist=(
            float(rng.uniform(-0.2, 0.02)),
            float(rng.uniform(0.0, 0.12)),
            float(rng.normal(0.0, 3e-4)),
            float(rng.normal(0.0, 3e-4)),
            0.0,
        ),
    )
    laser = base.laser
    n0, o0 = laser.normal, laser.origin
    crossing = np.array([0.0, 0.0, -laser.d / n0[2]])  # where the fan meets the optical axis
    axis = (crossing - o0) / np.linalg.norm(crossing - o0)
    origin = o0 * rng.uniform(0.8, 1.2)
    plane = _laser_plane(origin, crossing, np.cross(n0, axis), np.radians(rng.uniform(-8, 8)))
    laser = dataclasses.replace(
        laser,
        plane=plane,
        origin_mm=(float(origin[0]), float(origin[1]), float(origin[2])),
        speckle_contrast=float(rng.uniform(0.15, 0.35)),
    )
    robot = base.robot
    mount = np.asarray(robot.flange_from_cam_matrix(), dtype=np.float64).copy()
    turn = Rotation.from_rotvec(np.radians(3.0) * rng.uniform(-1, 1, 3))
    mount[:3, :3] = mount[:3, :3] @ turn.as_matrix()
    mount[:3, 3] += rng.uniform(-5.0, 5.0, 3)
    robot = dataclasses.replace(
        robot,
        flange_from_cam=tuple(tuple(float(x) for x in row) for row in mount),
        repeatability_mm=float(robot.repeatability_mm * rng.uniform(0.5, 1.5)),
        repeatability_deg=float(robot.repeatability_deg * rng.uniform(0.5, 1.5)),
    )
    imaging = dataclasses.replace(
        base.imaging, read_noise_e=float(base.imaging.read_noise_e * rng.uniform(0.7, 1.5))
    )
    return dataclasses.replace(
        base,
        name=f"{base.name}-randomised",
        description=f"{base.description} (sensor randomised)",
        camera=camera,
        laser=laser,
        robot=robot,
        imaging=imaging,
    )
