import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from scanner.core.conventions import RotationConvention, make_transform
from scanner.core.fileio import InputError
from scanner.core.targets import ConcentricCirclesTarget, OrientationMarker
from scanner.formats.session import Frame, read_session, write_session

TARGET = ConcentricCirclesTarget(
    ring_diameters_mm=(50.0, 80.0, 110.0, 160.0),
    line_width_mm=0.6,
    orientation_marker=OrientationMarker(diameter_mm=8.0, center_mm=(92.0, 0.0)),
)


def make_session(tmp_path: Path, rotation="euler_zyx_deg", n=4, size=(64, 48)) -> tuple[Path, list]:
    rng = np.random.default_rng(0)
    (tmp_path / "images").mkdir(parents=True, exist_ok=True)
    frames, poses = [], []
    for i in range(n):
        img = rng.integers(0, 255, size=(size[1], size[0]), dtype=np.uint8)
        cv2.imwrite(str(tmp_path / "images" / f"t{i}.png"), img)
        cv2.imwrite(str(tmp_path / "images" / f"l{i}.png"), img)
        pose = make_transform(Rotation.random(random_state=rng), rng.uniform(-800, 800, 3))
        poses.append(pose)
        frames.append(Frame(i, tmp_path / f"images/t{i}.png", tmp_path / f"images/l{i}.png", pose))
    write_session(tmp_path, "calibration", size[0], size[1], frames, rotation, TARGET)
    return tmp_path, poses


@pytest.mark.parametrize("rotation", [c.value for c in RotationConvention])
def test_write_then_read_round_trips_poses_and_target(tmp_path, rotation):
    root, poses = make_session(tmp_path, rotation)
    session = read_session(root)
    assert session.kind == "calibration"
    assert session.target == TARGET
    assert [f.id for f in session] == [0, 1, 2, 3]
    for frame, pose in zip(session, poses):
        np.testing.assert_allclose(frame.base_from_flange, pose, atol=1e-9)
        assert frame.target_image.is_file()
    assert session.load_target_image(session.frames[0]).shape == (48, 64)


def rewrite_csv(root: Path, edit) -> None:
    path = root / "frames.csv"
    lines = path.read_text().splitlines()
    path.write_text("\n".join(edit(lines)) + "\n")


def set_cell(lines, row, column, value):
    header = lines[0].split(",")
    cells = lines[row - 1].split(",")
    cells[header.index(column)] = value
    lines[row - 1] = ",".join(cells)
    return lines


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            lambda ls: set_cell(ls, 3, "x", "nan"),
            "frames.csv: row 3, column 'x': expected a finite number",
        ),
        (
            lambda ls: set_cell(ls, 2, "ry", "abc"),
            "row 2, column 'ry': expected a number, got 'abc'",
        ),
        (
            lambda ls: set_cell(ls, 4, "id", "0"),
            "row 4, column 'id': duplicate id 0 (first on row 2)",
        ),
        (
            lambda ls: set_cell(ls, 2, "target_image", "images/nope.png"),
            "row 2, column 'target_image': image 'images/nope.png' not found",
        ),
        (
            lambda ls: set_cell(ls, 3, "z", ""),
            "row 3, column 'z': empty while other pose columns are given",
        ),
        (
            lambda ls: [ls[0].replace("laser_image", "laser"), *ls[1:]],
            "header: missing column 'laser_image'",
        ),
        (lambda ls: [ls[0].replace(",rz", ",rzz"), *ls[1:]], "missing pose column(s) rz"),
        (
            lambda ls: set_cell(ls, 2, "x", "606,86"),  # a decimal comma splits the cell
            "row 2: expected at most",
        ),
        (lambda ls: set_cell(ls, 3, "z", "1e308"), "row 3, column 'z': expected a position within"),
        (
            lambda ls: set_cell(ls, 2, "laser_image", "../../etc/passwd"),
            "row 2, column 'laser_image': image '../../etc/passwd' is outside the session folder",
        ),
        (
            lambda ls: set_cell(ls, 2, "target_image", "/etc/passwd"),
            "image '/etc/passwd' is outside the session folder",
        ),
        (
            lambda ls: [ls[0], ls[1].replace("images", "ima\x00ges", 1), *ls[2:]],
            "row 2: a NUL byte",
        ),
    ],
)
def test_bad_frames_csv_names_file_row_and_column(tmp_path, edit, message):
    root, _ = make_session(tmp_path)
    rewrite_csv(root, edit)
    with pytest.raises(InputError) as err:
        read_session(root)
    assert message in str(err.value)
    assert "frames.csv" in str(err.value)


def test_image_size_differing_from_camera_is_refused(tmp_path):
    root, _ = make_session(tmp_path)
    cv2.imwrite(str(root / "images" / "l2.png"), np.zeros((10, 10), np.uint8))
    with pytest.raises(
        InputError,
        match=r"row 4, column 'laser_image': image 'images/l2.png' is 10x10, expected 64x48",
    ):
        read_session(root)


def test_unreadable_image_is_refused(tmp_path):
    root, _ = make_session(tmp_path)
    (root / "images" / "t1.png").write_bytes(b"not an image")
    with pytest.raises(InputError, match="row 3, column 'target_image': not a readable image"):
        read_session(root)


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("format", "scan-session/2", "format: expected 'scan-session/1'"),
        ("kind", "sweeps", "kind: expected one of calibration, check, sweep"),
        ("units", "m", "units: expected 'mm'"),
        ("rotation", "euler_abc", "unknown rotation convention 'euler_abc'"),
        ("target", {"kind": "hexagons"}, "target.kind: expected"),
    ],
)
def test_bad_session_json_names_the_key(tmp_path, key, value, message):
    root, _ = make_session(tmp_path)
    meta = json.loads((root / "session.json").read_text())
    meta[key] = value
    (root / "session.json").write_text(json.dumps(meta))
    with pytest.raises(InputError) as err:
        read_session(root)
    assert "session.json" in str(err.value)
    assert message in str(err.value)


def test_quaternion_far_from_unit_is_refused_with_its_row(tmp_path):
    root, _ = make_session(tmp_path, rotation="quaternion_wxyz")
    rewrite_csv(root, lambda ls: set_cell(ls, 3, "qw", "3.0"))
    with pytest.raises(InputError, match="row 3: quaternion_wxyz: expected unit norm"):
        read_session(root)


def test_sweep_with_a_pose_on_some_rows_only_is_refused(tmp_path):
    root, _ = make_session(tmp_path)
    meta = json.loads((root / "session.json").read_text())
    meta["kind"] = "sweep"
    (root / "session.json").write_text(json.dumps(meta))
    rewrite_csv(
        root, lambda ls: [ls[0], *ls[1:3], ",".join(ls[3].split(",")[:3] + [""] * 6), ls[4]]
    )
    with pytest.raises(InputError, match="frame 2: a sweep row needs a robot pose"):
        read_session(root)


def test_missing_session_folder_and_files(tmp_path):
    with pytest.raises(InputError, match="session folder not found"):
        read_session(tmp_path / "nope")
    with pytest.raises(InputError, match=r"session.json: missing"):
        read_session(tmp_path)


def test_extra_columns_are_ignored_and_sweep_column_is_read(tmp_path):
    root, _ = make_session(tmp_path)
    rewrite_csv(
        root,
        lambda ls: (
            [ls[0] + ",sweep,comment"] + [l + f",{i % 2},hello" for i, l in enumerate(ls[1:])]
        ),
    )
    session = read_session(root)
    assert [f.sweep for f in session] == [0, 1, 0, 1]


def test_session_written_from_a_relative_folder_reads_back(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    root = Path("out") / "calibration"
    (root / "images").mkdir(parents=True)
    cv2.imwrite(str(root / "images" / "t0.png"), np.zeros((48, 64), np.uint8))
    frames = [Frame(0, root / "images" / "t0.png", None)]
    write_session(root, "calibration", 64, 48, frames, None, TARGET)
    assert "images/t0.png" in (root / "frames.csv").read_text()
    assert read_session(root).frames[0].target_image == (tmp_path / root / "images" / "t0.png")


def test_an_excel_byte_order_mark_is_read(tmp_path):
    root, poses = make_session(tmp_path)
    csv_path = root / "frames.csv"
    csv_path.write_bytes(b"\xef\xbb\xbf" + csv_path.read_bytes())
    session = read_session(root)
    assert [f.id for f in session.frames] == [0, 1, 2, 3]
    np.testing.assert_allclose(session.frames[0].base_from_flange, poses[0], atol=1e-9)


def test_images_outside_the_folder_are_read_when_allowed(tmp_path, monkeypatch):
    root, _ = make_session(tmp_path / "S")
    shared = tmp_path / "shared.png"
    (root / "images" / "t0.png").rename(shared)
    rewrite_csv(root, lambda ls: set_cell(ls, 2, "target_image", "../shared.png"))
    with pytest.raises(InputError, match="outside the session folder"):
        read_session(root)
    monkeypatch.setenv("SCANNER_ALLOW_OUTSIDE_IMAGES", "1")
    assert read_session(root).frames[0].target_image == shared.resolve()


def test_a_row_ending_in_empty_cells_is_read(tmp_path):
    root, _ = make_session(tmp_path)
    rewrite_csv(root, lambda ls: [ls[0], ls[1] + ",,", *ls[2:]])  # a spreadsheet's trailing commas
    assert len(read_session(root).frames) == 4


@pytest.mark.parametrize("width", [1e999, "64", True, 64.5])
def test_an_image_size_that_is_no_whole_number_is_refused(tmp_path, width):
    root, _ = make_session(tmp_path)
    meta = json.loads((root / "session.json").read_text())
    meta["camera"]["width"] = width
    (root / "session.json").write_text(json.dumps(meta).replace("Infinity", "1e999"))
    with pytest.raises(InputError, match="camera: expected integer width and height"):
        read_session(root)
