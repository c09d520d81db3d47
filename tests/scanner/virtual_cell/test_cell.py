"""Cell and target configs load, validate and name what is wrong."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from scanner.core.config import ConfigError
from scanner.core.conventions import make_transform, transform_points
from scanner.core.targets import ChessboardTarget, CircleGridTarget, ConcentricCirclesTarget
from scanner.virtual_cell import cell_names, load_cell, load_target, render_target_image


def test_shipped_cells_load():
    assert {"paper", "modern"} <= set(cell_names())
    paper = load_cell("paper")
    assert (paper.camera.width, paper.camera.height) == (1024, 768)
    assert paper.camera.K[0, 0] == pytest.approx(1939.77)
    spec = paper.target_spec()
    assert isinstance(spec, ConcentricCirclesTarget)
    assert len(spec.ring_diameters_mm) == 14 and spec.radius_mm == 80.0
    # The paper's plane normalised, and the laser origin on it.
    n = np.array([4.2678, 9.3291, -0.8124])
    np.testing.assert_allclose(paper.laser.normal, n / np.linalg.norm(n))
    assert paper.laser.d == pytest.approx(1000.0 / np.linalg.norm(n))
    assert abs(paper.laser.normal @ paper.laser.origin + paper.laser.d) < 1e-9
    r = paper.robot.flange_from_cam_matrix()[:3, :3]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    modern = load_cell("modern")
    assert modern.camera_model().has_distortion
    assert modern.target_spec() != spec


def test_standard_targets_load():
    assert isinstance(load_target("chessboard_11x8"), ChessboardTarget)
    assert isinstance(load_target("circle_grid_7x5"), CircleGridTarget)


@pytest.mark.parametrize(
    ("good", "bad", "message"),
    [
        ("bit_depth = 8", "bit_depth = 12", r"bit_depth"),
        ("sigma_mm = 0.3", "sigma_mmm = 0.3", r"sigma_mmm: unknown key"),
        (
            "origin_mm = [-40.298, -88.088, 7.671]",
            "origin_mm = [0, 0, 0]",
            r"origin_mm: expected a point on the light plane",
        ),
        ("frames = 300", "frames = 0", r"sweep: expected frames >= 1"),
    ],
)
def test_bad_cell_names_the_key(tmp_path, good: str, bad: str, message: str):
    text = (load_cell.__globals__["CONFIG_DIR"] / "cells" / "paper.toml").read_text()
    assert good in text  # the edit below must change the shipped cell
    path = tmp_path / "bad.toml"
    path.write_text(text.replace(good, bad))
    with pytest.raises(ConfigError, match=message):
        load_cell(path)


def test_chessboard_override_is_found_by_opencv_where_projected():
    cell = load_cell("paper")
    cell = dataclasses.replace(cell, camera=dataclasses.replace(cell.camera, bit_depth=8))
    spec = load_target("chessboard_11x8")
    rot = Rotation.from_euler("xyz", [195.0, 10.0, 5.0], degrees=True)
    centre = np.array([5 * 14.0, 3.5 * 14.0, 0.0])
    c_t = make_transform(rot, -rot.apply(centre) + [0.0, 0.0, 560.0])
    image = render_target_image(cell, c_t, np.random.default_rng(0), target=spec)
    found, corners = cv2.findChessboardCorners(image, spec.inner_corners)
    assert found
    corners = cv2.cornerSubPix(
        image,
        corners,
        (5, 5),
        (-1, -1),
        (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4),
    ).reshape(-1, 2)
    expected = cell.camera_model().project(transform_points(c_t, spec.object_points()))
    err = (
        corners
        - expected[np.argmin(np.linalg.norm(corners[:, None] - expected[None], axis=2), axis=1)]
    )
    # cornerSubPix itself scatters by a few hundredths of a pixel (the same without noise);
    # the rendering is unbiased.
    assert np.median(np.linalg.norm(err, axis=1)) < 0.06
    assert np.max(np.linalg.norm(err, axis=1)) < 0.15
    assert np.all(np.abs(err.mean(axis=0)) < 0.01)


def test_circle_grid_override_is_found_by_opencv_where_projected():
    cell = load_cell("paper")
    spec = load_target("circle_grid_7x5")
    rot = Rotation.from_euler("xyz", [190.0, -12.0, 20.0], degrees=True)
    centre = spec.object_points().mean(axis=0)
    c_t = make_transform(rot, -rot.apply(centre) + [0.0, 0.0, 520.0])
    image = render_target_image(cell, c_t, np.random.default_rng(1), target=spec)
    found, centres = cv2.findCirclesGrid(image, spec.grid, flags=cv2.CALIB_CB_SYMMETRIC_GRID)
    assert found
    centres = centres.reshape(-1, 2)
    expected = cell.camera_model().project(transform_points(c_t, spec.object_points()))
    nearest = np.min(np.linalg.norm(centres[:, None] - expected[None], axis=2), axis=1)
    # Blob centroids of the projected discs: perspective shifts them by a few hundredths.
    assert np.max(nearest) < 0.1


def test_target_image_with_laser_shows_both():
    cell = load_cell("paper")
    rot = Rotation.from_euler("xyz", [200.0, 0.0, 0.0], degrees=True)
    c_t = make_transform(rot, [0.0, 20.0, 500.0])
    plain = render_target_image(cell, c_t, None).astype(int)
    lit = render_target_image(cell, c_t, None, laser=True).astype(int)
    assert np.all(lit >= plain)
    assert (lit - plain).max() > 40
    assert np.median(lit - plain) == 0
