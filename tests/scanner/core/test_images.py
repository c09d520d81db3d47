"""Image loading: a colour laser frame read as the laser's grey level, pairs read alike."""

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from scanner.core.fileio import InputError
from scanner.core.images import laser_gray, load_gray_image, load_laser_images
from scanner.stripe.extract import extract_stripe
from scanner.virtual_cell import quick

HEIGHT, WIDTH = 160, 400


def _true_row(u: np.ndarray) -> np.ndarray:
    return 70.3 + 0.02 * u


def _red_line_jpeg(rng: np.random.Generator, peak: float, laser_on: bool = True) -> np.ndarray:
    """A red laser line on a white card, as a colour camera's JPEG gives it (BGR).

    The red channel carries the line's core and a wide halo; green and blue see the core
    only, weaker (the sensor's crosstalk). With ``peak`` far above 255 the red channel clips
    over the halo, as in real line-laser captures on white targets.
    """
    v = np.arange(HEIGHT)[:, None]
    u = np.arange(WIDTH)[None, :]
    img = np.empty((HEIGHT, WIDTH, 3))
    img[...] = (165.0, 172.0, 178.0)
    img += rng.normal(0.0, 1.5, img.shape)
    if laser_on:
        core = np.exp(-0.5 * ((v - _true_row(u)) / 2.0) ** 2)
        halo = np.exp(-0.5 * ((v - _true_row(u)) / 7.0) ** 2)
        img[..., 2] += peak * (0.6 * core + 0.4 * halo)
        img[..., 1] += 0.35 * peak * core
        img[..., 0] += 0.3 * peak * core
    _, jpeg = cv2.imencode(
        ".jpg", np.clip(np.rint(img), 0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 90]
    )
    return cv2.imdecode(jpeg, cv2.IMREAD_COLOR)


def _write_pair(tmp_path: Path, peak: float, seed: int) -> tuple[Path, Path]:
    rng = np.random.default_rng(seed)
    on, off = tmp_path / "on.png", tmp_path / "off.png"
    cv2.imwrite(str(on), _red_line_jpeg(rng, peak))
    cv2.imwrite(str(off), _red_line_jpeg(rng, peak, laser_on=False))
    return on, off


def _row_errors(image: np.ndarray, background: np.ndarray) -> tuple[int, np.ndarray]:
    prof = extract_stripe(image, mode="precise", background=background)
    return len(prof.u), prof.v - _true_row(prof.u)


def test_a_clipped_colour_line_is_read_at_its_white_core(tmp_path):
    on_path, off_path = _write_pair(tmp_path, peak=600.0, seed=3)
    on, off = load_laser_images(on_path, off_path)
    assert laser_gray(cv2.imread(str(on_path)))[1] == "mean"
    found, err = _row_errors(on, off)
    # Every column, within a few tenths of a pixel (JPEG ringing on the core: 0.35 px RMS).
    assert found == WIDTH
    assert np.sqrt(np.mean(err**2)) < 0.5
    # The brightest channel alone clips over the halo and loses the line.
    found_max, err_max = _row_errors(
        cv2.imread(str(on_path)).max(axis=2), cv2.imread(str(off_path)).max(axis=2)
    )
    assert found_max < WIDTH // 2 or np.sqrt(np.mean(err_max**2)) > 2.0


def test_an_unclipped_colour_line_is_read_in_its_own_channel(tmp_path):
    on_path, off_path = _write_pair(tmp_path, peak=60.0, seed=4)
    on, off = load_laser_images(on_path, off_path)
    np.testing.assert_array_equal(on, cv2.imread(str(on_path)).max(axis=2))
    np.testing.assert_array_equal(off, cv2.imread(str(off_path)).max(axis=2))
    np.testing.assert_array_equal(load_gray_image(on_path, laser=True), on)
    found, err = _row_errors(on, off)
    assert found == WIDTH
    assert np.sqrt(np.mean(err**2)) < 0.2


def test_the_laser_off_frame_follows_its_laser_frame(tmp_path):
    on_path, _ = _write_pair(tmp_path, peak=600.0, seed=5)
    # A laser-off frame that would be read by its brightest channel on its own.
    off_path = tmp_path / "dim_off.png"
    dim = np.full((HEIGHT, WIDTH, 3), (40, 60, 200), np.uint8)
    cv2.imwrite(str(off_path), dim)
    _, off = load_laser_images(on_path, off_path)
    np.testing.assert_array_equal(off, np.full((HEIGHT, WIDTH), 100, np.uint8))


def _offsets_from_truth_px(found_uv: np.ndarray, truth_uv: np.ndarray) -> np.ndarray:
    """Distance of each found stripe point to the true stripe polyline (near points only)."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(truth_uv).query(found_uv, k=2)
    a, b = truth_uv[idx[:, 0]], truth_uv[idx[:, 1]]
    normal = np.column_stack([a[:, 1] - b[:, 1], b[:, 0] - a[:, 0]])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return np.abs(np.sum((found_uv - a) * normal, axis=1))[dist[:, 0] < 3.0]


def test_the_virtual_cells_colour_camera_gives_the_mono_cameras_stripe(tmp_path):
    """Round trip: a red laser clipping in red on a Bayer sensor, read back through the
    files, against the rendered truth and against the mono camera on the same views."""
    base = quick.quick_cell("modern", scale=2)
    offsets = {}
    reductions: list[str] = []
    for colour in (False, True):
        cell = dataclasses.replace(base, camera=dataclasses.replace(base.camera, colour=colour))
        found = []
        for seed in range(4):
            image, truth, _ = quick.laser_frame(cell, seed=seed)
            path = tmp_path / f"laser_{colour}_{seed}.png"
            cv2.imwrite(str(path), image)
            gray, _ = load_laser_images(path)
            if colour:
                reductions.append(laser_gray(image)[1])
            prof = extract_stripe(gray, mode="precise")
            found.append(_offsets_from_truth_px(np.column_stack([prof.u, prof.v]), truth.uv))
        offsets[colour] = np.concatenate(found)
    # Where the red pixels clip, the frame is read as the mean of its channels.
    assert "mean" in reductions, reductions
    rms = {k: float(np.sqrt(np.mean(v**2))) for k, v in offsets.items()}
    # Measured: mono 0.110 px RMS on 2209 points, colour 0.148 px on 2069 (the mean of the
    # channels dilutes the dim stripe on the ink, so fewer points there; read by the red
    # channel alone: 0.171 px on 2163).
    assert rms[False] < 0.15
    assert rms[True] < 1.5 * rms[False]
    assert len(offsets[True]) > 0.85 * len(offsets[False])


def test_grey_frames_pass_through_and_bad_pairs_name_the_file(tmp_path):
    rng = np.random.default_rng(6)
    grey = rng.integers(0, 65535, (40, 50), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "on.png"), grey)
    cv2.imwrite(str(tmp_path / "small.png"), grey[:30])
    cv2.imwrite(str(tmp_path / "colour.png"), np.zeros((40, 50, 3), np.uint8))
    on, off = load_laser_images(tmp_path / "on.png")
    np.testing.assert_array_equal(on, grey)
    assert off is None
    with pytest.raises(InputError, match=r"small\.png: expected the size .* 50x40, got 50x30"):
        load_laser_images(tmp_path / "on.png", tmp_path / "small.png")
    with pytest.raises(InputError, match=r"colour\.png: colour differs"):
        load_laser_images(tmp_path / "on.png", tmp_path / "colour.png")
    with pytest.raises(InputError, match=r"missing\.png: image file not found"):
        load_laser_images(tmp_path / "on.png", tmp_path / "missing.png")
    with pytest.raises(ValueError, match="reduction: expected"):
        laser_gray(np.zeros((4, 4, 3), np.uint8), "sum")
