from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from metrology.measure import measure_cloud
from metrology.plan import load_plan
from scanner.app.cli import main
from scanner.core.config import CONFIG_DIR
from scanner.core.fileio import InputError
from scanner.formats.clouds import read_points

PAPER_PLAN = CONFIG_DIR / "plans" / "paper_sweep.toml"

# The paper cell's sweep objects (configs/cells/paper.toml), base frame, mm.
SPHERES = (np.array([650.0, -45.0, 45.0]), np.array([750.0, -45.0, 45.0]))
PLATE_CENTER_XY, PLATE_SIZE_XY, PLATE_YAW_DEG, PLATE_TOP_Z = (
    (700.0, 55.0),
    (100.0, 60.0),
    15.0,
    12.0,
)


def paper_scene(
    rng: np.random.Generator,
    noise_mm: float = 0.01,
    n: int = 12000,
    centers: tuple[np.ndarray, np.ndarray] = SPHERES,
    diameter_mm: float = 25.4,
    plate_top_z: float = PLATE_TOP_Z,
    plate_bump_mm: float = 0.0,
) -> np.ndarray:
    """What a scanner looking down sees of the paper cell: upper sphere caps, the bar's top,
    the plate's top face and the table around it, with Gaussian noise."""
    parts = []
    r = diameter_mm / 2
    for c in centers:
        d = rng.normal(size=(n // 4, 3))
        d /= np.linalg.norm(d, axis=1)[:, None]
        d[:, 2] = np.abs(d[:, 2])
        parts.append(c + r * d)
    th = rng.uniform(0, np.pi, n // 4)
    x = rng.uniform(662.7, 737.3, n // 4)
    parts.append(np.c_[x, -45 + 4 * np.cos(th), 45 + 4 * np.sin(th)])
    a = np.radians(PLATE_YAW_DEG)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    half = np.array(PLATE_SIZE_XY) / 2
    local = rng.uniform(-half, half, (n, 2))
    # a smooth bump of height plate_bump_mm in the middle of the plate
    z = plate_top_z + plate_bump_mm * np.exp(-np.sum((local / 15.0) ** 2, axis=1))
    parts.append(np.c_[local @ rot.T + PLATE_CENTER_XY, z])
    xy = rng.uniform([630, -150], [770, 150], (2 * n, 2))
    loc = (xy - PLATE_CENTER_XY) @ rot
    keep = ~np.all(np.abs(loc) < half, axis=1)
    parts.append(np.c_[xy[keep], np.zeros(keep.sum())])
    p = np.vstack(parts)
    return p + rng.normal(0.0, noise_mm, p.shape)


#: Tolerances for the synthetic scene's 10 µm noise (the shipped plan's suit the virtual scanner).
TIGHT_UPPER = {
    "sphere_1 diameter": 0.05,
    "sphere_2 diameter": 0.05,
    "sphere_1 form": 0.15,
    "bar diameter": 0.1,
    "plate flatness": 0.1,
    "table flatness": 0.1,
}


def tight_plan():
    """The paper plan with tolerances sized for the synthetic scene."""
    plan = load_plan(PAPER_PLAN)
    ms = tuple(
        dataclasses.replace(m, tolerance=TIGHT_UPPER.get(m.name, m.tolerance))
        for m in plan.measurements
    )
    return dataclasses.replace(plan, measurements=ms)


def rows_by_name(report) -> dict:
    return {r.name: r for r in report.rows}


def test_paper_scene_measures_within_tolerance():
    rng = np.random.default_rng(0)
    report = measure_cloud(paper_scene(rng), tight_plan())
    assert report.passed, report.summary()
    rows = rows_by_name(report)
    assert abs(rows["sphere spacing"].deviation) < 0.002
    assert abs(rows["sphere_1 diameter"].deviation) < 0.002
    assert abs(rows["sphere_1 height above table"].deviation) < 0.002
    assert abs(rows["plate thickness above table"].deviation) < 0.002
    assert abs(rows["bar diameter"].deviation) < 0.005
    assert rows["plate parallel to table"].actual < 0.01
    # flatness of pure noise: about 6-8 sigma wide, minimum zone below the LSQ range
    plate = next(f for f in report.features if f.spec.name == "plate").fit
    assert 0.04 < plate.min_zone_mm <= plate.range_mm
    assert rows["plate flatness"].actual == pytest.approx(plate.min_zone_mm)
    assert report.summary().startswith("PASS: 11 passed, 0 failed")
    # the deviations used for the picture are the fit residuals of the points used
    assert np.isfinite(report.deviations_mm).sum() == sum(f.fit.n_inliers for f in report.features)


def test_out_of_tolerance_geometry_fails_the_right_rows():
    rng = np.random.default_rng(1)
    moved = (SPHERES[0], SPHERES[1] + [0.3, 0.0, 0.0])  # spacing 100.3 mm
    report = measure_cloud(
        paper_scene(rng, centers=moved, plate_top_z=12.2, plate_bump_mm=0.15), tight_plan()
    )
    rows = rows_by_name(report)
    assert rows["sphere spacing"].final_status == "fail"
    assert rows["sphere spacing"].deviation == pytest.approx(0.3, abs=0.003)
    assert rows["plate flatness"].final_status == "fail"
    assert rows["plate thickness above table"].final_status == "fail"
    assert rows["sphere_1 diameter"].final_status == "pass"
    assert not report.passed
    assert report.n_failed == 3


def test_missing_feature_is_reported_not_raised():
    rng = np.random.default_rng(2)
    cloud = paper_scene(rng)
    far = np.linalg.norm(cloud - SPHERES[1], axis=1) > 20  # sphere_2 not scanned
    report = measure_cloud(cloud[far], PAPER_PLAN)
    rows = rows_by_name(report)
    assert rows["sphere_2 diameter"].final_status == "error"
    assert "sphere_2" in rows["sphere spacing"].note
    assert rows["sphere_1 diameter"].final_status == "pass"
    assert "failed fits: sphere_2" in report.summary()
    data = report.to_json()
    fit2 = next(f for f in data["features"] if f["name"] == "sphere_2")["fit"]
    assert fit2["ok"] is False and "too few points" in fit2["reason"]
    json.dumps(data, allow_nan=False)


def test_report_json_is_plain_and_complete():
    rng = np.random.default_rng(3)
    report = measure_cloud(paper_scene(rng), load_plan(PAPER_PLAN))
    data = json.loads(json.dumps(report.to_json(), allow_nan=False))
    assert data["format"] == "scan-measurement/1"
    assert data["result"] == "pass"
    assert data["summary"]["passed"] == 11
    assert len(data["measurements"]) == 11
    first = data["measurements"][0]
    assert set(first) >= {"name", "nominal", "actual", "deviation", "lower", "upper", "status"}
    assert {f["name"] for f in data["features"]} == {
        "sphere_1",
        "sphere_2",
        "bar",
        "plate",
        "table",
    }


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".npy", ".xyz", ".csv"])
def test_load_cloud_reads_each_format(tmp_path: Path, suffix: str):
    import open3d as o3d

    pts = np.random.default_rng(4).uniform(-100, 100, (50, 3))
    path = tmp_path / f"c{suffix}"
    if suffix in (".ply", ".pcd"):
        o3d.io.write_point_cloud(
            str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        )
    elif suffix == ".npy":
        np.save(path, pts)
    else:
        np.savetxt(path, pts, delimiter="," if suffix == ".csv" else " ")
    loaded, prov = read_points(path)
    assert loaded.shape == (50, 3)
    np.testing.assert_allclose(loaded, pts, atol=1e-4 if suffix == ".pcd" else 1e-9)
    assert prov == {}


def test_load_cloud_reads_the_scanner_provenance_record(tmp_path: Path):
    path = tmp_path / "c.ply"
    header = (
        "ply\nformat ascii 1.0\n"
        'obj_info {"calibration":"/x/calib.json","calibration_sha256":"abc"}\n'
        "element vertex 3\nproperty double x\nproperty double y\nproperty double z\nend_header\n"
        "0 0 0\n1 0 0\n0 1 0\n"
    )
    path.write_text(header)
    pts, prov = read_points(path)
    assert pts.shape == (3, 3)
    assert prov["calibration"] == "/x/calib.json"


@pytest.mark.parametrize(
    ("name", "content", "words"),
    [
        ("missing.ply", None, "not found"),
        ("c.obj", "v 0 0 0\n", "expected a cloud file"),
        ("c.xyz", "", "non-empty"),
        ("c.csv", "1,2\n3,4\n", r"got shape \(2, 2\)"),
        ("d.csv", "x,y,z\na,b,c\n", "cannot read point cloud"),
    ],
)
def test_load_cloud_refuses_bad_files(tmp_path: Path, name, content, words):
    path = tmp_path / name
    if content is not None:
        path.write_text(content)
    with pytest.raises(InputError, match=words):
        read_points(path)


def test_measure_command_writes_json_csv_html(tmp_path: Path, capsys, monkeypatch):
    monkeypatch.setenv("SCANNER_RENDERER", "matplotlib")  # keep the test quick
    cloud = tmp_path / "cloud.npy"
    np.save(cloud, paper_scene(np.random.default_rng(5), n=6000))
    out = tmp_path / "out" / "report.json"
    assert main(["measure", str(cloud), "--plan", "paper_sweep", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "measure: PASS: 11 passed, 0 failed" in printed
    data = json.loads(out.read_text())
    assert data["summary"]["failed"] == 0
    csv_lines = out.with_suffix(".csv").read_text().splitlines()
    assert csv_lines[0].startswith("name,unit,nominal,actual,deviation")
    assert len(csv_lines) == 12
    page = out.with_suffix(".html").read_text()
    assert page.startswith("<!DOCTYPE html>") and "Uncertainty budgets" in page
    # Issue #19: every value with u and U; a cloud without its stops gets the noise share
    # only, and the report says what is missing.
    m = data["measurements"][1]
    assert m["U"] == pytest.approx(2 * m["u"]) and 0 < m["u"] < 0.05
    sources = [c["source"] for c in m["uncertainty"]["budget"]]
    assert sources == ["stripe noise and fit", "instrument (size error)"]  # plan's PS
    assert any(".npy" in s for s in m["uncertainty"]["not_included"])
    assert csv_lines[0].endswith(",u,U,decision_rule")


def test_measure_command_strict_exit_and_bad_input(tmp_path: Path, capsys, monkeypatch):
    monkeypatch.setenv("SCANNER_RENDERER", "matplotlib")
    cloud = tmp_path / "cloud.npy"
    moved = (SPHERES[0], SPHERES[1] + [0.5, 0.0, 0.0])
    np.save(cloud, paper_scene(np.random.default_rng(6), n=6000, centers=moved))
    out = tmp_path / "r.json"
    args = ["measure", str(cloud), "--plan", str(PAPER_PLAN), "--out", str(out)]
    assert main(args) == 0
    assert main([*args, "--strict"]) == 1
    assert "FAIL: sphere spacing" in capsys.readouterr().out
    assert (
        main(["measure", str(tmp_path / "none.ply"), "--plan", "paper_sweep", "--out", str(out)])
        == 2
    )
    err = capsys.readouterr().err
    assert "none.ply: point cloud not found" in err and len(err.strip().splitlines()) == 1
    assert (
        main(["measure", str(cloud), "--plan", "paper_sweep", "--out", str(tmp_path / "r.txt")])
        == 2
    )
    assert "expected a .json" in capsys.readouterr().err


def test_angles_and_distances_between_kinds():
    from metrology.fits import fit_cylinder, fit_line, fit_plane, fit_sphere
    from metrology.measure import evaluate_measurement
    from metrology.plan import MeasurementSpec

    rng = np.random.default_rng(7)
    st = rng.uniform(-20, 20, (300, 2))
    a30 = np.radians(30)
    fits = {
        "floor": fit_plane(np.c_[st, np.zeros(300)]),
        "ramp": fit_plane(np.c_[st[:, 0], st[:, 1] * np.cos(a30), st[:, 1] * np.sin(a30) + 5]),
        "rod": fit_line(np.outer(rng.uniform(-30, 30, 50), [np.cos(0.35), 0, np.sin(0.35)])),
        "ball": fit_sphere(
            [3.0, 4.0, 12.0]
            + 5 * (d := rng.normal(size=(200, 3))) / np.linalg.norm(d, axis=1)[:, None]
        ),
        "pipe": fit_cylinder(
            np.c_[
                rng.uniform(-30, 30, 400), 6 * np.cos(t := rng.uniform(0, 6.2, 400)), 6 * np.sin(t)
            ]
        ),
    }

    def value(type_, feats, **kw):
        spec = MeasurementSpec(name="m", type=type_, features=tuple(feats), **kw)
        return evaluate_measurement(spec, fits).actual

    assert value("angle", ["floor", "ramp"]) == pytest.approx(30.0, abs=1e-6)
    assert value("angle", ["rod", "floor"]) == pytest.approx(np.degrees(0.35), abs=1e-6)
    assert value("angle", ["pipe", "rod"]) == pytest.approx(np.degrees(0.35), abs=1e-6)
    assert value("distance", ["ball", "floor"]) == pytest.approx(12.0, abs=1e-6)  # signed, above
    assert value("distance", ["ball"], point_mm=(3.0, 4.0, 0.0)) == pytest.approx(12.0, abs=1e-6)
    assert value("distance", ["ball", "pipe"]) == pytest.approx(np.hypot(4.0, 12.0), abs=1e-6)
    assert value("diameter", ["pipe"]) == pytest.approx(12.0, abs=1e-6)
    assert value("form", ["ball"]) < 1e-9
