"""The compiled Hough transform against OpenCV's, line for line and bit for bit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.detection import concentric_rays
from calibration.detection.detect import detect_target
from calibration.detection.hough import HAVE_NUMBA, hough_lines
from scanner.core.targets import ConcentricCirclesTarget, OrientationMarker
from scanner.virtual_cell.randomised import draw_conditions, render_view
from tests.conftest import real_data_subdir

# (without numba the module calls OpenCV's own function: nothing to compare)
pytestmark = pytest.mark.skipif(not HAVE_NUMBA, reason="numba not installed")


def _opencv(mask: np.ndarray, step: float, threshold: int) -> np.ndarray:
    lines = cv2.HoughLines(mask, 1.0, step, threshold)
    return np.zeros((0, 2), np.float32) if lines is None else lines[:, 0, :]


def _mask(rng: np.random.Generator, h: int, w: int, n_lines: int, speckle: float) -> np.ndarray:
    """Thick lines at random places (many ties and flat-topped peaks) and speckle."""
    mask = np.zeros((h, w), np.uint8)
    for _ in range(n_lines):
        p, q = rng.integers(0, [w, h], size=(2, 2))
        cv2.line(mask, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), 255, int(rng.integers(1, 8)))
    mask[rng.random((h, w)) < speckle] = 1  # (any non-zero value votes)
    return mask


@pytest.mark.parametrize(
    ("h", "w", "step_deg", "threshold"),
    [
        (1024, 1280, 0.25, 81),
        (768, 1024, 0.25, 61),
        (480, 640, 1.0, 40),
        (97, 37, 0.25, 10),
        (64, 64, 0.5, 0),
        (50, 300, 0.3, 5),
    ],
)
def test_the_lines_are_opencvs_to_the_bit(h: int, w: int, step_deg: float, threshold: int) -> None:
    rng = np.random.default_rng([h, w, threshold])
    mask = _mask(rng, h, w, 20, 0.02)
    step = float(np.radians(step_deg))
    ours, theirs = hough_lines(mask, step, threshold), _opencv(mask, step, threshold)
    assert len(theirs) > 0
    assert ours.dtype == np.float32 and ours.shape == theirs.shape
    np.testing.assert_array_equal(ours, theirs)


def test_an_empty_mask_or_a_single_pixel_gives_what_opencv_gives() -> None:
    empty = np.zeros((40, 60), np.uint8)
    assert hough_lines(empty, np.pi / 720, 10).shape == (0, 2)
    dot = empty.copy()
    dot[20, 30] = 255
    np.testing.assert_array_equal(hough_lines(dot, np.pi / 180, 0), _opencv(dot, np.pi / 180, 0))


def test_the_detector_masks_of_rendered_views_give_opencvs_lines(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Real line masks (thick rings, diameters, clutter): the coarse stage's, on randomised
    views; the detector asks this module for its lines."""
    masks: list[tuple[np.ndarray, float, int]] = []

    def recording(mask: np.ndarray, step: float, threshold: int) -> np.ndarray:
        masks.append((mask.copy(), step, threshold))
        return hough_lines(mask, step, threshold)

    monkeypatch.setattr(concentric_rays, "hough_lines", recording)
    for i in range(3):
        rng = np.random.default_rng([0, 10_000 + i])
        view = render_view(draw_conditions(rng), rng)
        detect_target(view.image, view.spec)
    assert len(masks) >= 3
    for mask, step, threshold in masks:
        np.testing.assert_array_equal(
            hough_lines(mask, step, threshold), _opencv(mask, step, threshold)
        )


def test_real_captures_masks_give_opencvs_lines(monkeypatch: pytest.MonkeyPatch) -> None:
    """A real lens and real noise: the masks of ../shared/data/real's chessboard images
    (Zhang's, 640x480) and circle-grid images (1920x1080), where the detector refuses the
    view (no concentric target there) after its Hough lines."""
    masks: list[tuple[np.ndarray, float, int]] = []

    def recording(mask: np.ndarray, step: float, threshold: int) -> np.ndarray:
        masks.append((mask.copy(), step, threshold))
        return hough_lines(mask, step, threshold)

    monkeypatch.setattr(concentric_rays, "hough_lines", recording)
    spec = ConcentricCirclesTarget(
        ring_diameters_mm=(20.0, 40.0, 60.0, 80.0, 100.0, 120.0),
        line_width_mm=0.6,
        orientation_marker=OrientationMarker(diameter_mm=6.0, center_mm=(66.0, 0.0)),
    )
    frames = [real_data_subdir("zhang_msr") / "CalibIm1.png"]
    frames += sorted((real_data_subdir("zhaocongyang_linelight") / "calib_picture").iterdir())[:1]
    for path in frames:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        assert image is not None, path
        detect_target(image, spec)
    assert len(masks) >= 2 and all(np.count_nonzero(m) > 1000 for m, _, _ in masks)
    for mask, step, threshold in masks:
        np.testing.assert_array_equal(
            hough_lines(mask, step, threshold), _opencv(mask, step, threshold)
        )


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="expected a 2-D uint8 array, got float64"):
        hough_lines(np.zeros((4, 4)), 0.1, 1)
    with pytest.raises(ValueError, match=r"expected a finite step > 0 \(in float32\), got 0\.0"):
        hough_lines(np.zeros((4, 4), np.uint8), 0.0, 1)
    with pytest.raises(ValueError, match=r"threshold: expected an integer, got 10\.7"):
        hough_lines(np.zeros((4, 4), np.uint8), 0.1, 10.7)
