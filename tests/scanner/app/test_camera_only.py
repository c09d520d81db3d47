"""Sessions without laser images give a camera + hand-eye calibration (``light_plane: null``),
which scanning and the EF check refuse at once; a session that cannot give a file is refused
before any work."""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import calibration.pipeline as calibration_pipeline
import scanner.app.stages.calibration as calibration_stages
from scanner.app import stages
from scanner.app.cli import build_parser, main
from scanner.core.conventions import RotationConvention, angle_between_rotations_deg
from scanner.core.targets import ChessboardTarget
from scanner.formats.calibration_file import read_calibration
from scanner.formats.session import Frame, read_session, write_session
from scanner.virtual_cell.truth import read_truth
from tests.conftest import real_data_subdir


def _without_lasers(source: Path, out: Path, keep_posed: int | None = None) -> Path:
    """A copy of a calibration session with its laser images left out (images linked)."""
    session = read_session(source)
    out.mkdir(parents=True)
    (out / "images").symlink_to((source / "images").resolve())
    frames, posed = [], 0
    for f in session.frames:
        if f.target_image is None:
            continue
        if f.has_pose:
            posed += 1
            if keep_posed is not None and posed > keep_posed:
                continue
        image = out / "images" / f.target_image.name
        frames.append(replace(f, target_image=image, laser_image=None, laser_off_image=None))
    write_session(out, "calibration", session.width, session.height, frames,
                  session.rotation, session.target)  # fmt: skip
    return out


def test_too_few_posed_views_are_refused_before_any_work(
    simulated_cells, tmp_path, capsys, monkeypatch
):
    cell = simulated_cells("modern", sessions=("calibration",))
    session = _without_lasers(cell / "calibration", tmp_path / "S", keep_posed=2)

    def no_detection(*args: object, **kwargs: object) -> None:
        raise AssertionError("the session was refused only after detection began")

    monkeypatch.setattr(calibration_pipeline, "_detect_all", no_detection)
    assert main(["calibrate", str(session), "--out", str(tmp_path / "c.json"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "expected at least 3 rows with a robot pose and a target image, got 2" in err
    assert not (tmp_path / "c.json").exists()


@pytest.mark.slow
def test_a_session_without_laser_images_gives_a_camera_only_file(simulated_cells, tmp_path, capsys):
    cell = simulated_cells("modern", sessions=("calibration",))
    truth = read_truth(cell)
    session = _without_lasers(cell / "calibration", tmp_path / "S")
    out = tmp_path / "c.json"
    assert main(["calibrate", str(session), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "no light plane (no laser images: a camera-only calibration)" in printed
    assert json.loads(out.read_text())["light_plane"] is None
    cal = read_calibration(out)
    assert angle_between_rotations_deg(cal.flange_from_cam, truth.flange_from_cam) < 0.02
    assert np.linalg.norm(cal.flange_from_cam[:3, 3] - truth.flange_from_cam[:3, 3]) < 0.1
    assert "None: the session has no laser images" in out.with_suffix(".html").read_text()
    # Scanning and the EF check need the plane: refused at once, naming the file.
    cloud = tmp_path / "x.ply"
    assert main(["scan", str(session), "--calibration", str(out), "--out", str(cloud)]) == 2
    assert f"{out}: a camera-only calibration" in capsys.readouterr().err
    assert not cloud.exists()


def _kuka_session(root: Path, out: Path, convention: RotationConvention) -> Path:
    poses = np.loadtxt(root / "RobotPosesVec.txt").reshape(-1, 4, 4)
    poses[:, :3, 3] *= 1000.0  # the file is in metres
    out.mkdir(parents=True)
    (out / "images").symlink_to(root.resolve())
    frames = [Frame(i, out / "images" / f"{i:02d}.png", None, poses[i - 1]) for i in range(1, 31)]
    write_session(out, "calibration", 1928, 1208, frames, convention,
                  ChessboardTarget((28, 17), 20.0))  # fmt: skip
    return out


@pytest.mark.real_data
@pytest.mark.parametrize("convention", list(RotationConvention))
def test_kuka_poses_read_the_same_in_every_rotation_convention(tmp_path, convention):
    root = real_data_subdir("kuka_1")
    session = read_session(_kuka_session(root, tmp_path / "S", convention))
    poses = np.loadtxt(root / "RobotPosesVec.txt").reshape(-1, 4, 4)
    poses[:, :3, 3] *= 1000.0
    got = np.stack([f.base_from_flange for f in session.frames])
    np.testing.assert_allclose(got, poses, atol=1e-6)


@pytest.mark.slow
@pytest.mark.real_data
def test_kuka_camera_only_session_calibrates_through_the_command(tmp_path):
    root = real_data_subdir("kuka_1")
    session = _kuka_session(root, tmp_path / "S", RotationConvention.EULER_ZYX_DEG)
    out = tmp_path / "kuka.json"
    assert main(["calibrate", str(session), "--out", str(out), "--quiet"]) == 0
    cal = read_calibration(out)
    assert cal.light_plane is None
    # The whole chain reprojects the corners better than OpenCV's best solver (2.453 px,
    # the data's README); measured 2.38 px.
    assert cal.quality.hand_eye_rms_px < 2.45
    assert 255 < cal.flange_from_cam[0, 3] < 263
    assert os.path.getsize(out.with_suffix(".html")) > 10_000


@pytest.mark.slow
def test_laser_origin_from_the_drawing_is_written_when_it_lies_on_the_plane(
    simulated_cells, tmp_path, monkeypatch
):
    """``--laser-origin-mm`` (the sensor drawing's apex of the fan) goes into the file as
    ``laser_origin_cam``; a point off the calibrated light plane is refused, nothing written."""
    session = simulated_cells("modern", sessions=("calibration",)) / "calibration"
    out = tmp_path / "c.json"
    # The modern cell's laser: origin (10, -140, -5) mm in the camera frame (configs/cells).
    run = stages.calibrate(session, out, report=None, laser_origin_cam_mm=(10.0, -140.0, -5.0))
    written = read_calibration(out)
    np.testing.assert_allclose(written.laser_origin_cam, [10.0, -140.0, -5.0])
    # The drawing's value replaces the estimate from the shadow edges, and the file says so.
    assert written.quality.record["laser_origin_source"].startswith("given")
    assert written.quality.record["laser_origin"]["estimated"]
    # ... and the estimate's covariance (which it would have written) is not carried for the
    # drawing's point (issue #19)
    assert (
        written.quality.record["laser_origin"]["std_mm"] <= calibration_pipeline.MAX_ORIGIN_STD_MM
    )
    assert written.covariance is not None and written.covariance.laser_origin_mm2 is None
    # The same calibration again (not recomputed: calibrate_session is replaced where the
    # calibrate stage looks it up), with an origin 40 mm off the plane: refused.
    calls = []

    def calibrated_before(*args, **kwargs):
        calls.append(args)
        return run.result

    monkeypatch.setattr(calibration_stages, "calibrate_session", calibrated_before)
    off = tmp_path / "off.json"
    with pytest.raises(ValueError, match="off it"):
        stages.calibrate(session, off, report=None, laser_origin_cam_mm=(10.0, -100.0, -5.0))
    assert len(calls) == 1, "the stand-in calibration was not the one run"
    assert not off.exists()


def test_laser_origin_option_is_parsed_in_mm() -> None:
    args = build_parser().parse_args(
        ["calibrate", "S", "--out", "c.json", "--laser-origin-mm", "10", "-140", "-5"]
    )
    assert args.laser_origin_mm == [10.0, -140.0, -5.0]
