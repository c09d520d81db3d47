"""What a detector found in one target image: the contract between detection and calibration.

A :class:`TargetObservation` always carries exact point correspondences ``points_px`` (N, 2)
<-> ``points_target`` (N, 3), usable by any pose or intrinsics solver. For the
concentric-circles target it also carries everything the method and the nonlinear
adjustment need: every ring's sub-pixel edge points and fitted conic, points on both
diameter lines, the centre O, the named points O, A, B, C, D, the vanishing points p (x axis)
and q (y axis), and the orientation marker.

An observation is truthy when the target was found; otherwise ``reason`` says why.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

__all__ = ["AxisObservation", "RingObservation", "TargetObservation"]


def _empty2() -> NDArray:
    return np.zeros((0, 2))


def _empty3() -> NDArray:
    return np.zeros((0, 3))


@dataclass
class RingObservation:
    """One printed ring as seen in the image.

    Attributes
    ----------
    radius_mm : float
        Radius of the ring's centre line on the target, mm (the located curve).
    edge_points_px : ndarray, shape (M, 2)
        Sub-pixel points on the image of that centre line (u, v).
    conic : ndarray, shape (3, 3)
        Symmetric conic fitted to ``edge_points_px``: ``x^T C x = 0`` for ``x = (u, v, 1)``,
        normalised to unit Frobenius norm.
    index : int
        Position of the ring in the target spec (0 = smallest).
    """

    radius_mm: float
    edge_points_px: NDArray
    conic: NDArray
    index: int = -1


@dataclass
class AxisObservation:
    """Sub-pixel points on the image of one diameter line.

    Attributes
    ----------
    axis : str
        ``"x"`` (through B, O, A) or ``"y"`` (through D, O, C).
    points_px : ndarray, shape (M, 2)
        Points on the centre line of the printed diameter line; none (M = 0) where a laser
        stripe hides the diameter.
    line : ndarray, shape (3,)
        Homogeneous line ``l . (u, v, 1) = 0`` fitted to them, ``|l[:2]| = 1``; for a hidden
        diameter, the other one's conjugate with respect to the ring conics
        (:func:`calibration.detection.concentric_axes.conjugate_diameter`).
    """

    axis: str
    points_px: NDArray
    line: NDArray


@dataclass
class TargetObservation:
    """The target found (or not) in one image.

    Attributes
    ----------
    ok : bool
        True when the target was found and labelled; the observation's truth value.
    reason : str
        Why the target was not found (empty when ``ok``).
    image_size : tuple of int
        ``(width, height)`` of the image, pixels.
    kind : str
        The target kind: ``"concentric_circles"``, ``"chessboard"`` or ``"circle_grid"``.
    points_px : ndarray, shape (N, 2)
        Image points (u, v), distorted pixels as observed.
    points_target : ndarray, shape (N, 3)
        The same points in the target frame, mm (z = 0). For the concentric target:
        O, then per ring (+r, 0, 0), (-r, 0, 0), (0, +r, 0), (0, -r, 0) for the ends that are
        visible, each found as the intersection of the diameter line and the ring's image.
    point_names : list of str
        A label per point (``"O"``, ``"r3+x"``, ... or ``"c17"``).
    rings : list of RingObservation
        Concentric target only: every ring found, ascending radius.
    axis_points : list of AxisObservation
        Concentric target only: the x and y diameter lines.
    center_px : ndarray, shape (2,) or None
        Image of the centre O (from the pencil of ring conics and the diameter lines, never
        an ellipse centre).
    named_px : dict of str to ndarray, shape (2,)
        ``"O", "A", "B", "C", "D"`` where visible (A = +x end, C = +y end on the largest ring).
    vanishing_points : dict of str to ndarray, shape (3,)
        ``"p"`` (x axis) and ``"q"`` (y axis), homogeneous, from the harmonic conjugate of O
        with respect to the ends of the largest ring's diameters.
    marker_px : ndarray, shape (2,) or None
        Image of the orientation marker's centre.
    labelling : {"unique", "symmetry"}
        ``"unique"``: the points' target coordinates are certain (the concentric target's
        marker was seen; a chessboard's or grid's own pattern). ``"symmetry"``: the marker
        was not seen, the labelling is right up to a rotation of the target by a multiple of
        90 deg about its normal: good for intrinsics and the light plane, and for a hand-eye
        only once :func:`calibration.symmetry.resolve_quarter_turns` has resolved it.
    """

    ok: bool
    reason: str
    image_size: tuple[int, int]
    kind: str = ""
    points_px: NDArray = field(default_factory=_empty2)
    points_target: NDArray = field(default_factory=_empty3)
    point_names: list[str] = field(default_factory=list)
    rings: list[RingObservation] = field(default_factory=list)
    axis_points: list[AxisObservation] = field(default_factory=list)
    center_px: NDArray | None = None
    named_px: dict[str, NDArray] = field(default_factory=dict)
    vanishing_points: dict[str, NDArray] = field(default_factory=dict)
    marker_px: NDArray | None = None
    labelling: str = "unique"

    def __bool__(self) -> bool:
        return bool(self.ok)

    @classmethod
    def failed(cls, reason: str, image_size: tuple[int, int], kind: str = "") -> TargetObservation:
        """A not-found observation (falsy) saying why."""
        return cls(ok=False, reason=reason, image_size=image_size, kind=kind)

    @property
    def axis(self) -> dict[str, AxisObservation]:
        """The diameter lines by name, ``{"x": ..., "y": ...}``."""
        return {a.axis: a for a in self.axis_points}
