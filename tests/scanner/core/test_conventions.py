import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from scanner.core.conventions import (
    RotationConvention,
    angle_between_rotations_deg,
    check_points,
    check_transform,
    invert_transform,
    make_transform,
    orthonormalize,
    pose_to_transform,
    transform_points,
    transform_to_pose,
)

RZ90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def random_transform(rng: np.random.Generator) -> np.ndarray:
    return make_transform(Rotation.random(random_state=rng), rng.uniform(-500, 500, 3))


def test_invert_transform_composes_to_identity():
    rng = np.random.default_rng(0)
    a_from_b = random_transform(rng)
    np.testing.assert_allclose(a_from_b @ invert_transform(a_from_b), np.eye(4), atol=1e-12)


def test_transform_points_matches_homogeneous_product():
    rng = np.random.default_rng(1)
    a_from_b = random_transform(rng)
    points_b = rng.normal(size=(10, 3)) * 100
    homog = np.column_stack([points_b, np.ones(10)]) @ a_from_b.T
    np.testing.assert_allclose(transform_points(a_from_b, points_b), homog[:, :3], atol=1e-9)


def test_names_cancel_when_composing():
    rng = np.random.default_rng(2)
    base_from_flange, flange_from_cam = random_transform(rng), random_transform(rng)
    points_cam = rng.normal(size=(5, 3))
    base_from_cam = base_from_flange @ flange_from_cam
    np.testing.assert_allclose(
        transform_points(base_from_cam, points_cam),
        transform_points(base_from_flange, transform_points(flange_from_cam, points_cam)),
        atol=1e-9,
    )


@pytest.mark.parametrize(
    ("matrix", "message"),
    [
        (np.eye(3), "expected a 4x4 matrix, got shape (3, 3)"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "det"),
        (np.diag([2.0, 1.0, 1.0, 1.0]), "orthonormal"),
        (np.full((4, 4), np.nan), "finite"),
    ],
)
def test_check_transform_says_expected_versus_got(matrix, message):
    with pytest.raises(ValueError, match="expected") as err:
        check_transform(matrix, "flange_from_cam")
    assert message in str(err.value)
    assert "flange_from_cam" in str(err.value)


def test_check_points_names_shapes():
    with pytest.raises(ValueError, match=r"expected \(N, 3\) with N >= 3, got \(2, 3\)"):
        check_points(np.zeros((2, 3)), min_count=3)


@pytest.mark.parametrize("convention", list(RotationConvention))
def test_pose_round_trip_in_every_convention(convention):
    rng = np.random.default_rng(3)
    base_from_flange = np.stack([random_transform(rng) for _ in range(50)])
    pos, vals = transform_to_pose(base_from_flange, convention)
    back = pose_to_transform(pos, vals, convention)
    np.testing.assert_allclose(back, base_from_flange, atol=1e-10)


def test_yaskawa_fixed_xyz_hand_computed():
    # Fixed axes: x by 90, then z by 90 -> R = Rz(90) @ Rx(90), worked out by hand.
    expected = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    m = pose_to_transform([1, 2, 3], [90.0, 0.0, 90.0], "euler_xyz_deg")
    np.testing.assert_allclose(m[:3, :3], expected, atol=1e-12)
    np.testing.assert_allclose(m[:3, 3], [1, 2, 3])


def test_kuka_abc_hand_computed():
    # A about z, then B about the new y, then C about the new x: R = Rz(A) Ry(B) Rx(C).
    expected = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # A=90, C=90
    np.testing.assert_allclose(
        pose_to_transform([0, 0, 0], [90.0, 0.0, 90.0], "euler_zyx_deg")[:3, :3],
        expected,
        atol=1e-12,
    )
    ry90 = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    np.testing.assert_allclose(
        pose_to_transform([0, 0, 0], [0.0, 90.0, 0.0], "euler_zyx_deg")[:3, :3], ry90, atol=1e-12
    )
    # KUKA's A is about z: A=90 alone is Rz(90), not Rx(90).
    np.testing.assert_allclose(
        pose_to_transform([0, 0, 0], [90.0, 0.0, 0.0], "euler_zyx_deg")[:3, :3], RZ90, atol=1e-12
    )


def test_universal_robots_rotvec_hand_computed():
    m = pose_to_transform([0, 0, 0], [0.0, 0.0, np.pi / 2], "rotvec_rad")
    np.testing.assert_allclose(m[:3, :3], RZ90, atol=1e-12)


def test_quaternion_is_scalar_first():
    s = np.sqrt(0.5)
    m = pose_to_transform([0, 0, 0], [s, 0.0, 0.0, s], "quaternion_wxyz")
    np.testing.assert_allclose(m[:3, :3], RZ90, atol=1e-12)


def test_quaternion_far_from_unit_norm_is_refused():
    with pytest.raises(ValueError, match="unit norm"):
        pose_to_transform([0, 0, 0], [1.0, 0.1, 0.0, 0.0], "quaternion_wxyz")


def test_unknown_convention_lists_the_known_ones():
    with pytest.raises(ValueError, match="euler_zyx_deg"):
        pose_to_transform([0, 0, 0], [0, 0, 0], "abc_deg")


def test_orthonormalize_repairs_a_printed_table():
    printed = np.array(
        [[0.7234, 0.5888, 0.3605], [-0.1897, -0.3326, 0.9238], [0.6639, -0.7367, -0.1289]]
    )
    r = orthonormalize(printed)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) > 0
    assert angle_between_rotations_deg(r, printed) < 0.2
