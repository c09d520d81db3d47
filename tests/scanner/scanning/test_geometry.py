"""Each cloud point's stop, its pixel back, and the point other calibrations or a missed stop
would have given."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from scanner.app import stages
from scanner.formats.calibration_covariance import PARAMETERS, CalibrationCovariance
from scanner.formats.calibration_file import write_calibration
from scanner.formats.clouds import read_cloud
from scanner.scanning.geometry import ScanGeometry, scan_geometry_of, sweep_numbering
from scanner.scanning.pipeline import ScanOptions
from scanner.scanning.triangulate import Triangulator
from scanner.virtual_cell.analytic import write_table_step_sweep
from tests.metrology._sweep import ball_sweep


def test_pixels_come_back_and_the_same_calibration_gives_the_same_points():
    sweep = ball_sweep(stops=30)
    points = sweep.points()
    geo = sweep.geometry()
    which = np.arange(0, len(points), 7)
    uv = geo.pixels(points, which)
    np.testing.assert_allclose(uv, sweep.pixels[which], atol=1e-6)
    np.testing.assert_allclose(
        geo.retriangulated(sweep.calibration, uv, which), points[which], atol=1e-9
    )


def test_another_calibration_moves_the_points_as_triangulating_with_it_does():
    sweep = ball_sweep(stops=30)
    points = sweep.points()
    geo = sweep.geometry()
    delta = np.zeros(len(PARAMETERS))
    delta[PARAMETERS.index("plane_d")] = 0.1
    delta[PARAMETERS.index("fx")] = 2.0
    cal = sweep.calibration.corrected(delta)
    which = np.arange(len(points))
    moved = geo.retriangulated(cal, geo.pixels(points, which), which)
    direct = Triangulator(cal, grid_step_px=0).points_base(
        sweep.pixels, sweep.frame_index, sweep.base_from_flange
    )
    np.testing.assert_allclose(moved, direct, atol=1e-6)
    assert np.abs(moved - points).max() > 0.05


def test_the_calibrations_moves_are_its_principal_directions_triangulated():
    sweep = ball_sweep(stops=30)
    points = sweep.points()
    which = np.arange(0, len(points), 5)
    # no covariance: the points as they are, no moves
    as_is, moves = sweep.geometry().calibration_moves(points, which)
    np.testing.assert_allclose(as_is, points[which], atol=1e-9)
    assert moves.shape == (0, len(which), 3)
    # a plane offset of 0.1 mm and fx of 2 px (1 sigma, independent): two directions
    sigma = np.zeros(len(PARAMETERS))
    sigma[PARAMETERS.index("plane_d")] = 0.1
    sigma[PARAMETERS.index("fx")] = 2.0
    cal = dataclasses.replace(
        sweep.calibration, covariance=CalibrationCovariance(np.diag(sigma**2))
    )
    geo = ScanGeometry(cal, sweep.base_from_flange, sweep.frame_index)
    as_is, moves = geo.calibration_moves(points, which)
    np.testing.assert_allclose(as_is, points[which], atol=1e-6)
    assert moves.shape == (2, len(which), 3)
    pixels = geo.pixels(points, which)
    for delta in (
        sigma * (np.arange(len(PARAMETERS)) == PARAMETERS.index(k)) for k in ("plane_d", "fx")
    ):
        moved = geo.retriangulated(cal.corrected(delta), pixels, which) - as_is
        # the direction's sign is free
        assert min(np.abs(m - s * moved).max() for m in moves for s in (1, -1)) < 1e-6
        assert np.abs(moved).max() > 0.01


def test_a_stop_missed_by_a_translation_moves_its_points_by_it_in_the_base():
    sweep = ball_sweep(stops=30)
    points = sweep.points()
    geo = sweep.geometry()
    n = len(sweep.base_from_flange)
    rot = np.zeros((n, 3))
    shift = np.zeros((n, 3))
    shift[3] = [0.1, 0.0, 0.0]  # stop 3 missed by 0.1 mm along the flange's x
    which = np.arange(len(points))
    moved = geo.pose_moved(points, which, rot, shift)
    at3 = sweep.frame_index == 3
    expected = sweep.base_from_flange[3][:3, :3] @ shift[3]
    np.testing.assert_allclose(
        moved[at3] - points[at3], np.broadcast_to(expected, (at3.sum(), 3)), atol=1e-9
    )
    np.testing.assert_allclose(moved[~at3], points[~at3], atol=1e-9)


class _Frame:
    def __init__(self, fid: int, sweep: int, pose: np.ndarray) -> None:
        self.id, self.sweep, self.base_from_flange = fid, sweep, pose


class _Session:
    def __init__(self, frames: list[_Frame]) -> None:
        self.frames = frames


def test_stops_are_numbered_as_the_scan_numbers_them():
    pose = np.eye(4)
    sessions = [
        _Session([_Frame(0, 0, pose), _Frame(1, 0, pose), _Frame(2, 1, pose)]),
        _Session([_Frame(0, 0, pose * 2)]),
    ]
    poses, index = sweep_numbering(sessions)  # type: ignore[arg-type]
    assert index == {(0, 0): 0, (0, 1): 1, (1, 2): 2, (2, 0): 3}
    assert poses[3][0, 0] == 2.0
    sweep = ball_sweep(stops=3)
    geo = ScanGeometry.from_sessions(
        sweep.calibration,
        sessions,
        np.array([2, 0, 1]),
        np.array([0, 1, 2]),  # type: ignore[arg-type]
    )
    np.testing.assert_array_equal(geo.frame_index, [3, 1, 2])
    with pytest.raises(ValueError, match="sweep 5 frame 0 not there"):
        ScanGeometry.from_sessions(sweep.calibration, sessions, np.array([5]), np.array([0]))  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def scanned(tmp_path_factory):
    """A cloud ``scanner scan`` wrote from an analytic sweep, with its session and calibration."""

    root = tmp_path_factory.mktemp("geometry")
    session, cal, _ = write_table_step_sweep(root / "session", x_mm=np.linspace(-20, 20, 5))
    write_calibration(root / "cal.json", cal)
    stages.scan([session], root / "cal.json", root / "cloud.ply")
    return root, cal


def test_the_geometry_of_a_scanned_cloud_puts_each_point_on_its_stops_plane(scanned):

    root, _ = scanned
    geo, why = scan_geometry_of(root / "cloud.ply")
    assert geo is not None, why
    points = read_cloud(root / "cloud.ply").point.positions.numpy()
    assert len(geo.frame_index) == len(points) and geo.base_from_flange.shape == (5, 4, 4)
    assert np.max(geo.plane_distances(points, np.arange(len(points)))) < 1e-6


def test_a_cloud_the_geometry_did_not_make_is_refused_with_the_reason(scanned, tmp_path):

    root, cal = scanned
    other = cal.corrected(np.eye(len(PARAMETERS))[PARAMETERS.index("plane_d")] * 0.5)
    write_calibration(tmp_path / "other.json", other)
    geo, why = scan_geometry_of(root / "cloud.ply", tmp_path / "other.json")
    assert geo is None and "off the light plane" in why
    stages.scan(
        [root / "session"],
        root / "cal.json",
        tmp_path / "voxel.ply",
        options=ScanOptions(voxel_mm=25.0),
    )
    geo, why = scan_geometry_of(tmp_path / "voxel.ply")
    assert geo is None and why
    shutil.copy(root / "cloud.ply", tmp_path / "moved.ply")
    shutil.move(root / "session", tmp_path / "session")
    try:
        geo, why = scan_geometry_of(tmp_path / "moved.ply")
        assert geo is None and "not found" in why
    finally:
        shutil.move(tmp_path / "session", root / "session")
    geo, why = scan_geometry_of(tmp_path / "cloud.pcd")
    assert geo is None and ".pcd" in why
