"""Small nominal parts and scans of them for the inspection tests (Open3D primitives)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from metrology.inspect.surface import NominalSurface
from scanner.formats.meshes import TriangleMesh


def box_mesh(size_mm: tuple[float, float, float] = (100.0, 60.0, 30.0)) -> TriangleMesh:
    """A closed box from the origin to ``size_mm``, outward normals."""
    m = o3d.geometry.TriangleMesh.create_box(*size_mm)
    return TriangleMesh(np.asarray(m.vertices), np.asarray(m.triangles).astype(np.int32))


def boss_part() -> TriangleMesh:
    """A 100 x 60 x 30 mm block with a cylindrical boss (r 8, h 20) off its centre: no symmetry."""
    box = o3d.geometry.TriangleMesh.create_box(100, 60, 30)
    boss = o3d.geometry.TriangleMesh.create_cylinder(8, 20, resolution=120)
    boss.translate((70, 20, 35))
    m = box + boss
    return TriangleMesh(np.asarray(m.vertices), np.asarray(m.triangles).astype(np.int32))


@dataclass(frozen=True)
class Scan:
    """A synthetic scan: the cloud (any frame) and the true ``nominal_from_cloud``."""

    points_cloud: NDArray
    nominal_from_cloud: NDArray
    true_deviation_mm: NDArray
    stray: NDArray


def random_pose(rng: np.random.Generator) -> NDArray:
    """Any yaw, tilts up to 10 deg, a few hundred mm away: ``cloud_from_nominal``."""
    pose = np.eye(4)
    angles = [rng.uniform(-180, 180), rng.uniform(-10, 10), rng.uniform(-10, 10)]
    pose[:3, :3] = Rotation.from_euler("zyx", angles, degrees=True).as_matrix()
    pose[:3, 3] = rng.uniform(-500, 500, 3)
    return pose


def scan_of(
    mesh: TriangleMesh,
    rng: np.random.Generator,
    *,
    count: int = 60_000,
    noise_mm: float = 0.02,
    stray_share: float = 0.0,
    bump: tuple[NDArray, float, float] | None = None,
) -> Scan:
    """Points on the faces seen from above and the sides (normal z > -0.5), with noise, an
    optional Gaussian bump ``(centre_nominal, amplitude_mm, sigma_mm)`` along the normal and
    stray points up to 3 mm off, moved by a random pose."""
    surface = NominalSurface(mesh)
    p, n = surface.sample(count, rng)
    seen = n[:, 2] > -0.5
    p, n = p[seen], n[seen]
    true = np.zeros(len(p))
    if bump is not None:
        centre, amplitude, sigma = bump
        true = amplitude * np.exp(-np.sum((p - centre) ** 2, axis=1) / (2 * sigma**2))
    p = p + n * (true + rng.normal(0.0, noise_mm, len(p)))[:, None]
    stray = np.zeros(len(p), bool)
    n_stray = int(stray_share * len(p))
    if n_stray:
        pick = rng.choice(len(p), n_stray, replace=False)
        p[pick] += n[pick] * rng.uniform(0.5, 3.0, n_stray)[:, None]
        stray[pick] = True
    cloud_from_nominal = random_pose(rng)
    cloud = p @ cloud_from_nominal[:3, :3].T + cloud_from_nominal[:3, 3]
    return Scan(cloud, np.linalg.inv(cloud_from_nominal), true, stray)
