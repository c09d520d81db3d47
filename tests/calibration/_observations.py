"""Ideal concentric-target observations of a known camera: what a perfect detector reports.

Shared by the intrinsics, camera-model and symmetry tests.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from calibration.detection.conics import fit_conic, fit_line, harmonic_conjugate
from calibration.detection.observations import AxisObservation, RingObservation, TargetObservation
from scanner.core.conventions import make_transform

SIZE = (1280, 1024)
K_TRUE = np.array([[1800.0, 0.0, 652.3], [0.0, 1797.5, 498.7], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.12, 0.08, 0.0005, -0.0003, -0.01])
RADII = np.linspace(20.0, 60.0, 10)


def poses(n: int, rng: np.random.Generator, max_tilt_deg: float = 45.0) -> list[np.ndarray]:
    out = []
    face = Rotation.from_euler("x", 180, degrees=True)
    for i in range(n):
        u = (0.15 + 0.7 * ((i % 5) + rng.uniform(0.2, 0.8)) / 5) * SIZE[0]
        v = (0.15 + 0.7 * (((i // 5) % 4) + rng.uniform(0.2, 0.8)) / 4) * SIZE[1]
        ray = np.linalg.solve(K_TRUE, [u, v, 1.0])
        ray /= np.linalg.norm(ray)
        align, _ = Rotation.align_vectors([[0, 0, 1.0]], [ray])
        tilt = np.radians(max_tilt_deg) * np.sqrt(rng.uniform(0.05, 1.0))
        az = rng.uniform(0, 2 * np.pi)
        rot = (
            align.inv()
            * Rotation.from_rotvec(tilt * np.array([np.cos(az), np.sin(az), 0.0]))
            * face
            * Rotation.from_euler("z", rng.uniform(0, 360), degrees=True)
        )
        out.append(make_transform(rot, ray * 350.0 * rng.uniform(0.9, 1.1)))
    return out


def project(T: np.ndarray, pts_t: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    rvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    uv, _ = cv2.projectPoints(pts_t.reshape(-1, 1, 3), rvec, T[:3, 3], K, dist)
    return uv.reshape(-1, 2)


def synthetic_observation(
    T: np.ndarray, K: np.ndarray, dist: np.ndarray, rng: np.random.Generator, noise_px: float
) -> TargetObservation:
    """What a perfect detector reports for one view, plus Gaussian noise on the edge points."""
    rings = []
    for k, r in enumerate(RADII):
        th = np.linspace(0, 2 * np.pi, 360, endpoint=False)
        pts = project(T, np.column_stack([r * np.cos(th), r * np.sin(th), 0 * th]), K, dist)
        inside = (
            (pts[:, 0] > 5)
            & (pts[:, 0] < SIZE[0] - 6)
            & (pts[:, 1] > 5)
            & (pts[:, 1] < SIZE[1] - 6)
        )
        pts = pts[inside] + rng.normal(0, noise_px, (int(inside.sum()), 2))
        rings.append(RingObservation(float(r), pts, fit_conic(pts, geometric=False), k))
    axes = []
    s = np.r_[np.linspace(-58, -3, 30), np.linspace(3, 58, 30)]
    for name, col in (("x", 0), ("y", 1)):
        p = np.zeros((len(s), 3))
        p[:, col] = s
        uv = project(T, p, K, dist) + rng.normal(0, noise_px, (len(s), 2))
        axes.append(AxisObservation(name, uv, fit_line(uv)))
    pts_t = [np.zeros(3)]
    for r in RADII:
        pts_t += [
            np.array([r, 0, 0]),
            np.array([-r, 0, 0]),
            np.array([0, r, 0]),
            np.array([0, -r, 0]),
        ]
    pts_t = np.asarray(pts_t)
    uv = project(T, pts_t, K, dist)
    named = {"O": uv[0], "A": uv[-4], "B": uv[-3], "C": uv[-2], "D": uv[-1]}
    vps = {
        "p": harmonic_conjugate(named["A"], named["B"], named["O"]),
        "q": harmonic_conjugate(named["C"], named["D"], named["O"]),
    }
    return TargetObservation(
        ok=True,
        reason="",
        image_size=SIZE,
        kind="concentric_circles",
        points_px=uv,
        points_target=pts_t,
        rings=rings,
        axis_points=axes,
        center_px=uv[0],
        named_px=named,
        vanishing_points=vps,
    )
