import json
import math

import numpy as np
import pytest

from metrology.ef_check import run_ef_check
from scanner.app.cli import main
from scanner.formats.calibration_file import read_calibration
from scanner.formats.session import read_session
from scanner.virtual_cell.truth import read_truth

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def modern_check(simulated_cells):
    return simulated_cells("modern", sessions=("check",), seed=1)


def test_ef_with_the_true_calibration_measures_the_diameter(modern_check, tmp_path):
    # With the truth as calibration only the image measurement is left: E and F must land on
    # the ring to well under the 0.03 mm the modern cell is allowed in total.
    result = run_ef_check(
        read_session(modern_check / "check"),
        read_calibration(modern_check / "calibration_true.json"),
    )
    truth = read_truth(modern_check)
    assert result.nominal_mm == pytest.approx(truth.target.ring_diameters_mm[-1])
    assert len(result.valid) >= 5
    assert result.mean_abs_error_mm < 0.015
    assert result.max_abs_error_mm < 0.04
    # The target is fixed, so O stays put up to the robot's repeatability (0.02 mm, 0.005 deg).
    assert result.o_spread_mm < 0.15


def test_ef_result_file_keeps_the_contract(modern_check, tmp_path):
    out = tmp_path / "ef.json"
    assert (
        main(
            [
                "check",
                str(modern_check / "check"),
                "--calibration",
                str(modern_check / "calibration_true.json"),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    obj = json.loads(out.read_text())
    assert {"nominal_mm", "measurements", "mean_abs_error_mm", "mean_rel_error"} <= set(obj)
    errors = [m["error_mm"] for m in obj["measurements"]]
    for m in obj["measurements"]:
        assert m["error_mm"] == pytest.approx(m["length_mm"] - obj["nominal_mm"])
    assert obj["mean_abs_error_mm"] == pytest.approx(np.mean(np.abs(errors)))
    assert obj["mean_rel_error"] == pytest.approx(obj["mean_abs_error_mm"] / obj["nominal_mm"])
    assert obj["verdict"] == "pass" and obj["tolerances_mm"]["mean_abs_error"] == 0.1
    html_text = (tmp_path / "ef.html").read_text()
    assert "PASS — 3 passed, 0 failed" in html_text


def test_a_wrong_light_plane_shows_in_the_ef_error(modern_check, tmp_path):
    # Moving the light plane 1 mm scales every triangulated length: the check must see it.
    calib = json.loads((modern_check / "calibration_true.json").read_text())
    calib["light_plane"]["d"] += 1.0 * math.copysign(1.0, calib["light_plane"]["d"])
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(calib))
    result = run_ef_check(read_session(modern_check / "check"), read_calibration(bad))
    assert result.mean_abs_error_mm > 0.1
    assert not result.passed and result.rows[0].final_status == "fail"


def test_a_sweep_session_is_refused(tmp_path, modern_check, capsys):
    code = main(
        [
            "check",
            str(tmp_path / "none"),
            "--calibration",
            str(modern_check / "calibration_true.json"),
            "--out",
            str(tmp_path / "x.json"),
        ]
    )
    assert code == 2
    assert "session folder not found" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()
