"""The calibration's covariance: its parameterisation, its square roots and its file form."""

from __future__ import annotations

import json

import numpy as np
import pytest

from scanner.formats.calibration_covariance import (
    PARAMETERS,
    CalibrationCovariance,
    apply_correction,
    camera_correction,
    plane_correction,
    plane_tilt_axes,
)
from scanner.formats.calibration_file import read_calibration, write_calibration
from tests.scanner.scanning.test_triangulate import _calibration


def _random_covariance(rng: np.random.Generator, rank: int = 12) -> np.ndarray:
    scale = np.array([0.05, 0.05, 0.1, 0.1, 1e-4, 1e-3, 1e-5, 1e-5, 0.0] + [2e-5] * 2 + [3e-3]
                     + [5e-5] * 3 + [5e-3] * 3)  # fmt: skip
    a = rng.normal(size=(len(PARAMETERS), rank)) * scale[:, None]
    return a @ a.T


def test_principal_directions_are_a_square_root_of_the_matrix():
    rng = np.random.default_rng(0)
    cov = CalibrationCovariance(_random_covariance(rng))
    dirs = cov.principal_directions()
    assert dirs.shape[1] == len(PARAMETERS)
    assert len(dirs) <= 12
    np.testing.assert_allclose(dirs.T @ dirs, cov.matrix, rtol=1e-9, atol=1e-20)
    # k3 was held fixed: no direction moves it
    assert np.all(dirs[:, PARAMETERS.index("k3")] == 0)


def test_draws_follow_the_covariance():
    rng = np.random.default_rng(1)
    cov = CalibrationCovariance(_random_covariance(rng))
    d = cov.draws(20000, np.random.default_rng(2))
    sd = np.sqrt(np.diag(cov.matrix))
    live = sd > 0
    np.testing.assert_allclose(d.std(axis=0)[live], sd[live], rtol=0.03)


def test_zero_correction_changes_nothing_and_a_tilt_turns_the_normal_by_its_angle():
    cal = _calibration()
    plane = (cal.light_plane.normal, cal.light_plane.d)
    K, dist, (n, _), f = apply_correction(cal.K, cal.dist, plane, cal.flange_from_cam, np.zeros(18))
    np.testing.assert_array_equal(K, cal.K)
    np.testing.assert_array_equal(dist, cal.dist)
    np.testing.assert_allclose(n, cal.light_plane.normal)
    np.testing.assert_allclose(f, cal.flange_from_cam)
    delta = np.zeros(18)
    delta[PARAMETERS.index("plane_b")] = 1e-3
    delta[PARAMETERS.index("cam_tz")] = 0.5
    moved = cal.corrected(delta)
    angle = np.arccos(np.clip(moved.light_plane.normal @ cal.light_plane.normal, -1, 1))
    assert angle == pytest.approx(1e-3, rel=1e-3)
    e1, e2 = plane_tilt_axes(cal.light_plane.normal)
    assert abs(e1 @ cal.light_plane.normal) < 1e-12 and abs(e2 @ e1) < 1e-12
    # the camera moved 0.5 mm along its own z axis
    shift = moved.flange_from_cam[:3, 3] - cal.flange_from_cam[:3, 3]
    np.testing.assert_allclose(shift, 0.5 * cal.flange_from_cam[:3, 2], atol=1e-12)


def test_the_file_carries_the_covariance(tmp_path):
    rng = np.random.default_rng(3)
    cal = _calibration()
    cal.covariance = CalibrationCovariance(_random_covariance(rng), 0.005, 0.02, "test")
    path = tmp_path / "cal.json"
    write_calibration(path, cal)
    back = read_calibration(path)
    np.testing.assert_allclose(back.covariance.matrix, cal.covariance.matrix)
    assert back.covariance.robot_translation_mm == 0.02
    assert back.covariance.laser_origin_mm2 is None
    record = json.loads(path.read_text())["covariance"]
    assert record["parameters"] == list(PARAMETERS) and "laser_origin_mm2" not in record


def _with_origin_covariance(cal, rng: np.random.Generator) -> np.ndarray:
    """Give ``cal`` a laser origin on its light plane and a covariance with the origin's
    (rank 2, within the plane); returns the origin's covariance."""
    e1, e2 = plane_tilt_axes(cal.light_plane.normal)
    cal.laser_origin_cam = -cal.light_plane.d * cal.light_plane.normal + 50.0 * e1
    basis = np.column_stack([e1, e2])
    origin = basis @ np.diag([0.4, 0.1]) @ basis.T
    cal.covariance = CalibrationCovariance(_random_covariance(rng), laser_origin_mm2=origin)
    return origin


def test_the_file_carries_the_laser_origins_covariance(tmp_path):
    # issue #19: the origin's covariance (rank 2, within the light plane) goes with the rest
    cal = _calibration()
    origin = _with_origin_covariance(cal, np.random.default_rng(4))
    path = tmp_path / "cal.json"
    write_calibration(path, cal)
    back = read_calibration(path).covariance
    np.testing.assert_allclose(back.laser_origin_mm2, origin, atol=1e-15)
    np.testing.assert_allclose(back.matrix, cal.covariance.matrix)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda r: r["covariance"].update(laser_origin_mm2=[[1.0, 0.0]]), "expected a finite 3x3"),
        (lambda r: r["covariance"].update(laser_origin_mm2=(-np.eye(3)).tolist()), "semi-definite"),
        (lambda r: r.pop("laser_origin_cam"), "no laser_origin_cam"),
    ],
)
def test_an_origin_covariance_it_cannot_use_is_dropped_alone(tmp_path, caplog, change, message):
    # the origin's entry has no line in any budget: a bad one must not cost the matrix
    cal = _calibration()
    _with_origin_covariance(cal, np.random.default_rng(6))
    record = cal.to_json()
    change(record)
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(record))
    back = read_calibration(path).covariance
    assert back is not None and back.laser_origin_mm2 is None
    np.testing.assert_allclose(back.matrix, cal.covariance.matrix)
    assert "laser_origin_mm2 ignored" in caplog.text and message in caplog.text
    assert str(path) in caplog.text


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda r: r.update(parameters=["fx"]), "covariance.parameters"),
        (lambda r: r.update(matrix=[[1.0]]), "expected a finite 18x18"),
        (lambda r: r.update(matrix=(-np.eye(18)).tolist()), "positive semi-definite"),
        (lambda r: r.update(robot={"rotation_deg": -1}), "expected a finite value >= 0"),
    ],
)
def test_a_covariance_it_cannot_use_is_ignored_with_a_warning(tmp_path, caplog, change, message):
    # "more keys may be added" (contract section 2): another tool's or a damaged covariance
    # must not make the calibration itself unreadable
    cal = _calibration()
    cal.covariance = CalibrationCovariance(np.eye(18) * 1e-6)
    record = cal.to_json()
    change(record["covariance"])
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(record))
    back = read_calibration(path)
    assert back.covariance is None
    np.testing.assert_allclose(back.K, cal.K)
    assert message in caplog.text and str(path) in caplog.text
    with pytest.raises(ValueError, match=message):
        CalibrationCovariance.from_json(record["covariance"])


def test_the_corrections_between_two_calibrations_invert_apply_correction():
    rng = np.random.default_rng(5)
    cal = _calibration()
    delta = np.zeros(18)
    delta[9:] = rng.normal(0, [3e-4, 3e-4, 0.05, 2e-4, 2e-4, 2e-4, 0.1, 0.1, 0.1])
    moved = cal.corrected(delta)
    back_plane = plane_correction(
        moved.light_plane.normal, moved.light_plane.d, cal.light_plane.normal, cal.light_plane.d
    )
    back_cam = camera_correction(moved.flange_from_cam, cal.flange_from_cam)
    np.testing.assert_allclose(back_plane, delta[9:12], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(back_cam, delta[12:], rtol=1e-9, atol=1e-12)
    # the same plane, oriented the other way, is the same correction
    flipped = plane_correction(
        -moved.light_plane.normal, -moved.light_plane.d, cal.light_plane.normal, cal.light_plane.d
    )
    np.testing.assert_allclose(flipped, back_plane)
