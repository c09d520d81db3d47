"""The paper's hand-eye (Section III.D): the stripe on the target's points O, A and C.

Each named point is seen with the stripe crossing it from at least two robot poses; its
camera-frame position is the stripe pixel's ray met with the light plane
(:class:`StripePointView`). The fixed-point constraints give ``T_ec`` in closed form, eqs.
(12)-(13) give O, A and C in the base frame, and ``T_ec = T_o6O^-1 T_ow T_wcO``
(:func:`paper_hand_eye`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration.hand_eye_views import HandEyeResult, check_robot_motion
from scanner.core.conventions import (
    invert_transform,
    make_transform,
    orthonormalize,
    transform_points,
)

__all__ = ["StripePointView", "paper_hand_eye"]


@dataclass
class StripePointView:
    """A posed view in which the stripe crosses one of the named target points.

    Attributes
    ----------
    frame_id : int
    name : str
        ``"O"``, ``"A"`` or ``"C"``.
    base_from_flange : ndarray, shape (4, 4)
    point_cam : ndarray, shape (3,)
        The named point in the camera frame: its stripe pixel's ray met with the light plane.
    cam_from_target : ndarray, shape (4, 4) or None
        The view's extrinsics (needed for the reference view aimed at O).
    """

    frame_id: int
    name: str
    base_from_flange: NDArray
    point_cam: NDArray
    cam_from_target: NDArray | None = None


def _linear_hand_eye_from_points(groups: dict[str, list[StripePointView]]) -> NDArray:
    """Closed form for X from fixed points seen at several poses.

    ``F_j X p_j = F_0 X p_0`` for every view j of the same point. Every ``p`` lies in the light
    plane ``n . p + d = 0``, so write ``p = -d n + alpha e1 + beta e2``; then
    ``X p = alpha (R e1) + beta (R e2) + (t - d R n)`` is linear in the nine unknowns
    ``a = R e1``, ``b = R e2``, ``s = t - d R n`` (the 12 entries of R and t are not all
    observable from coplanar points: a linear solve for them has a 3-D null space). R follows
    from ``[a, b, a x b]`` by SVD orthonormalisation, then the translation is re-solved.
    """
    all_p = np.array([v.point_cam for g in groups.values() for v in g])
    centre = all_p.mean(axis=0)
    _, sv, vt = np.linalg.svd(all_p - centre)
    if sv[1] < 1e-6 * max(sv[0], 1e-12):
        raise ValueError("paper hand-eye: the stripe points are collinear")
    e1, e2 = vt[0], vt[1]
    n = np.cross(e1, e2)  # right-handed basis: R n = R e1 x R e2
    if sv[2] > 1e-2 * sv[0]:
        return _linear_hand_eye_general(groups)
    rows, rhs = [], []
    for views in groups.values():
        ref = views[0]
        r_0, t_0 = ref.base_from_flange[:3, :3], ref.base_from_flange[:3, 3]
        a0, b0 = float(e1 @ ref.point_cam), float(e2 @ ref.point_cam)
        for v in views[1:]:
            r_j, t_j = v.base_from_flange[:3, :3], v.base_from_flange[:3, 3]
            aj, bj = float(e1 @ v.point_cam), float(e2 @ v.point_cam)
            rows.append(np.hstack([aj * r_j - a0 * r_0, bj * r_j - b0 * r_0, r_j - r_0]))
            rhs.append(t_0 - t_j)
    a = np.vstack(rows)
    b = np.concatenate(rhs)
    if np.linalg.matrix_rank(a, tol=1e-9 * np.abs(a).max()) < 9:
        raise ValueError("paper hand-eye: the views aimed at O, A and C do not determine T_ec")
    sol = np.linalg.lstsq(a, b, rcond=None)[0]
    ra, rb = sol[:3], sol[3:6]
    rn = np.cross(ra, rb)
    rn /= np.linalg.norm(rn)
    rot = orthonormalize(np.column_stack([ra, rb, rn]) @ np.vstack([e1, e2, n]))
    return _resolve_translation(groups, rot)


def _linear_hand_eye_general(groups: dict[str, list[StripePointView]]) -> NDArray:
    """The same constraints for points in general position: linear in vec(R) and t."""
    rows, rhs = [], []
    for views in groups.values():
        ref = views[0]
        r_0, t_0 = ref.base_from_flange[:3, :3], ref.base_from_flange[:3, 3]
        for v in views[1:]:
            r_j, t_j = v.base_from_flange[:3, :3], v.base_from_flange[:3, 3]
            m = r_j @ np.kron(np.eye(3), v.point_cam) - r_0 @ np.kron(np.eye(3), ref.point_cam)
            rows.append(np.hstack([m, r_j - r_0]))
            rhs.append(t_0 - t_j)
    a = np.vstack(rows)
    if np.linalg.matrix_rank(a, tol=1e-9 * np.abs(a).max()) < 12:
        raise ValueError("paper hand-eye: the views aimed at O, A and C do not determine T_ec")
    sol = np.linalg.lstsq(a, np.concatenate(rhs), rcond=None)[0]
    return _resolve_translation(groups, orthonormalize(sol[:9].reshape(3, 3)))


def _resolve_translation(groups: dict[str, list[StripePointView]], rot: NDArray) -> NDArray:
    """Least-squares translation of X with its rotation fixed."""
    # Re-solve the translation with the rotation fixed.
    rows_t, rhs_t = [], []
    for views in groups.values():
        ref = views[0]
        for v in views[1:]:
            r_j, t_j = v.base_from_flange[:3, :3], v.base_from_flange[:3, 3]
            r_0, t_0 = ref.base_from_flange[:3, :3], ref.base_from_flange[:3, 3]
            rows_t.append(r_j - r_0)
            rhs_t.append(t_0 - t_j - r_j @ rot @ v.point_cam + r_0 @ rot @ ref.point_cam)
    t = np.linalg.lstsq(np.vstack(rows_t), np.concatenate(rhs_t), rcond=None)[0]
    return make_transform(rot, t)


def _point_in_base_eq13(views: list[StripePointView], x: NDArray) -> NDArray:
    """Eqs. (12)-(13): the named point in the base frame, least squares over its views.

    Eq. (12) carries each view's stripe point ``i_c^j`` into the base through
    ``T_o6^j T_o6,0^-1 T_oi' T_wci0`` and ``T_oi' T_wci0 = T_o6,0 T_ec``, so every view gives
    ``i_o = T_o6^j T_ec i_c^j``; eq. (13) solves the stacked system by least squares, whose
    solution is the mean of those chains.
    """
    chains = [transform_points(v.base_from_flange @ x, v.point_cam.reshape(1, 3))[0] for v in views]
    return np.mean(chains, axis=0)


def paper_hand_eye(views: Sequence[StripePointView], radius_mm: float) -> HandEyeResult:
    """The paper's hand-eye (Section III.D) from views with the stripe on O, A and C.

    Parameters
    ----------
    views : sequence of StripePointView
        At least two views per point O, A and C; the first view aimed at O must carry its
        ``cam_from_target`` (the paper's T_cwO, e.g. from :func:`calibration.extrinsics.paper_pose`).
    radius_mm : float
        R = |OA| = |OC|, to report how far the recovered points are from the target's geometry.

    Returns
    -------
    HandEyeResult
        ``flange_from_cam = T_o6O^-1 T_ow T_wcO`` and ``base_from_target = T_ow`` built from
        O, A and C in the base frame; falsy with a reason when a point has too few views.

    Notes
    -----
    Eq. (13) as printed needs ``T_wci0``, which contains the unknown rotation of ``T_ec``.
    The rotation and translation of ``T_ec`` are first taken from the same fixed-point
    constraints ``T_o6^j T_ec i_c^j = T_o6^0 T_ec i_c^0`` (linear in the entries of ``R_ec``,
    SVD-orthonormalised), then O, A and C follow from eqs. (12)-(13) by least squares.
    """
    groups: dict[str, list[StripePointView]] = {"O": [], "A": [], "C": []}
    for v in views:
        if v.name not in groups:
            raise ValueError(f"view {v.frame_id}: expected name O, A or C, got {v.name!r}")
        groups[v.name].append(v)
    for name, g in groups.items():
        if len(g) < 2:
            return HandEyeResult(
                False,
                f"paper hand-eye: expected >= 2 views with the stripe on {name}, got {len(g)}",
                method="paper",
            )
    ref_o = next((v for v in groups["O"] if v.cam_from_target is not None), None)
    if ref_o is None:
        return HandEyeResult(
            False, "paper hand-eye: no view aimed at O has extrinsics", method="paper"
        )
    groups["O"].remove(ref_o)
    groups["O"].insert(0, ref_o)
    bf = np.stack([v.base_from_flange for v in views])
    reason = check_robot_motion(bf)
    if reason:
        return HandEyeResult(False, reason, method="paper")
    try:
        x_lin = _linear_hand_eye_from_points(groups)
    except ValueError as exc:
        return HandEyeResult(False, str(exc), method="paper")
    pts = {name: _point_in_base_eq13(g, x_lin) for name, g in groups.items()}
    o, a, c = pts["O"], pts["A"], pts["C"]
    x_axis = (a - o) / np.linalg.norm(a - o)
    y_axis = c - o
    z_axis = np.cross(x_axis, y_axis)
    z_axis /= np.linalg.norm(z_axis)
    y_axis = np.cross(z_axis, x_axis)
    base_from_target = make_transform(orthonormalize(np.column_stack([x_axis, y_axis, z_axis])), o)
    target_from_cam_o = invert_transform(ref_o.cam_from_target)  # type: ignore[arg-type]
    x = invert_transform(ref_o.base_from_flange) @ base_from_target @ target_from_cam_o
    per_pose = []
    for name, g in groups.items():
        for v in g:
            p_base = transform_points(v.base_from_flange @ x, v.point_cam.reshape(1, 3))[0]
            per_pose.append(
                {
                    "frame_id": int(v.frame_id),
                    "point": name,
                    "point_base_mm": p_base.tolist(),
                    "scatter_mm": float(np.linalg.norm(p_base - pts[name])),
                }
            )
    warnings = []
    for name, p in (("A", a), ("C", c)):
        err = abs(float(np.linalg.norm(p - o)) - radius_mm)
        if err > 1.0:
            warnings.append(f"|O{name}| differs from R = {radius_mm:.3f} mm by {err:.2f} mm")
    spread = np.std([q["point_base_mm"] for q in per_pose if q["point"] == "O"], axis=0, ddof=1)
    return HandEyeResult(
        True,
        flange_from_cam=x,
        base_from_target=base_from_target,
        method="paper",
        per_pose=per_pose,
        target_spread_mm=spread,
        warnings=warnings,
    )
