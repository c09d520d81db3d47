"""Views of the concentric target labelled up to its symmetry, resolved by the robot's motion.

Without the orientation marker the detector labels a view right up to a rotation of the target
by ``k`` quarter turns about its normal (``TargetObservation.labelling == "symmetry"``). The
rings and the diameter lines look the same under it, so the intrinsics and the light plane use
such views as they are. A hand-eye does not: the view's pose is turned by ``k`` quarter turns.
Once the uniquely labelled views give a first hand-eye, each posed view's target pose is
predicted from the robot (``cam_from_target = inv(base_from_flange @ flange_from_cam) @
base_from_target``) and the quarter turn that brings the measured pose onto the prediction is
taken, when one clearly does; the others stay out of the hand-eye.

Conventions: with the detector's labelling the view's points have target coordinates
``X_found``; the true ones are ``X_true = turn(k)^-1 X_found`` and ``cam_from_target_true =
cam_from_target_found @ turn(k)``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from calibration.detection.observations import TargetObservation

__all__ = ["QuarterTurns", "relabel", "resolve_quarter_turns", "turn"]

#: The measured pose must lie within this of the predicted one after the turn (deg). The
#: turns are 90 deg apart, so every other turn then lies beyond 70 deg: a clear decision.
MAX_ANGLE_DEG = 20.0


def turn(quarter_turns: int) -> NDArray[np.float64]:
    """``(4, 4)`` rotation about the target's z axis by ``quarter_turns`` x 90 deg."""
    t = np.eye(4)
    t[:3, :3] = Rotation.from_euler("z", 90.0 * (quarter_turns % 4), degrees=True).as_matrix()
    return np.round(t, 15)


@dataclass(frozen=True)
class QuarterTurns:
    """The resolved labelling of one view; falsy with a reason when it stays ambiguous.

    Attributes
    ----------
    quarter_turns : int or None
        ``k`` in 0..3 (``cam_from_target_true = cam_from_target_found @ turn(k)``).
    angle_deg : float
        Rotation between the turned measured pose and the predicted one.
    runner_up_deg : float
        The same for the next best turn.
    reason : str
    """

    quarter_turns: int | None
    angle_deg: float
    runner_up_deg: float
    reason: str = ""

    def __bool__(self) -> bool:
        return self.quarter_turns is not None


def resolve_quarter_turns(
    cam_from_target_found: NDArray, cam_from_target_predicted: NDArray
) -> QuarterTurns:
    """The quarter turn that brings the measured pose ``(4, 4)`` onto the predicted one.

    Parameters
    ----------
    cam_from_target_found : ndarray, shape (4, 4)
        The view's pose with the detector's labelling.
    cam_from_target_predicted : ndarray, shape (4, 4)
        The pose a first hand-eye and the robot predict.

    Returns
    -------
    QuarterTurns
        Falsy when no turn lies within :data:`MAX_ANGLE_DEG`.
    """
    predicted = Rotation.from_matrix(np.asarray(cam_from_target_predicted)[:3, :3])
    angles = np.array(
        [
            np.degrees(
                (
                    predicted.inv()
                    * Rotation.from_matrix((np.asarray(cam_from_target_found) @ turn(k))[:3, :3])
                ).magnitude()
            )
            for k in range(4)
        ]
    )
    order = np.argsort(angles)
    best, runner_up = float(angles[order[0]]), float(angles[order[1]])
    if best > MAX_ANGLE_DEG:
        return QuarterTurns(
            None, best, runner_up, f"no quarter turn within {MAX_ANGLE_DEG:g} deg ({best:.1f})"
        )
    return QuarterTurns(int(order[0]), best, runner_up)


def _point_name(xyz: NDArray, ring: str) -> str:
    if not np.any(np.abs(xyz[:2]) > 1e-9):
        return "O"
    axis = 0 if abs(xyz[0]) > abs(xyz[1]) else 1
    return f"{ring}{'+' if xyz[axis] > 0 else '-'}{'xy'[axis]}"


def relabel(obs: TargetObservation, quarter_turns: int) -> TargetObservation:
    """The observation with its target coordinates turned to the true labelling.

    Point names, the named ends A-D, the diameter lines' names and the vanishing points follow;
    ``labelling`` becomes ``"unique"``.
    """
    k = quarter_turns % 4
    inverse = turn(k)[:3, :3].T
    points_target = np.round(obs.points_target @ inverse.T, 9)
    names = [
        _point_name(xyz, old.split("+")[0].split("-")[0])
        for xyz, old in zip(points_target, obs.point_names)
    ]
    # A-D lie on the largest ring measured, as the detector names them.
    largest = max(
        (r.radius_mm for r in obs.rings),
        default=max((np.linalg.norm(p[:2]) for p in points_target), default=0.0),
    )
    key = {"+x": "A", "-x": "B", "+y": "C", "-y": "D"}
    named = {"O": obs.named_px["O"]} if "O" in obs.named_px else {}
    for xyz, name, px in zip(points_target, names, obs.points_px):
        if name != "O" and abs(np.linalg.norm(xyz[:2]) - largest) < 1e-6:
            named[key[name[-2:]]] = px
    odd = k % 2 == 1
    axes = [
        dataclasses.replace(a, axis={"x": "y", "y": "x"}[a.axis] if odd else a.axis)
        for a in obs.axis_points
    ]
    vps = dict(obs.vanishing_points)
    if odd and {"p", "q"} <= vps.keys():
        vps = {"p": vps["q"], "q": vps["p"]}
    return dataclasses.replace(
        obs,
        points_target=points_target,
        point_names=names,
        named_px=named,
        axis_points=sorted(axes, key=lambda a: a.axis),
        vanishing_points=vps,
        labelling="unique",
    )
