"""`scanner scan` through the command line's entry point."""

from __future__ import annotations

import numpy as np
import pytest

from scanner.app.cli import main
from scanner.formats.calibration_file import write_calibration
from scanner.formats.clouds import read_cloud
from scanner.virtual_cell.analytic import TableStepScene, write_table_step_sweep


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    session, cal, _ = write_table_step_sweep(root / "session", x_mm=np.linspace(-20, 20, 5))
    write_calibration(root / "cal.json", cal)
    return session, root / "cal.json"


def test_scan_writes_the_cloud_and_a_summary(sweep, tmp_path, capsys):
    session, cal = sweep
    out = tmp_path / "cloud.ply"
    code = main(["scan", str(session), "--calibration", str(cal), "--out", str(out), "--quiet"])
    assert code == 0
    stdout = capsys.readouterr().out
    assert f"wrote {out}" in stdout
    assert "points from 5 frames in 1 sweep(s)" in stdout
    assert len(read_cloud(out).point.positions) > 500


def test_scan_options_and_resume(sweep, tmp_path, capsys):
    session, cal = sweep
    args = [
        "scan",
        str(session),
        str(session),
        "--calibration",
        str(cal),
        "--quiet",
        "--mode",
        "precise",
        "--voxel-mm",
        "0.5",
        "--workdir",
        str(tmp_path / "w"),
    ]
    assert main([*args, "--out", str(tmp_path / "a.e57")]) == 0
    assert main([*args, "--out", str(tmp_path / "b.pcd")]) == 0
    stdout = capsys.readouterr().out
    assert "in 2 sweep(s)" in stdout and "resumed 1 saved chunk(s)" in stdout


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ("no_calibration", "calibration file not found"),
        ("bad_extension", "expected a .ply, .pcd, .e57 file name"),
        ("other_size", "images are 320x240, the calibration is for 640x480"),
        ("no_session", "session folder not found"),
        ("no_poses", "a sweep row needs a robot pose"),
    ],
)
def test_bad_input_exits_2_with_one_line(sweep, tmp_path, capsys, change, reason):
    session, cal = sweep
    out = tmp_path / "cloud.ply"
    if change == "no_calibration":
        cal = tmp_path / "missing.json"
    elif change == "bad_extension":
        out = tmp_path / "cloud.txt"
    elif change == "other_size":
        cal = tmp_path / "big.json"
        write_calibration(cal, TableStepScene(width=640, height=480).calibration())
    elif change == "no_session":
        session = tmp_path / "nowhere"
    elif change == "no_poses":
        from dataclasses import replace

        from scanner.formats.session import read_session, write_session

        s = read_session(session)
        (tmp_path / "s" / "images").mkdir(parents=True)
        frames = []
        for f in s.frames:
            image = tmp_path / "s" / "images" / f.laser_image.name
            image.write_bytes(f.laser_image.read_bytes())
            frames.append(replace(f, laser_image=image, base_from_flange=None))
        write_session(tmp_path / "s", "sweep", s.width, s.height, frames)
        session = tmp_path / "s"
    code = main(["scan", str(session), "--calibration", str(cal), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("scanner scan: error:") and reason in err[0]
    assert not out.exists()


def test_the_cloud_holds_trusted_points_unless_asked(sweep, tmp_path, capsys):
    # The step's walls are seen obliquely: with an incidence limit they are flagged grazing.
    session, cal = sweep
    args = ["scan", str(session), "--calibration", str(cal), "--quiet", "--max-incidence-deg", "30"]
    assert main([*args, "--out", str(tmp_path / "trusted.ply")]) == 0
    printed = capsys.readouterr().out
    assert main([*args, "--out", str(tmp_path / "all.ply"), "--keep-flagged"]) == 0
    trusted = read_cloud(tmp_path / "trusted.ply").point["flags"].numpy()
    every = read_cloud(tmp_path / "all.ply").point["flags"].numpy()
    assert np.all(trusted == 0)
    n_flagged = int(np.count_nonzero(every))
    assert n_flagged > 0 and len(every) == len(trusted) + n_flagged
    grazing = int(np.count_nonzero(every & 32))
    assert "left out as flagged (--keep-flagged keeps them): " in printed
    assert f"{grazing} grazing" in printed


def test_a_failed_scan_leaves_no_work_folder(tmp_path, capsys):
    session, cal, _ = write_table_step_sweep(tmp_path / "s", x_mm=np.linspace(-20, 20, 5))
    write_calibration(tmp_path / "cal.json", cal)
    images = sorted((session / "images").glob("*.png"))
    images[2].write_bytes(b"\x89PNG\r\n\x1a\n" + images[2].read_bytes()[8:40])  # truncated
    out = tmp_path / "out" / "cloud.ply"
    code = main(["scan", str(session), "--calibration", str(tmp_path / "cal.json"),
                 "--out", str(out), "--quiet"])  # fmt: skip
    assert code == 2, capsys.readouterr().err
    assert images[2].name in capsys.readouterr().err
    assert not out.exists()
    assert not (out.parent / ".scanner-work").exists()


@pytest.mark.parametrize(
    ("amplitude", "reason"),
    [
        (0.0, "no stripe points found in any of the 5 frames; nothing written"),
        (5000.0, "stripe points are flagged ("),
    ],
)
def test_a_scan_with_no_point_to_keep_exits_2_and_keeps_the_old_cloud(
    tmp_path, capsys, amplitude, reason
):
    # A sweep where the laser never shows, and one where it saturates every point.
    session, cal, _ = write_table_step_sweep(
        tmp_path / "s", scene=TableStepScene(amplitude=amplitude), x_mm=np.linspace(-20, 20, 5)
    )
    write_calibration(tmp_path / "cal.json", cal)
    out = tmp_path / "cloud.ply"
    out.write_bytes(b"an earlier cloud")
    code = main(["scan", str(session), "--calibration", str(tmp_path / "cal.json"),
                 "--out", str(out), "--quiet"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2
    assert reason in err and str(session) in err
    assert len(err.strip().splitlines()) == 1
    assert out.read_bytes() == b"an earlier cloud"


def test_uneven_background_is_taken_out_unless_kept(tmp_path, capsys):
    scene = TableStepScene(amplitude=25.0, ambient_ramp=60.0)
    session, cal, _ = write_table_step_sweep(
        tmp_path / "lit", scene=scene, x_mm=np.linspace(-20, 20, 5)
    )
    write_calibration(tmp_path / "cal.json", cal)
    args = ["scan", str(session), "--calibration", str(tmp_path / "cal.json"), "--quiet"]
    for choice in ("auto", "remove"):
        out = tmp_path / f"{choice}.ply"
        assert main([*args, "--out", str(out), "--uneven-background", choice]) == 0
        assert len(read_cloud(out).point.positions) > 500
    assert main([*args, "--out", str(tmp_path / "keep.ply"), "--uneven-background", "keep"]) == 2
    assert "no stripe points found" in capsys.readouterr().err
