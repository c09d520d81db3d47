import numpy as np
import pytest

from calibration.detection.detect import detect_target
from calibration.detection.observations import TargetObservation
from scanner.core.images import to_gray_float
from tests.calibration.synth_concentric import demo_target


def test_to_gray_float_scales_8_and_16_bit_and_colour():
    assert to_gray_float(np.full((2, 2), 255, np.uint8)).max() == pytest.approx(1.0)
    assert to_gray_float(np.full((2, 2), 65535, np.uint16)).max() == pytest.approx(1.0)
    bgr = np.zeros((2, 2, 3), np.uint8)
    bgr[..., 1] = 255
    assert to_gray_float(bgr)[0, 0] == pytest.approx(0.587)
    with pytest.raises(ValueError, match="expected a 2-D grey image"):
        to_gray_float(np.zeros((2, 2, 2)))


def test_detect_target_refuses_unknown_target_kind():
    with pytest.raises(ValueError, match="expected a ConcentricCirclesTarget"):
        detect_target(np.zeros((10, 10), np.uint8), object())


def test_failed_observation_is_falsy_with_reason():
    obs = detect_target(np.full((64, 80), 128, np.uint8), demo_target())
    assert isinstance(obs, TargetObservation)
    assert not obs
    assert obs.reason
    assert obs.image_size == (80, 64)
    assert obs.points_px.shape == (0, 2)
    assert obs.points_target.shape == (0, 3)
