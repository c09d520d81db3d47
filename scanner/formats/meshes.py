"""Nominal meshes on disk: STL (binary or ASCII), PLY and OBJ triangle meshes, mm.

Read through Open3D; a mesh is checked once here (triangles present, finite vertices, indices
in range, a plausible size) so that every later stage can take it as it is.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from scanner.core.fileio import InputError

__all__ = ["MESH_SUFFIXES", "TriangleMesh", "read_mesh", "write_mesh"]

MESH_SUFFIXES = (".stl", ".ply", ".obj")

#: No coordinate of a part is farther than this from its origin (mm): a workspace bound.
_SIZE_LIMIT_MM = 1.0e5


@dataclass(frozen=True)
class TriangleMesh:
    """A triangle mesh in its own frame, mm.

    Attributes
    ----------
    vertices : ndarray, shape (V, 3), float64
    triangles : ndarray, shape (T, 3), int32
        Vertex indices, counter-clockwise seen from outside (outward normals).
    """

    vertices: NDArray[np.float64]
    triangles: NDArray[np.int32]

    def face_normals(self) -> NDArray[np.float64]:
        """Unit normals ``(T, 3)`` of the triangles (zero for degenerate ones)."""
        v = self.vertices[self.triangles]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, length, out=np.zeros_like(n), where=length > 0)

    def face_areas(self) -> NDArray[np.float64]:
        """Areas ``(T,)`` of the triangles, mm²."""
        v = self.vertices[self.triangles]
        return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)

    def sample_surface(
        self, count: int, rng: np.random.Generator
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``count`` points uniform by area and their outward normals, each ``(count, 3)``."""
        areas = self.face_areas()
        faces = rng.choice(len(areas), size=count, p=areas / areas.sum())
        u, v = rng.random(count), rng.random(count)
        flip = u + v > 1
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        tri = self.vertices[self.triangles[faces]]
        points = (
            tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
        )
        return points, self.face_normals()[faces]

    def to_open3d(self) -> o3d.geometry.TriangleMesh:
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices),
            o3d.utility.Vector3iVector(self.triangles.astype(np.int32)),
        )
        mesh.compute_triangle_normals()
        return mesh

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Axis-aligned bounds (lower, upper) of the vertices used by triangles."""
        used = self.vertices[np.unique(self.triangles)]
        return used.min(axis=0), used.max(axis=0)


def read_mesh(path: str | os.PathLike[str]) -> TriangleMesh:
    """Read and check a triangle mesh (``.stl`` binary or ASCII, ``.ply``, ``.obj``).

    Raises
    ------
    InputError
        Missing file, unknown extension, unreadable file, no triangles, non-finite vertices,
        indices out of range, or coordinates beyond the workspace bound.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "nominal mesh not found")
    ext = p.suffix.lower()
    if ext not in MESH_SUFFIXES:
        raise InputError(p, f"expected a mesh file ({', '.join(MESH_SUFFIXES)}), got {ext!r}")
    try:
        mesh = o3d.io.read_triangle_mesh(str(p), enable_post_processing=False, print_progress=False)
    except (RuntimeError, UnicodeDecodeError) as exc:
        raise InputError(p, f"cannot read mesh ({exc})") from None
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    triangles = np.asarray(mesh.triangles, dtype=np.int64)
    if len(triangles) == 0 or len(vertices) < 3:
        raise InputError(
            p,
            f"expected a triangle mesh, got {len(vertices)} vertices and {len(triangles)} triangles",
        )
    if not np.all(np.isfinite(vertices)):
        raise InputError(p, "expected finite vertex coordinates, got NaN or inf")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise InputError(p, f"triangle indices out of range (0..{len(vertices) - 1})")
    if np.abs(vertices).max() > _SIZE_LIMIT_MM:
        raise InputError(p, f"expected coordinates within ±{_SIZE_LIMIT_MM:g} mm, got larger")
    result = TriangleMesh(vertices, triangles.astype(np.int32))
    if not np.any(result.face_areas() > 0):
        raise InputError(p, "every triangle is degenerate (zero area)")
    return result


def write_mesh(path: str | os.PathLike[str], mesh: TriangleMesh) -> Path:
    """Write ``mesh`` (binary STL or PLY, ASCII OBJ, by extension); not atomic: for fixtures
    and generated parts."""
    p = Path(path)
    if p.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"{p}: expected a mesh extension {', '.join(MESH_SUFFIXES)}")
    o3d_mesh = mesh.to_open3d()
    if not o3d.io.write_triangle_mesh(str(p), o3d_mesh, write_ascii=False):
        raise OSError(f"{p}: Open3D could not write the mesh")
    return p
