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

__all__ = ["MESH_SUFFIXES", "MeshRaycaster", "TriangleMesh", "read_mesh", "write_mesh"]

MESH_SUFFIXES = (".stl", ".ply", ".obj")

#: No coordinate of a part is farther than this from its origin (mm): a workspace bound.
_SIZE_LIMIT_MM = 1.0e5

#: Open3D's "no primitive" id.
_INVALID_ID = o3d.t.geometry.RaycastingScene.INVALID_ID


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

    def transformed(self, world_from_mesh: NDArray[np.float64]) -> TriangleMesh:
        """The same mesh with its vertices moved by a 4x4 rigid ``world_from_mesh``."""
        m = np.asarray(world_from_mesh, dtype=np.float64)
        return TriangleMesh(self.vertices @ m[:3, :3].T + m[:3, 3], self.triangles)

    def section(self, normal: NDArray[np.float64], d: float, step_mm: float) -> NDArray[np.float64]:
        """Points ``(M, 3)`` about every ``step_mm`` along the cut by ``normal . p + d = 0``.

        Each triangle the plane crosses gives one segment, sampled at the middles of
        ``ceil(length / step_mm)`` equal pieces (so shared edges give no duplicates).
        """
        s = self.vertices @ np.asarray(normal, dtype=np.float64) + d
        above = s[self.triangles] > 0
        crossed = above.any(axis=1) & ~above.all(axis=1)
        tri = self.triangles[crossed]
        st, ab = s[tri], above[crossed]
        ends = []
        for i, j in ((0, 1), (1, 2), (2, 0)):
            cut = ab[:, i] != ab[:, j]
            w = np.where(cut, st[:, i] / np.where(cut, st[:, i] - st[:, j], 1.0), np.nan)
            vi, vj = self.vertices[tri[:, i]], self.vertices[tri[:, j]]
            ends.append(vi + w[:, None] * (vj - vi))
        ends_arr = np.stack(ends, axis=1)  # (K, 3 edges, 3); exactly two edges are cut
        valid = ~np.isnan(ends_arr[:, :, 0])
        order = np.argsort(~valid, axis=1, kind="stable")[:, :2]
        a = np.take_along_axis(ends_arr, order[:, :1, None], axis=1)[:, 0]
        b = np.take_along_axis(ends_arr, order[:, 1:2, None], axis=1)[:, 0]
        length = np.linalg.norm(b - a, axis=1)
        count = np.maximum(1, np.ceil(length / step_mm)).astype(np.int64)
        seg = np.repeat(np.arange(len(a)), count)
        start = np.repeat(np.cumsum(count) - count, count)
        frac = (np.arange(len(seg)) - start + 0.5) / count[seg]
        return a[seg] + frac[:, None] * (b[seg] - a[seg])


class MeshRaycaster:
    """Rays and closest points against a triangle mesh, through Open3D's ray-casting scene.

    Open3D casts in float32; every hit is then recomputed in float64 on the plane of the
    triangle it found, so a ray towards a point of the surface ends at ``t = 1`` to about
    1e-12 (shadow and occlusion tests can use a tight tolerance). Picklable: the scene is
    rebuilt in the process that uses it.

    Parameters
    ----------
    mesh : TriangleMesh
        In the frame the rays are given in, mm.
    """

    def __init__(self, mesh: TriangleMesh) -> None:
        self.mesh = mesh
        self._normals = mesh.face_normals()
        self._v0 = mesh.vertices[mesh.triangles[:, 0]]
        self._scene: o3d.t.geometry.RaycastingScene | None = None

    def __reduce__(self) -> tuple[type, tuple[TriangleMesh]]:
        return (MeshRaycaster, (self.mesh,))

    def _get_scene(self) -> o3d.t.geometry.RaycastingScene:
        if self._scene is None:
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(
                o3d.core.Tensor(self.mesh.vertices.astype(np.float32)),
                o3d.core.Tensor(self.mesh.triangles.astype(np.uint32)),
            )
            self._scene = scene
        return self._scene

    def cast(
        self, origin: NDArray[np.float64], dirs: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """First hit of each ray ``origin + t * dirs``.

        Parameters
        ----------
        origin : ndarray, shape (3,) or (N, 3)
        dirs : ndarray, shape (N, 3)
            Any length: ``t`` is in units of it.

        Returns
        -------
        t : ndarray, shape (N,)
            ``inf`` where the ray misses (or only grazes behind its origin).
        triangle : ndarray, shape (N,)
            Index of the triangle hit, -1 on a miss.
        """
        d = np.asarray(dirs, dtype=np.float64)
        o = np.broadcast_to(np.asarray(origin, dtype=np.float64), d.shape)
        if not len(d):
            return np.zeros(0), np.zeros(0, dtype=np.int64)
        rays = o3d.core.Tensor(np.hstack([o, d]).astype(np.float32))
        ans = self._get_scene().cast_rays(rays)
        tri = ans["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(ans["t_hit"].numpy()) & (tri != _INVALID_ID)
        tri = np.where(hit, tri, -1)
        t = np.full(len(d), np.inf)
        k = np.flatnonzero(hit)
        n = self._normals[tri[k]]
        den = np.einsum("ij,ij->i", n, d[k])
        num = np.einsum("ij,ij->i", n, self._v0[tri[k]] - o[k])
        ok = np.abs(den) > 1e-12 * np.linalg.norm(d[k], axis=1)
        t_exact = np.where(ok, num / np.where(ok, den, 1.0), ans["t_hit"].numpy()[k])
        t[k] = np.where(t_exact > 0, t_exact, np.inf)
        tri[k[t_exact <= 0]] = -1
        return t, tri

    def closest_triangles(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        """Index ``(N,)`` of the triangle nearest each of ``points`` ``(N, 3)``."""
        p = np.asarray(points, dtype=np.float64)
        if not len(p):
            return np.zeros(0, dtype=np.int64)
        ans = self._get_scene().compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))
        return ans["primitive_ids"].numpy().astype(np.int64)

    def normals_at(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Outward unit normals ``(N, 3)`` of the triangles nearest ``points`` ``(N, 3)``."""
        return self._normals[self.closest_triangles(points)]


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
