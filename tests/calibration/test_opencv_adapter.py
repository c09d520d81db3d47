"""The adapter's names: OpenCV's solvers recover our flange_from_cam and base_from_target."""

import numpy as np
import pytest

from calibration.opencv_adapter import (
    AX_XB_METHODS,
    AX_ZB_METHODS,
    hand_eye_ax_xb,
    robot_world_hand_eye_ax_zb,
)
from scanner.core.conventions import angle_between_rotations_deg, invert_transform
from tests.calibration import _synthetic as S


def _motion(n: int = 10, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    cam_from_target = np.stack([S.look_at_target(rng) for _ in range(n)])
    base_from_flange = np.stack(
        [
            S.BASE_FROM_TARGET @ invert_transform(c) @ invert_transform(S.FLANGE_FROM_CAM)
            for c in cam_from_target
        ]
    )
    return base_from_flange, cam_from_target


@pytest.mark.parametrize("method", list(AX_XB_METHODS))
def test_ax_xb_solvers_recover_flange_from_cam_from_exact_motion(method):
    bf, ct = _motion()
    x = hand_eye_ax_xb(bf, ct, method)
    assert angle_between_rotations_deg(x, S.FLANGE_FROM_CAM) < 1e-4
    assert np.linalg.norm(x[:3, 3] - S.FLANGE_FROM_CAM[:3, 3]) < 1e-3


@pytest.mark.parametrize("method", list(AX_ZB_METHODS))
def test_ax_zb_solvers_recover_both_transforms(method):
    bf, ct = _motion()
    x, z = robot_world_hand_eye_ax_zb(bf, ct, method)
    assert angle_between_rotations_deg(x, S.FLANGE_FROM_CAM) < 1e-3
    assert np.linalg.norm(x[:3, 3] - S.FLANGE_FROM_CAM[:3, 3]) < 1e-2
    assert angle_between_rotations_deg(z, S.BASE_FROM_TARGET) < 1e-3
    assert np.linalg.norm(z[:3, 3] - S.BASE_FROM_TARGET[:3, 3]) < 1e-2


def test_adapter_refuses_unknown_method_and_too_few_poses():
    bf, ct = _motion(5)
    with pytest.raises(ValueError, match="expected one of"):
        hand_eye_ax_xb(bf, ct, "nope")
    with pytest.raises(ValueError, match=">= 3"):
        hand_eye_ax_xb(bf[:2], ct[:2])
    with pytest.raises(ValueError, match="shape"):
        robot_world_hand_eye_ax_zb(bf[:, :3], ct)
