"""A synthetic laser sweep over a ball on a table, exact to the pixel: robot stops, the
calibration that made the cloud, and each point's stop (a :class:`ScanGeometry`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from scanner.core.camera import CameraModel
from scanner.core.conventions import make_transform
from scanner.formats.calibration_file import Calibration
from scanner.scanning.geometry import ScanGeometry
from scanner.scanning.triangulate import Triangulator
from tests.scanner.scanning.test_triangulate import _calibration

BALL_CENTER = np.array([0.0, 0.0, 0.0])
BALL_RADIUS = 12.7
PLAN = """
name = "ball on a table"
threshold_mm = 0.3
instrument = { probing_size_mm = 0.004, sphere_spacing_mm = 0.004 }

[[features]]
name = "ball"
kind = "sphere"
region = { seed_mm = [0.0, 0.0, 0.0], radius_mm = 15.0 }
nominal = { center_mm = [0.0, 0.0, 0.0], diameter_mm = 25.4 }

[[features]]
name = "table"
kind = "plane"
region = { box_min_mm = [-40.0, -40.0, -16.0], box_max_mm = [40.0, 40.0, -9.5] }
nominal = { normal = [0.0, 0.0, 1.0] }

[[measurements]]
name = "ball diameter"
type = "diameter"
features = ["ball"]
nominal = 25.4
tolerance = 0.05

[[measurements]]
name = "ball height"
type = "distance"
features = ["ball", "table"]
nominal = 12.7
tolerance = 0.05

[[measurements]]
name = "table flatness"
type = "flatness"
features = ["table"]
tolerance = 0.5
"""


@dataclass
class Sweep:
    calibration: Calibration
    base_from_flange: np.ndarray  # (F, 4, 4)
    pixels: np.ndarray  # (N, 2) exact
    frame_index: np.ndarray  # (N,)

    def geometry(self) -> ScanGeometry:
        return ScanGeometry(self.calibration, self.base_from_flange, self.frame_index)

    def points(
        self,
        rng: np.random.Generator | None = None,
        noise_px: float = 0.0,
        robot_mm: float = 0.0,
        robot_deg: float = 0.0,
    ) -> np.ndarray:
        """The cloud the scanner makes: pixel noise, and the robot missing each stop."""
        uv = self.pixels.copy()
        poses = self.base_from_flange.copy()
        if rng is not None and noise_px:
            uv += rng.normal(0.0, noise_px, uv.shape)
        if rng is not None and (robot_mm or robot_deg):
            for i in range(len(poses)):
                miss = make_transform(
                    Rotation.from_rotvec(rng.normal(0, np.radians(robot_deg), 3)),
                    rng.normal(0, robot_mm, 3),
                )
                poses[i] = poses[i] @ miss
        return Triangulator(self.calibration, grid_step_px=0).points_base(
            uv, self.frame_index, poses
        )


def ball_sweep(stops: int = 120, step_mm: float = 0.3) -> Sweep:
    """The camera 300 mm above the table looking down, the sweep across the stripe."""
    cal = _calibration(dist=(-0.1, 0.05, 0.0, 0.0, 0.0))
    cam = CameraModel(cal.width, cal.height, cal.K, cal.dist)
    n, d = cal.light_plane.normal, cal.light_plane.d
    look_down = Rotation.from_matrix(np.diag([1.0, -1.0, -1.0]))
    poses, pixels, frames = [], [], []
    for i, x in enumerate((np.arange(stops) - stops / 2) * step_mm):
        base_from_cam = make_transform(look_down, [x, 0.0, 300.0 - 12.7])
        cam_from_base = np.linalg.inv(base_from_cam)
        poses.append(base_from_cam @ np.linalg.inv(cal.flange_from_cam))
        c = cam_from_base[:3, :3] @ BALL_CENTER + cam_from_base[:3, 3]
        # the stripe on the table (z = -12.7 in the base: the ball rests on it)
        table_n = cam_from_base[:3, :3] @ np.array([0.0, 0.0, 1.0])
        table_d = -(
            table_n
            @ (cam_from_base[:3, :3] @ np.array([0, 0, -BALL_RADIUS]) + cam_from_base[:3, 3])
        )
        direction = np.cross(n, table_n)
        direction /= np.linalg.norm(direction)
        a = np.array([n, table_n, direction])
        p0 = np.linalg.solve(a, [-d, -table_d, 0.0])
        line = p0 + np.outer(np.linspace(-35, 35, 140), direction)
        pts = [line[np.linalg.norm((line - c)[:, :2], axis=1) > BALL_RADIUS + 1.0]]
        t = n @ c + d
        if abs(t) < BALL_RADIUS - 0.5:
            q, rho = c - t * n, np.sqrt(BALL_RADIUS**2 - t**2)
            e1 = np.cross(n, [0.0, 0.0, 1.0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(n, e1)
            ang = np.linspace(0, 2 * np.pi, 200, endpoint=False)
            ring = q + rho * (np.outer(np.cos(ang), e1) + np.outer(np.sin(ang), e2))
            facing = np.einsum("ij,ij->i", ring - c, ring) < -0.2 * rho * np.linalg.norm(
                ring, axis=1
            )
            pts.append(ring[facing])
        p = np.vstack(pts)
        pixels.append(cam.project(p))
        frames.append(np.full(len(p), i))
    return Sweep(cal, np.stack(poses), np.vstack(pixels), np.concatenate(frames))
