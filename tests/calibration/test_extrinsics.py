"""Extrinsics: PnP with refinement, and the paper's vanishing-point construction."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.extrinsics import (
    estimate_pose,
    paper_pose,
    paper_rotation_from_vanishing_points,
    pose_covariance_as_turns,
    project_target,
    rodrigues_align,
)
from scanner.core.camera import CameraModel
from scanner.core.conventions import angle_between_rotations_deg, transform_points
from scanner.formats.calibration_file import LightPlane
from tests.calibration import _synthetic as S


def test_estimate_pose_recovers_truth_with_honest_uncertainty():
    rng = np.random.default_rng(0)
    cam = S.camera()
    pts = S.grid_points()
    for _ in range(5):
        ct = S.look_at_target(rng)
        uv = project_target(cam, ct, pts) + rng.normal(0, 0.1, (len(pts), 2))
        pose = estimate_pose(uv, pts, cam)
        assert pose, pose.reason
        dr = angle_between_rotations_deg(pose.cam_from_target, ct)
        dt = np.linalg.norm(pose.cam_from_target[:3, 3] - ct[:3, 3])
        assert dr < 0.05 and dt < 0.2
        assert dt < 5 * np.linalg.norm(pose.std_translation_mm)
        assert abs(pose.rms_px - 0.1 * np.sqrt(2)) < 0.05


def test_estimate_pose_reports_too_few_points_and_checks_shapes():
    cam = S.camera()
    pose = estimate_pose(np.zeros((3, 2)), np.zeros((3, 3)), cam)
    assert not pose and ">= 4" in pose.reason
    with pytest.raises(ValueError, match="as many"):
        estimate_pose(np.zeros((5, 2)), np.zeros((4, 3)), cam)


def test_rodrigues_matrix_maps_the_normal_onto_the_optical_axis():
    n = np.array([0.2, -0.4, 0.9])
    r = rodrigues_align(n)
    assert np.allclose(r @ (n / np.linalg.norm(n)), [0, 0, 1], atol=1e-12)
    assert np.isclose(np.linalg.det(r), 1.0)


@pytest.mark.parametrize("flip_p", [1.0, -1.0])
@pytest.mark.parametrize("flip_q", [1.0, -1.0])
def test_paper_rotation_handles_the_four_sign_cases(flip_p, flip_q):
    # An ideal camera (no distortion): vanishing points are K r1 and K r2, up to sign and scale.
    rng = np.random.default_rng(1)
    cam0 = S.camera()
    cam = CameraModel(cam0.width, cam0.height, cam0.K, np.zeros(5))
    r = 80.0
    named_t = np.array([[0, 0, 0], [r, 0, 0], [0, r, 0]], float)
    for _ in range(4):
        ct = S.look_at_target(rng, tilt_deg=35)
        p = flip_p * 3.7 * cam.K @ ct[:3, 0]
        q = flip_q * 0.2 * cam.K @ ct[:3, 1]
        o, a, c = project_target(cam, ct, named_t)
        r_cw = paper_rotation_from_vanishing_points(cam, p, q, o, a, c)
        assert angle_between_rotations_deg(r_cw, ct[:3, :3]) < 1e-6


def test_paper_pose_translation_from_the_stripe_on_o():
    rng = np.random.default_rng(2)
    cam0 = S.camera()
    cam = CameraModel(cam0.width, cam0.height, cam0.K, np.zeros(5))
    ct = S.look_at_target(rng)
    r = 80.0
    o, a, c = project_target(cam, ct, np.array([[0, 0, 0], [r, 0, 0], [0, r, 0]], float))
    o_cam = ct[:3, 3]
    # A light plane through O (and tilted arbitrarily).
    n = np.array([0.95, 0.05, 0.3])
    plane = LightPlane(n, -float(n @ o_cam))
    pose = paper_pose(cam, cam.K @ ct[:3, 0], cam.K @ ct[:3, 1], o, a, c, o, plane)
    assert pose, pose.reason
    assert np.linalg.norm(pose.cam_from_target[:3, 3] - o_cam) < 1e-6
    assert angle_between_rotations_deg(pose.cam_from_target, ct) < 1e-6
    # A point of the target lands where it should.
    p = transform_points(pose.cam_from_target, np.array([[10.0, 20.0, 0.0]]))
    assert np.allclose(p, transform_points(ct, np.array([[10.0, 20.0, 0.0]])), atol=1e-6)


@pytest.mark.parametrize("angle_rad", [0.4, 3.1])  # 3.1: a camera looking down at the target
def test_pose_covariance_as_turns_matches_sampled_turns(angle_rad):
    # Rotation vectors drawn from the covariance, each turned into exp(w) R(r): the sampled
    # w's covariance is what the conversion gives, near 180 deg too (where a vector and its
    # equivalent on the far side differ by 2 pi).
    rng = np.random.default_rng(5)
    axis = np.array([0.9, 0.3, -0.2])
    r = angle_rad * axis / np.linalg.norm(axis)
    a = rng.normal(size=(6, 6)) * 1e-3
    cov = a @ a.T
    turned = pose_covariance_as_turns(r, cov)
    draws = rng.multivariate_normal(np.zeros(6), cov, size=20_000)
    base = Rotation.from_rotvec(r).inv()
    w = (Rotation.from_rotvec(r + draws[:, :3]) * base).as_rotvec()
    sampled = np.cov(np.column_stack([w, draws[:, 3:]]).T)
    scale = np.sqrt(np.outer(np.diag(turned), np.diag(turned)))
    assert np.max(np.abs(sampled - turned) / scale) < 0.05
    assert np.allclose(turned[3:, 3:], cov[3:, 3:])  # translations are left as they are
    with pytest.raises(ValueError, match=r"expected shape \(6, 6\)"):
        pose_covariance_as_turns(r, np.eye(3))
