"""`scanner inspect` as the contract (section 5) says: the result JSON, DEV.ply with every
point, the report beside; bad input refused in one line with exit 2, nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from scanner.app.cli import main
from scanner.formats.clouds import read_cloud, write_cloud
from scanner.formats.meshes import write_mesh
from scanner.virtual_cell.parts import boss_part, scan_part


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("inspect")
    rng = np.random.default_rng(3)
    scan = scan_part(boss_part(), rng, count=50_000, stray_share=0.005)
    cloud = root / "cloud.ply"
    write_cloud(cloud, o3d.t.geometry.PointCloud(o3d.core.Tensor(scan.points_cloud)))
    np.save(root / "truth.npy", scan.nominal_from_cloud)
    return {"root": root, "cloud": cloud, "nominal": write_mesh(root / "part.stl", boss_part())}


def _apply(a_from_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    return points_b @ a_from_b[:3, :3].T + a_from_b[:3, 3]


def test_inspect_writes_the_contracts_files(files: dict[str, Path], capsys) -> None:
    out, dev = files["root"] / "result.json", files["root"] / "dev.ply"
    argv = ["inspect", str(files["cloud"]), "--nominal", str(files["nominal"])]
    assert main([*argv, "--out", str(out), "--deviations", str(dev)]) == 0
    assert "inspect: PASS" in capsys.readouterr().out
    data = json.loads(out.read_text())
    assert data["format"] == "scan-inspection/1"
    assert data["nominal"] == str(files["nominal"])
    truth = np.load(files["root"] / "truth.npy")
    found = np.asarray(data["nominal_from_cloud"])
    points_cloud = read_cloud(files["cloud"]).point.positions.numpy().astype(np.float64)
    moved_mm = _apply(found, points_cloud) - _apply(truth, points_cloud)
    assert np.linalg.norm(moved_mm, axis=1).max() < 0.01  # pose error anywhere on the part
    assert {"method", "rms_mm", "points_used"} <= set(data["alignment"])
    assert {"mean", "rms", "min", "max", "p01", "p99"} == set(data["deviation_mm"])
    assert data["verdict"] == "pass"
    assert out.with_suffix(".html").is_file()
    cloud = read_cloud(dev)
    points = cloud.point.positions.numpy()
    assert len(points) == data["points"] == len(read_cloud(files["cloud"]).point.positions)
    assert cloud.point["deviation_mm"].numpy().dtype == np.float32
    outlier = cloud.point["outlier"].numpy().reshape(-1)
    assert outlier.dtype == np.uint8 and set(np.unique(outlier)) <= {0, 1}
    assert int(outlier.sum()) == data["outliers"] > 0
    header = dev.read_bytes()[:200].decode("ascii", "replace")
    assert "nominal frame" in header


@pytest.mark.parametrize(
    "argv,reason",
    [
        ("{cloud} --nominal {root}/missing.stl --out {root}/r.json", "nominal mesh not found"),
        ("{root}/none.ply --nominal {nominal} --out {root}/r.json", "point cloud not found"),
        ("{cloud} --nominal {nominal} --out {root}/r.txt", "expected a .json"),
        ("{cloud} --nominal {nominal} --out {root}/r.json --deviations {root}/d.xyz", ".ply"),
        ("{cloud} --nominal {nominal} --out {cloud}", "expected a .json"),
        ("{cloud} --nominal {nominal} --out {root}/r.json --spec {root}/nope.toml", "not found"),
        ("{cloud} --nominal {cloud} --out {root}/r.json", "expected a triangle mesh"),
    ],
)
def test_bad_input_is_refused_in_one_line_and_nothing_is_written(
    files: dict[str, Path], capsys, argv: str, reason: str
) -> None:
    before = sorted(p.name for p in files["root"].iterdir())
    args = argv.format(**{k: str(v) for k, v in files.items()}).split()
    assert main(["inspect", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and reason in err
    assert sorted(p.name for p in files["root"].iterdir()) == before
