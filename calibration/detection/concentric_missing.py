"""Rings the coarse stage missed, named and measured from the pencil of two measured ones.

Part of step 5 of :mod:`calibration.detection.concentric`. The fine stage measures the rings
the coarse stage's rays found; where it measures only two (a small target whose innermost
ring is lost under a laser stripe over O, the outermost one too faint for the rays), the
view needs a third. Two rings of the spec's concentric circles fix the images of all the
others (:func:`~calibration.detection.conics.pencil_member`), once the two are named: the
coarse labels may be a ring off (the stripe hid ring 0 from every ray, and the rays named
ring 1 as ring 0), so the names are those under which the two rings' conics have the spec's
radius ratio, where exactly one naming does. Every other ring's predicted conic is then
refined like a coarse one (:func:`~calibration.detection.concentric_rings._refine_ring`),
and the fine stage's checks judge the result as any other measurement.

This is the detector's last sweep (:class:`RingRecovery`), so that a view another pass
measures never depends on it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calibration.detection.concentric_rings import _ellipse_ok, _pair_agrees
from calibration.detection.conics import pencil_member

__all__ = ["RingRecovery", "recovered_rings"]

#: A measured ring: its centre-line points ``(M, 2)`` px, its conic ``(3, 3)``, ``[rms]``.
_Ring = tuple[NDArray, NDArray, NDArray]


@dataclass
class RingRecovery:
    """Whether the fine stage names and measures missing rings (:func:`recovered_rings`),
    and whether a measurement without it stopped where it would have."""

    enabled: bool = False
    """Recover missing rings: the detector's last sweep."""
    wanted: bool = False
    """Set by the fine stage where, with ``enabled`` off, it stopped with two rings measured
    and fewer than it needs: the last sweep measures that scale and pass again."""


def _namings(rings: dict[int, _Ring], radii: NDArray) -> list[int]:
    """The shifts ``s`` of the rings' labels (``k -> k + s``, every label a ring of the spec)
    under which every pair of the rings' conics has the spec's radius ratio."""
    keys = sorted(rings)
    shifts = []
    for shift in range(-keys[0], len(radii) - keys[-1]):
        conics = {k + shift: rings[k][1] for k in keys}
        named = sorted(conics)
        if all(
            _pair_agrees(conics, radii, i, j) for a, i in enumerate(named) for j in named[a + 1 :]
        ):
            shifts.append(shift)
    return shifts


def recovered_rings(
    rings: dict[int, _Ring],
    radii: NDArray,
    c: NDArray,
    refine: Callable[[NDArray], _Ring | None],
) -> dict[int, _Ring]:
    """The measured rings, named by their radius ratios, and the missing rings they predict.

    Parameters
    ----------
    rings : dict of int to tuple
        At least two measured rings by their coarse labels (points ``(M, 2)`` px, conic
        ``(3, 3)``, ``[rms]``), as :func:`~calibration.detection.concentric_rings._refine_ring`
        gives them.
    radii : ndarray, shape (K,)
        The spec's ring radii, mm.
    c : ndarray, shape (2,)
        The pencil's centre, px: a predicted conic must be an ellipse around it.
    refine : callable
        The fine stage's refinement of one ring from a conic ``(3, 3)``
        (:func:`~calibration.detection.concentric_rings._refine_ring` with the fine stage's
        windows, rays and image), None where it finds no ring.

    Returns
    -------
    dict of int to tuple
        The measured rings under the one naming that agrees with the spec's radius ratios
        and every other ring whose predicted conic could be refined; ``rings`` unchanged
        where no naming, or more than one, agrees.
    """
    if len(rings) < 2:
        raise ValueError(f"rings: expected at least 2 measured rings, got {len(rings)}")
    shifts = _namings(rings, radii)
    if len(shifts) != 1:
        return rings
    named = {k + shifts[0]: ring for k, ring in rings.items()}
    i, j = sorted(named)[:2]
    out = dict(named)
    for k in range(len(radii)):
        if k in named:
            continue
        try:
            predicted = pencil_member(named[i][1], radii[i], named[j][1], radii[j], radii[k])
        except np.linalg.LinAlgError:
            continue
        if not np.all(np.isfinite(predicted)) or not _ellipse_ok(predicted, c):
            continue
        res = refine(predicted)
        if res is not None:
            out[k] = res
    return out
