"""`scanner plan-scan`: the plan files, poses that reproduce the planned sweeps, refusals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from scanner.app.cli import main
from scanner.core.config import CONFIG_DIR
from scanner.formats.scan_plan import read_scan_plan
from scanner.virtual_cell import load_cell

BRACKET = CONFIG_DIR / "parts" / "bracket.stl"


@pytest.mark.parametrize("rotation", ["quaternion_wxyz", "euler_zyx_deg"])
def test_plan_scan_writes_poses_that_are_the_planned_sweeps(tmp_path: Path, rotation, capsys):
    out = tmp_path / "plan"
    argv = ["plan-scan", str(BRACKET), "--cell", "modern", "--out", str(out), "--step-mm", "1"]
    assert main([*argv, "--part-yaw-deg", "30", "--rotation", rotation]) == 0
    printed = capsys.readouterr().out
    assert "predicted coverage" in printed
    assert sorted(p.name for p in out.iterdir()) == [
        "coverage.npz",
        "coverage.png",
        "plan.json",
        "sweeps.csv",
    ]
    record = json.loads((out / "plan.json").read_text())
    assert record["format"] == "scan-plan/1"
    assert record["coverage"]["predicted"] >= 0.95 and record["coverage"]["reached"]
    plan = read_scan_plan(out)
    assert plan.rotation.value == rotation
    assert len(plan.base_from_flange) == len(record["sweeps"])
    # Each sweep's flange poses, carried to the camera, are the start pose moved step by step
    # along the travel with a fixed orientation.
    flange_from_cam = load_cell("modern").robot.flange_from_cam_matrix()
    for poses, sweep in zip(plan.base_from_flange, record["sweeps"]):
        cams = poses @ flange_from_cam
        assert len(cams) == sweep["frames"]
        start = np.asarray(sweep["base_from_cam_start"])
        np.testing.assert_allclose(cams[0], start, atol=1e-5)
        steps = np.diff(cams[:, :3, 3], axis=0)
        np.testing.assert_allclose(
            steps,
            np.tile(np.asarray(sweep["direction"]) * sweep["step_mm"], (len(steps), 1)),
            atol=1e-5,
        )
        np.testing.assert_allclose(
            cams[:, :3, :3], np.tile(start[:3, :3], (len(cams), 1, 1)), atol=1e-7
        )
    samples = np.load(out / "coverage.npz")
    visible, measured = samples["visible"], samples["measured_by"] >= 0
    assert measured.sum() / visible.sum() == pytest.approx(record["coverage"]["predicted"])


def test_plan_scan_refuses_bad_input_in_one_line(tmp_path: Path, capsys):
    out = tmp_path / "plan"
    missing = tmp_path / "nothing.stl"
    assert main(["plan-scan", str(missing), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing.stl" in err[0]
    assert not out.exists()
    # A calibration without the laser origin cannot say where shadows fall.
    calib = tmp_path / "calib.json"
    calib.write_text(
        json.dumps(
            {
                "format": "scan-calibration/1",
                "camera": {
                    "width": 1280,
                    "height": 1024,
                    "K": [[2000, 0, 640], [0, 2000, 512], [0, 0, 1]],
                    "dist": [0, 0, 0, 0, 0],
                },
                "light_plane": {"normal": [0.0, 0.6, 0.8], "d": -280.0},
                "flange_from_cam": np.eye(4).tolist(),
                "quality": {},
            }
        )
    )
    argv = ["plan-scan", str(BRACKET), "--calibration", str(calib), "--out", str(out)]
    assert main([*argv, "--part-at", "600,100,0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "calib.json" in err[0] and "laser_origin_cam" in err[0]
    assert not out.exists()
