"""The nominal surface as a distance field: closest points, signed distances, area sampling.

Open3D's :class:`~open3d.t.geometry.RaycastingScene` answers the closest-point queries (a BVH,
float32 inside); the signed distance is then computed in float64 from the closest face's plane
where the closest point lies inside that face, and from the closest point itself on its edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from scanner.formats.meshes import TriangleMesh

__all__ = ["Closest", "NominalSurface"]


@dataclass(frozen=True)
class Closest:
    """Closest nominal points of a set of query points.

    Attributes
    ----------
    points : ndarray, shape (N, 3)
        Closest points on the surface, nominal frame, mm.
    normals : ndarray, shape (N, 3)
        Unit outward normals of the faces they lie on.
    faces : ndarray, shape (N,)
        Indices of those faces.
    signed_mm : ndarray, shape (N,)
        Signed distance: positive on the side the face normal points to (outside).
    """

    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    faces: NDArray[np.int64]
    signed_mm: NDArray[np.float64]


class NominalSurface:
    """A triangle mesh ready for distance queries.

    Parameters
    ----------
    mesh : TriangleMesh
        The nominal, its own frame, mm; normals outward (counter-clockwise triangles).
    """

    def __init__(self, mesh: TriangleMesh) -> None:
        self.mesh = mesh
        self.face_normals = mesh.face_normals()
        self._first_vertex = mesh.vertices[mesh.triangles[:, 0]]
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(mesh.vertices.astype(np.float32)),
            o3d.core.Tensor(mesh.triangles.astype(np.uint32)),
        )
        lower, upper = mesh.bounds()
        self.lower, self.upper = lower, upper
        self.diagonal_mm = float(np.linalg.norm(upper - lower))
        self.centre = 0.5 * (lower + upper)

    def corners(self) -> NDArray[np.float64]:
        """The 8 corners ``(8, 3)`` of the nominal's bounding box (its extremities)."""
        lo, hi = self.lower, self.upper
        return np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )

    def closest(self, points_nominal: NDArray) -> Closest:
        """Closest surface points of ``points_nominal`` ``(N, 3)`` and their signed distances."""
        p = np.asarray(points_nominal, dtype=np.float64)
        answer = self._scene.compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))
        q = answer["points"].numpy().astype(np.float64)
        faces = answer["primitive_ids"].numpy().astype(np.int64)
        n = self.face_normals[faces]
        along_normal = np.einsum("ij,ij->i", p - self._first_vertex[faces], n)
        distance = np.linalg.norm(p - q, axis=1)
        # Inside a face the plane distance is exact in float64; on an edge or a vertex the
        # closest point is, with the side the face's normal gives.
        on_face = np.abs(distance - np.abs(along_normal)) < 1e-4
        sign = np.where(along_normal >= 0, 1.0, -1.0)
        signed = np.where(on_face, along_normal, sign * distance)
        return Closest(q, n, faces, signed)

    def sample(self, count: int, rng: np.random.Generator) -> tuple[NDArray, NDArray]:
        """``count`` points uniform by area and their outward normals, each ``(count, 3)``."""
        return self.mesh.sample_surface(count, rng)
