"""Nominal meshes read from STL (binary, ASCII), PLY and OBJ, and refused when they are not."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from scanner.core.fileio import InputError
from scanner.formats.meshes import TriangleMesh, read_mesh, write_mesh
from scanner.virtual_cell.parts import box_mesh


@pytest.mark.parametrize(
    "name,ascii_", [("p.stl", False), ("p.stl", True), ("p.ply", False), ("p.obj", True)]
)
def test_mesh_round_trips_in_every_format(tmp_path: Path, name: str, ascii_: bool) -> None:
    mesh = box_mesh((10.0, 20.0, 30.0))
    path = tmp_path / name
    if name.endswith(".stl") and ascii_:
        path.write_text(_ascii_stl(mesh))  # as other CAD tools write it; Open3D cannot
    else:
        assert o3d.io.write_triangle_mesh(str(path), mesh.to_open3d(), write_ascii=ascii_)
    back = read_mesh(path)
    assert len(back.triangles) == 12
    lower, upper = back.bounds()
    np.testing.assert_allclose(lower, 0.0, atol=1e-6)
    np.testing.assert_allclose(upper, [10.0, 20.0, 30.0], atol=1e-5)
    assert back.face_areas().sum() == pytest.approx(2 * (200 + 300 + 600), rel=1e-6)
    # Normals point out of the box: the top face's normal is +z.
    top = back.face_normals()[back.vertices[back.triangles].mean(axis=1)[:, 2] > 29.9]
    np.testing.assert_allclose(top, [[0, 0, 1], [0, 0, 1]], atol=1e-9)


def _ascii_stl(mesh: TriangleMesh) -> str:
    lines = ["solid part"]
    for tri, n in zip(mesh.triangles, mesh.face_normals()):
        lines += [f"  facet normal {n[0]:e} {n[1]:e} {n[2]:e}", "    outer loop"]
        lines += [f"      vertex {v[0]:e} {v[1]:e} {v[2]:e}" for v in mesh.vertices[tri]]
        lines += ["    endloop", "  endfacet"]
    return "\n".join([*lines, "endsolid part", ""])


def test_write_mesh_then_read(tmp_path: Path) -> None:
    path = write_mesh(tmp_path / "b.stl", box_mesh())
    assert len(read_mesh(path).triangles) == 12


@pytest.mark.parametrize(
    "name,content,reason",
    [
        ("missing.stl", None, "not found"),
        ("part.step", b"ISO-10303-21;", "expected a mesh file"),
        ("empty.stl", b"", "expected a triangle mesh"),
        ("junk.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nend_header\n1 2\n", "triangle"),
        ("points.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "expected a triangle mesh"),
    ],
)
def test_bad_mesh_refused_with_file_and_reason(
    tmp_path: Path, name: str, content: bytes | None, reason: str
) -> None:
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputError) as info:
        read_mesh(path)
    assert str(path) in str(info.value)
    assert reason in str(info.value)


def test_degenerate_mesh_refused(tmp_path: Path) -> None:
    path = tmp_path / "flat.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    with pytest.raises(InputError, match="degenerate"):
        read_mesh(path)
