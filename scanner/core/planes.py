"""How far one plane is from another: the light plane's accuracy figures.

A plane is ``normal . p + d = 0`` with a unit normal; the same plane has two descriptions
(``normal, d`` and ``-normal, -d``), so the comparison aligns the normals' signs first.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

__all__ = ["Plane", "plane_errors"]


class Plane(Protocol):
    """Anything with a unit ``normal`` (3,) and an offset ``d``: ``normal . p + d = 0``."""

    @property
    def normal(self) -> NDArray: ...

    @property
    def d(self) -> float: ...


def plane_errors(plane: Plane, truth: Plane) -> tuple[float, float]:
    """Angle between the normals and difference of the offsets, signs aligned.

    Parameters
    ----------
    plane, truth : Plane
        The estimate and the reference, unit normals.

    Returns
    -------
    angle_deg : float
        Angle between the two normals, degrees (0 to 90).
    d_mm : float
        ``d`` of ``plane`` minus ``d`` of ``truth`` after turning ``plane``'s normal towards
        ``truth``'s (its ``d`` changes sign with it), in the planes' units.
    """
    n, d = plane.normal, plane.d
    if n @ truth.normal < 0:
        n, d = -n, -d
    angle = float(np.degrees(np.arccos(np.clip(n @ truth.normal, -1, 1))))
    return angle, float(d - truth.d)
