import json

import numpy as np
import pytest

from scanner.core.conventions import make_transform, orthonormalize
from scanner.core.fileio import InputError
from scanner.formats.calibration_file import (
    Calibration,
    CalibrationQuality,
    LightPlane,
    read_calibration,
    write_calibration,
)

PAPER_T_EC = np.array(
    [
        [0.7234, 0.5888, 0.3605, -338.0554],
        [-0.1897, -0.3326, 0.9238, -433.5400],
        [0.6639, -0.7367, -0.1289, -34.8966],
    ]
)


def paper_calibration() -> Calibration:
    return Calibration(
        width=1024,
        height=768,
        K=np.array([[1939.77, 0, 574.69], [0, 1937.73, 475.58], [0, 0, 1]]),
        dist=np.zeros(5),
        light_plane=LightPlane.from_coefficients(4.2678, 9.3291, -0.8124, 1000.0),
        flange_from_cam=make_transform(orthonormalize(PAPER_T_EC[:, :3]), PAPER_T_EC[:, 3]),
        quality={"method": "paper"},
    )


def test_light_plane_is_normalised_without_moving_it():
    plane = LightPlane.from_coefficients(4.2678, 9.3291, -0.8124, 1000.0)
    assert np.linalg.norm(plane.normal) == pytest.approx(1.0)
    # A point on the original plane stays on the normalised one.
    p = np.array([0.0, 0.0, 1000.0 / 0.8124])
    assert plane.signed_distance(p[None])[0] == pytest.approx(0.0, abs=1e-9)


def test_calibration_file_round_trips(tmp_path):
    calib = paper_calibration()
    write_calibration(tmp_path / "calib.json", calib)
    back = read_calibration(tmp_path / "calib.json")
    np.testing.assert_allclose(back.K, calib.K)
    np.testing.assert_allclose(back.flange_from_cam, calib.flange_from_cam)
    np.testing.assert_allclose(back.light_plane.normal, calib.light_plane.normal)
    assert back.light_plane.d == pytest.approx(calib.light_plane.d)
    assert back.quality.record == {"method": "paper"}
    assert back.quality.method == "paper" and back.quality.intrinsics_rms_px is None
    obj = json.loads((tmp_path / "calib.json").read_text())
    assert obj["format"] == "scan-calibration/1"
    assert set(obj) >= {"camera", "light_plane", "flange_from_cam", "quality"}
    assert len(obj["camera"]["dist"]) == 5


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda o: o.update(format="scan-calibration/9"), "format: expected 'scan-calibration/1'"),
        (lambda o: o.pop("camera"), "missing key 'camera'"),
        (lambda o: o.update(laser_origin_cam=[1, 2]), "laser_origin_cam: expected [x, y, z]"),
        (
            lambda o: o["camera"].update(K=[[1, 0], [0, 1]]),
            "camera.K: expected a finite 3x3 matrix",
        ),
        (lambda o: o.update(flange_from_cam=np.eye(3).tolist()), "flange_from_cam: expected a 4x4"),
        (lambda o: o["camera"]["K"][0].__setitem__(0, 1e308), "camera.K: expected fx, fy <= "),
        (lambda o: o["camera"]["dist"].__setitem__(0, 1e6), "camera.dist: expected coefficients"),
        (lambda o: o["light_plane"].update(d=0.0), "light_plane.d: expected the plane 1 to"),
        (lambda o: o["flange_from_cam"][2].__setitem__(3, 1e308), "flange_from_cam: expected the"),
        (lambda o: o["camera"].update(width=10**9), "camera: expected a positive image size"),
    ],
)
def test_bad_calibration_file_is_refused_with_its_path(tmp_path, mutate, message):
    write_calibration(tmp_path / "c.json", paper_calibration())
    obj = json.loads((tmp_path / "c.json").read_text())
    mutate(obj)
    (tmp_path / "c.json").write_text(json.dumps(obj))
    with pytest.raises(InputError) as err:
        read_calibration(tmp_path / "c.json")
    assert str(err.value).startswith(str(tmp_path / "c.json"))
    assert message in str(err.value)


def test_failed_write_keeps_the_previous_file(tmp_path):
    path = tmp_path / "c.json"
    write_calibration(path, paper_calibration())
    before = path.read_text()
    bad = paper_calibration()
    bad.quality = CalibrationQuality.from_json({"not_json": object()})
    with pytest.raises(TypeError):
        write_calibration(path, bad)
    assert path.read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.json"]


def test_written_files_get_ordinary_permissions(tmp_path):
    import os
    import stat

    write_calibration(tmp_path / "c.json", paper_calibration())
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE((tmp_path / "c.json").stat().st_mode) == 0o666 & ~umask


def test_undetermined_quality_figures_are_written_as_null(tmp_path):
    calib = paper_calibration()
    calib.quality = CalibrationQuality.from_json(
        {"std": np.array([0.1, np.nan]), "rms": float("inf")}
    )
    write_calibration(tmp_path / "c.json", calib)
    assert json.loads((tmp_path / "c.json").read_text())["quality"] == {
        "std": [0.1, None],
        "rms": None,
    }


@pytest.mark.parametrize("plane", [None, "absent"])
def test_a_camera_only_calibration_reads_and_writes(tmp_path, plane):
    write_calibration(tmp_path / "c.json", paper_calibration())
    obj = json.loads((tmp_path / "c.json").read_text())
    if plane is None:
        obj["light_plane"] = None
    else:
        del obj["light_plane"]
    (tmp_path / "c.json").write_text(json.dumps(obj))
    calib = read_calibration(tmp_path / "c.json")
    assert calib.light_plane is None
    with pytest.raises(InputError, match=r"c\.json: a camera-only calibration"):
        calib.require_light_plane(tmp_path / "c.json", "scanning")
    write_calibration(tmp_path / "d.json", calib)
    assert json.loads((tmp_path / "d.json").read_text())["light_plane"] is None


def test_the_laser_origin_round_trips(tmp_path):
    calib = paper_calibration()
    calib.laser_origin_cam = np.array([-150.0, 0.5, 20.0])
    write_calibration(tmp_path / "c.json", calib)
    assert json.loads((tmp_path / "c.json").read_text())["laser_origin_cam"] == [-150.0, 0.5, 20.0]
    np.testing.assert_array_equal(
        read_calibration(tmp_path / "c.json").laser_origin_cam, calib.laser_origin_cam
    )


@pytest.mark.parametrize("width", [1e999, "1024", True])
def test_a_calibration_image_size_must_be_a_whole_number(tmp_path, width):
    write_calibration(tmp_path / "c.json", paper_calibration())
    text = (tmp_path / "c.json").read_text()
    obj = json.loads(text)
    obj["camera"]["width"] = width
    (tmp_path / "c.json").write_text(json.dumps(obj).replace("Infinity", "1e999"))
    with pytest.raises(InputError, match=r"camera\.width: expected a whole number"):
        read_calibration(tmp_path / "c.json")
