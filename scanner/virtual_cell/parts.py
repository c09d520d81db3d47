"""Nominal parts and simulated scans of them, with their truth (for inspection tests, the
inspection benchmark and trying ``scanner inspect`` without a part at hand).

A scan here is the cloud a well-calibrated scanner would give: points on the faces a sensor
above sees (the top and the sides), Gaussian noise along the surface normal, optional stray
points off the surface and optional smooth bumps and dents (known form errors), all moved into an
arbitrary cloud frame. The truth is ``nominal_from_cloud`` and each point's true deviation.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import manifold3d
import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from scanner.formats.meshes import TriangleMesh, write_mesh

__all__ = [
    "SAMPLE_PARTS",
    "PartScan",
    "boss_part",
    "box_mesh",
    "bracket_part",
    "flange_part",
    "pinned_block",
    "random_pose",
    "scan_part",
    "stepped_part",
    "write_sample_parts",
]


def _from_open3d(mesh: o3d.geometry.TriangleMesh) -> TriangleMesh:
    return TriangleMesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles).astype(np.int32))


def box_mesh(size_mm: tuple[float, float, float] = (100.0, 60.0, 30.0)) -> TriangleMesh:
    """A closed box from the origin to ``size_mm``, outward normals."""
    return _from_open3d(o3d.geometry.TriangleMesh.create_box(*size_mm))


def boss_part() -> TriangleMesh:
    """A 100 x 60 x 30 mm block with a cylindrical boss (r 8, h 20) off its centre: no symmetry."""
    boss = o3d.geometry.TriangleMesh.create_cylinder(8, 20, resolution=120)
    boss.translate((70, 20, 35))
    return _from_open3d(o3d.geometry.TriangleMesh.create_box(100, 60, 30) + boss)


def pinned_block(pin_radius_mm: float = 2.5, pin_height_mm: float = 3.0) -> TriangleMesh:
    """A 120 x 80 x 25 mm block with one small pin near a corner of its top.

    Nearly symmetric: without the pin the block fits itself in four poses on its top face, so
    the pin alone tells the alignment which one is right.
    """
    pin = o3d.geometry.TriangleMesh.create_cylinder(pin_radius_mm, pin_height_mm, resolution=60)
    pin.translate((100.0, 62.0, 25.0 + pin_height_mm / 2))
    return _from_open3d(o3d.geometry.TriangleMesh.create_box(120, 80, 25) + pin)


_SEGMENTS = 96  # facets of a full circle: 0.05 mm chord error on a 20 mm radius


def _solid(body: manifold3d.Manifold) -> TriangleMesh:
    mesh = body.to_mesh()
    return TriangleMesh(
        np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3],
        np.asarray(mesh.tri_verts, dtype=np.int32),
    )


def _cube(size: tuple[float, float, float], at: tuple[float, float, float]) -> manifold3d.Manifold:
    return manifold3d.Manifold.cube(size).translate(at)


def _cylinder(radius: float, height: float, at: tuple[float, float, float]) -> manifold3d.Manifold:
    """A z-axis cylinder standing on ``at``."""
    return manifold3d.Manifold.cylinder(height, radius, radius, _SEGMENTS).translate(at)


def bracket_part() -> TriangleMesh:
    """The sample part: a machined bracket, 120 x 80 mm, 50 mm high, standing on z = 0.

    A 20 mm base plate with a rectangular pocket (40 x 30, 8 deep), a 12 mm through hole and
    a boss (18 mm, 12 high, with a 8 mm blind bore); a 15 mm upright wall along the back with
    a 10 mm cross hole. One closed, oriented solid (exact CSG by Manifold).
    """
    body = _cube((120, 80, 20), (0, 0, 0)) + _cube((120, 15, 50), (0, 65, 0))
    body -= _cube((40, 30, 10), (15, 15, 12))
    body -= _cylinder(6, 40, (85, 30, -10))
    body += _cylinder(9, 12, (100, 45, 20))
    body -= _cylinder(4, 20, (100, 45, 22))
    cross = manifold3d.Manifold.cylinder(40, 5, 5, _SEGMENTS).rotate((-90, 0, 0))
    body -= cross.translate((30, 55, 35))
    return _solid(body)


def stepped_part() -> TriangleMesh:
    """A stepped block: three 15 mm steps of 90, 60 and 30 mm depth, 70 mm wide, on z = 0."""
    body = _cube((90, 70, 15), (0, 0, 0))
    body += _cube((60, 70, 15), (30, 0, 15))
    body += _cube((30, 70, 15), (60, 0, 30))
    return _solid(body)


def flange_part() -> TriangleMesh:
    """A round flange: 100 mm disc 10 high, a 50 mm hub 20 high above it with a 30 mm bore
    through both, and six 14 mm bolt holes on an 80 mm circle; centred on the z axis."""
    body = _cylinder(50, 10, (0, 0, 0)) + _cylinder(25, 20, (0, 0, 10))
    body -= _cylinder(15, 60, (0, 0, -10))
    for k in range(6):
        a = np.pi / 3 * k
        body -= _cylinder(7, 30, (40 * np.cos(a), 40 * np.sin(a), -5))
    return _solid(body)


#: The parts the virtual cell ships (``configs/parts/<name>.stl`` is each one written out).
SAMPLE_PARTS = {"bracket": bracket_part, "stepped": stepped_part, "flange": flange_part}


@dataclass(frozen=True)
class PartScan:
    """A simulated scan and its truth.

    Attributes
    ----------
    points_cloud : ndarray, shape (N, 3)
        The points in the cloud frame, mm.
    nominal_from_cloud : ndarray, shape (4, 4)
        The true pose of the cloud in the nominal frame.
    true_deviation_mm : ndarray, shape (N,)
        The form error put into each point (bumps and dents), noise and strays excluded.
    stray : ndarray, shape (N,), bool
        The points moved 0.5-3 mm off the surface.
    """

    points_cloud: NDArray[np.float64]
    nominal_from_cloud: NDArray[np.float64]
    true_deviation_mm: NDArray[np.float64]
    stray: NDArray[np.bool_]


def random_pose(rng: np.random.Generator) -> NDArray[np.float64]:
    """Any yaw, tilts up to 10 deg, up to 500 mm off: a ``cloud_from_nominal``."""
    pose = np.eye(4)
    angles = [rng.uniform(-180, 180), rng.uniform(-10, 10), rng.uniform(-10, 10)]
    pose[:3, :3] = Rotation.from_euler("zyx", angles, degrees=True).as_matrix()
    pose[:3, 3] = rng.uniform(-500, 500, 3)
    return pose


def scan_part(
    mesh: TriangleMesh,
    rng: np.random.Generator,
    *,
    count: int = 60_000,
    noise_mm: float = 0.02,
    stray_share: float = 0.0,
    bumps: Sequence[tuple[NDArray[np.float64], float, float]] = (),
) -> PartScan:
    """Simulate a scan of ``mesh``.

    Parameters
    ----------
    mesh : TriangleMesh
        The nominal part, mm.
    rng : numpy.random.Generator
        The only source of randomness (sampling, noise, strays, pose).
    count : int
        Points drawn on the whole surface before the faces facing down are dropped.
    noise_mm : float
        Standard deviation of the noise along the surface normal.
    stray_share : float
        Share of the points moved 0.5-3 mm off the surface, outwards.
    bumps : sequence of (centre_nominal (3,), amplitude_mm, sigma_mm)
        Gaussian form errors along the normal (a negative amplitude is a dent).

    Returns
    -------
    PartScan
    """
    p, n = mesh.sample_surface(count, rng)
    seen = n[:, 2] > -0.5
    p, n = p[seen], n[seen]
    true = np.zeros(len(p))
    for centre, amplitude, sigma in bumps:
        true += amplitude * np.exp(-np.sum((p - centre) ** 2, axis=1) / (2 * sigma**2))
    p = p + n * (true + rng.normal(0.0, noise_mm, len(p)))[:, None]
    stray = np.zeros(len(p), bool)
    n_stray = int(stray_share * len(p))
    if n_stray:
        pick = rng.choice(len(p), n_stray, replace=False)
        p[pick] += n[pick] * rng.uniform(0.5, 3.0, n_stray)[:, None]
        stray[pick] = True
    cloud_from_nominal = random_pose(rng)
    cloud = p @ cloud_from_nominal[:3, :3].T + cloud_from_nominal[:3, 3]
    return PartScan(cloud, np.linalg.inv(cloud_from_nominal), true, stray)


def write_sample_parts(folder: Path) -> list[Path]:
    """Write every sample part as ``folder/<name>.stl`` (how ``configs/parts`` was made)."""
    folder.mkdir(parents=True, exist_ok=True)
    return [write_mesh(folder / f"{name}.stl", make()) for name, make in SAMPLE_PARTS.items()]


if __name__ == "__main__":
    for written in write_sample_parts(Path(__file__).resolve().parents[2] / "configs" / "parts"):
        print(written)
