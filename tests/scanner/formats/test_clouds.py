"""Clouds on disk: what is written reads back, and a file that lies about itself is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from scanner.core.fileio import InputError
from scanner.formats.clouds import read_points, write_cloud


def _cloud(n: int = 500) -> np.ndarray:
    return np.random.default_rng(0).uniform(-50, 50, size=(n, 3))


def build_tensor_cloud(points: np.ndarray) -> o3d.t.geometry.PointCloud:
    return o3d.t.geometry.PointCloud(o3d.core.Tensor(points))


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".e57"])
def test_points_and_provenance_round_trip(tmp_path: Path, suffix: str):
    points = _cloud()
    path = write_cloud(tmp_path / f"c{suffix}", build_tensor_cloud(points), {"sessions": ["S"]})
    back, provenance = read_points(path)
    np.testing.assert_allclose(back, points, atol=1e-9)
    if suffix != ".e57":
        assert provenance["sessions"] == ["S"]


def test_a_truncated_binary_ply_is_refused(tmp_path: Path):
    path = write_cloud(tmp_path / "c.ply", build_tensor_cloud(_cloud(2000)))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated"):
        read_points(path)


def test_a_header_claiming_more_vertices_is_refused(tmp_path: Path):
    path = write_cloud(tmp_path / "c.ply", build_tensor_cloud(_cloud(2000)))
    data = path.read_bytes()
    path.write_bytes(data.replace(b"element vertex 2000", b"element vertex 20000", 1))
    with pytest.raises(InputError, match="declares"):
        read_points(path)


def test_an_ascii_ply_short_of_rows_is_refused(tmp_path: Path):
    rows = "\n".join("1 2 3" for _ in range(5))
    header = "ply\nformat ascii 1.0\nelement vertex 9\nproperty float x\nproperty float y\n"
    path = tmp_path / "a.ply"
    path.write_text(header + "property float z\nend_header\n" + rows + "\n")
    with pytest.raises(InputError, match="5 data lines, its header declares 9"):
        read_points(path)
    path.write_text(
        header.replace("vertex 9", "vertex 5") + "property float z\nend_header\n" + rows
    )
    assert read_points(path)[0].shape == (5, 3)


def test_not_a_ply_says_so(tmp_path: Path):
    path = tmp_path / "x.ply"
    path.write_text("hello")
    with pytest.raises(InputError, match="not a PLY file"):
        read_points(path)
