"""The one place that states the conventions, and the helpers that enforce them.

Frames
------
``base``   robot base (the paper's {o}), the reference frame of every scan.
``flange`` robot end effector / tool flange ({e}).
``cam``    camera: origin at the optical centre, x right, y down, z along the optical axis ({c}).
``target`` calibration target: origin at the common centre O of the rings, x towards A
           (the diameter end marked by the orientation disc), z out of the printed face ({w}).

Transforms
----------
A transform named ``a_from_b`` is a 4x4 float64 homogeneous matrix mapping points given in
frame b into frame a: ``p_a = a_from_b @ p_b``. Names cancel when composing::

    base_from_cam = base_from_flange @ flange_from_cam

The paper's T_ec is ``flange_from_cam``, T_o6 is ``base_from_flange``, T_ow is
``base_from_target`` and T_cw is ``cam_from_target``.

Units
-----
Lengths in millimetres everywhere inside the code; angles in radians unless a name ends in
``_deg``. A boundary that takes another unit says so in the name (``pose_m``).

Pixels
------
OpenCV convention: u = column, v = row, origin at the centre of the top-left pixel. Lens
distortion follows OpenCV's model and order ``(k1, k2, p1, p2, k3)``.

Robot poses
-----------
Robot controllers report the flange pose as a position (mm) and a rotation in one of four
conventions (``RotationConvention``); :func:`pose_to_transform` turns them into
``base_from_flange`` through ``scipy.spatial.transform.Rotation``.
"""

from __future__ import annotations

from enum import Enum

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

__all__ = [
    "FRAMES",
    "QUATERNION_NORM_TOLERANCE",
    "RotationConvention",
    "angle_between_rotations_deg",
    "check_points",
    "check_transform",
    "invert_transform",
    "make_transform",
    "orthonormalize",
    "pose_to_transform",
    "rotation_columns",
    "transform_points",
    "transform_to_pose",
]

FRAMES = ("base", "flange", "cam", "target")

#: A quaternion whose norm differs from 1 by more than this is refused as a transcription error.
QUATERNION_NORM_TOLERANCE = 1e-3


class RotationConvention(str, Enum):
    """How the rotation columns of a capture session's ``frames.csv`` read."""

    QUATERNION_WXYZ = "quaternion_wxyz"
    """Columns ``qw,qx,qy,qz``: unit quaternion, scalar first (ABB and most ROS tools)."""
    ROTVEC_RAD = "rotvec_rad"
    """Columns ``rx,ry,rz``: rotation axis times angle in radians (Universal Robots)."""
    EULER_XYZ_DEG = "euler_xyz_deg"
    """Columns ``rx,ry,rz``: fixed axes x, then y, then z, degrees (Yaskawa/MOTOMAN):
    ``R = Rz(rz) @ Ry(ry) @ Rx(rx)``."""
    EULER_ZYX_DEG = "euler_zyx_deg"
    """Columns ``rx,ry,rz`` holding KUKA's A, B, C, degrees: about z by A, then the new y by B,
    then the new x by C: ``R = Rz(A) @ Ry(B) @ Rx(C)``."""

    @classmethod
    def parse(cls, value: str, where: str = "rotation") -> RotationConvention:
        try:
            return cls(value)
        except ValueError:
            known = ", ".join(c.value for c in cls)
            raise ValueError(
                f"{where}: unknown rotation convention {value!r}; expected one of {known}"
            ) from None


def rotation_columns(convention: RotationConvention) -> tuple[str, ...]:
    """Names of the ``frames.csv`` columns that hold the rotation for ``convention``."""
    if convention is RotationConvention.QUATERNION_WXYZ:
        return ("qw", "qx", "qy", "qz")
    return ("rx", "ry", "rz")


def check_transform(matrix: ArrayLike, name: str = "transform", tol: float = 1e-6) -> NDArray:
    """Return ``matrix`` as a checked 4x4 float64 rigid transform (a copy).

    Raises
    ------
    ValueError
        Saying expected versus got: wrong shape, non-finite entries, a bottom row other than
        ``[0, 0, 0, 1]``, or a rotation block that is not orthonormal with determinant +1.
    """
    m = np.array(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"{name}: expected a 4x4 matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name}: expected finite entries, got NaN or inf")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=tol):
        raise ValueError(f"{name}: expected bottom row [0, 0, 0, 1], got {m[3].tolist()}")
    rot = m[:3, :3]
    ortho_err = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if ortho_err > max(tol, 1e-6) * 100:
        raise ValueError(
            f"{name}: expected an orthonormal rotation block, got R^T R off identity by {ortho_err:.2e}"
        )
    det = float(np.linalg.det(rot))
    if det < 0:
        raise ValueError(f"{name}: expected a proper rotation (det +1), got det {det:.4f}")
    return m


def make_transform(rotation: ArrayLike | Rotation, translation: ArrayLike) -> NDArray:
    """Build ``a_from_b`` from a rotation (3x3 matrix or ``Rotation``) and a translation (mm)."""
    rot = rotation.as_matrix() if isinstance(rotation, Rotation) else np.asarray(rotation, float)
    t = np.asarray(translation, dtype=np.float64).reshape(-1)
    if rot.shape != (3, 3):
        raise ValueError(f"rotation: expected shape (3, 3), got {rot.shape}")
    if t.shape != (3,):
        raise ValueError(f"translation: expected 3 values, got {t.shape[0]}")
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = t
    return m


def invert_transform(a_from_b: ArrayLike) -> NDArray:
    """Return ``b_from_a`` exactly (rotation transposed, not a general matrix inverse)."""
    m = np.asarray(a_from_b, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"expected a 4x4 transform, got shape {m.shape}")
    inv = np.eye(4)
    inv[:3, :3] = m[:3, :3].T
    inv[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return inv


def check_points(
    points: ArrayLike, min_count: int = 1, name: str = "points", dim: int = 3
) -> NDArray:
    """Return ``points`` as a float64 ``(N, dim)`` array with N >= ``min_count`` (a copy).

    Raises
    ------
    ValueError
        "points: expected (N, 3) with N >= 3, got (2, 3)", or non-finite values.
    """
    p = np.array(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != dim or p.shape[0] < min_count:
        raise ValueError(f"{name}: expected (N, {dim}) with N >= {min_count}, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    return p


def transform_points(a_from_b: ArrayLike, points_b: ArrayLike) -> NDArray:
    """Map ``(N, 3)`` points from frame b to frame a."""
    m = np.asarray(a_from_b, dtype=np.float64)
    p = np.asarray(points_b, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"expected a 4x4 transform, got shape {m.shape}")
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points: expected shape (N, 3), got {p.shape}")
    return p @ m[:3, :3].T + m[:3, 3]


def orthonormalize(rotation: ArrayLike) -> NDArray:
    """Nearest proper rotation matrix in the Frobenius sense (SVD), e.g. for printed tables."""
    u, _, vt = np.linalg.svd(np.asarray(rotation, dtype=np.float64))
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return r


def angle_between_rotations_deg(r_a: ArrayLike, r_b: ArrayLike) -> float:
    """Angle of the rotation taking ``r_a`` to ``r_b`` (3x3 or 4x4 inputs), degrees."""
    a = np.asarray(r_a, dtype=np.float64)[:3, :3]
    b = np.asarray(r_b, dtype=np.float64)[:3, :3]
    return float(np.degrees(Rotation.from_matrix(a.T @ b).magnitude()))


def _rotation_from_values(values: NDArray, convention: RotationConvention) -> Rotation:
    if convention is RotationConvention.QUATERNION_WXYZ:
        if values.shape[-1] != 4:
            raise ValueError(f"quaternion_wxyz: expected 4 values, got {values.shape[-1]}")
        norm = np.linalg.norm(values, axis=-1)
        bad = np.abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE
        if np.any(bad):
            first = float(np.atleast_1d(norm)[np.argmax(np.atleast_1d(bad))])
            raise ValueError(
                f"quaternion_wxyz: expected unit norm (within {QUATERNION_NORM_TOLERANCE}), "
                f"got norm {first:.6f}"
            )
        xyzw = np.concatenate([values[..., 1:], values[..., :1]], axis=-1)
        return Rotation.from_quat(xyzw)
    if values.shape[-1] != 3:
        raise ValueError(f"{convention.value}: expected 3 values, got {values.shape[-1]}")
    if convention is RotationConvention.ROTVEC_RAD:
        return Rotation.from_rotvec(values)
    if convention is RotationConvention.EULER_XYZ_DEG:
        # Fixed (extrinsic) axes x, y, z: R = Rz @ Ry @ Rx.
        return Rotation.from_euler("xyz", values, degrees=True)
    # KUKA A, B, C: intrinsic z, y', x'': R = Rz(A) @ Ry(B) @ Rx(C).
    return Rotation.from_euler("ZYX", values, degrees=True)


def pose_to_transform(
    position_mm: ArrayLike, rotation_values: ArrayLike, convention: RotationConvention | str
) -> NDArray:
    """Turn a robot controller's pose into ``base_from_flange``.

    Parameters
    ----------
    position_mm : array_like, shape (3,) or (N, 3)
        Flange position in the base frame, mm.
    rotation_values : array_like, shape (3,) or (4,), or (N, 3) / (N, 4)
        Rotation columns as the convention reads them (see :class:`RotationConvention`).
    convention : RotationConvention or str

    Returns
    -------
    ndarray, shape (4, 4) or (N, 4, 4)
    """
    conv = RotationConvention.parse(convention) if isinstance(convention, str) else convention
    pos = np.asarray(position_mm, dtype=np.float64)
    vals = np.asarray(rotation_values, dtype=np.float64)
    single = pos.ndim == 1
    pos = np.atleast_2d(pos)
    vals = np.atleast_2d(vals)
    if pos.shape[1] != 3:
        raise ValueError(f"position: expected 3 values, got {pos.shape[1]}")
    if pos.shape[0] != vals.shape[0]:
        raise ValueError(
            f"expected as many rotations as positions, got {vals.shape[0]} and {pos.shape[0]}"
        )
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(vals))):
        raise ValueError("pose: expected finite values, got NaN or inf")
    rot = _rotation_from_values(vals, conv).as_matrix().reshape(-1, 3, 3)
    out = np.tile(np.eye(4), (pos.shape[0], 1, 1))
    out[:, :3, :3] = rot
    out[:, :3, 3] = pos
    return out[0] if single else out


def transform_to_pose(
    base_from_flange: ArrayLike, convention: RotationConvention | str
) -> tuple[NDArray, NDArray]:
    """Inverse of :func:`pose_to_transform`: ``(position_mm, rotation_values)``.

    Quaternions are returned with ``qw >= 0``.
    """
    conv = RotationConvention.parse(convention) if isinstance(convention, str) else convention
    m = np.asarray(base_from_flange, dtype=np.float64)
    single = m.ndim == 2
    m = m.reshape(-1, 4, 4)
    rot = Rotation.from_matrix(m[:, :3, :3])
    if conv is RotationConvention.QUATERNION_WXYZ:
        xyzw = rot.as_quat()
        vals = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
        vals[vals[:, 0] < 0] *= -1
    elif conv is RotationConvention.ROTVEC_RAD:
        vals = rot.as_rotvec()
    elif conv is RotationConvention.EULER_XYZ_DEG:
        vals = rot.as_euler("xyz", degrees=True)
    else:
        vals = rot.as_euler("ZYX", degrees=True)
    pos = m[:, :3, 3].copy()
    return (pos[0], vals[0]) if single else (pos, vals)
