"""The paper's closed-form intrinsics (Section III.A): K from the diameters' vanishing points.

The vanishing points p, q of the two diameters come from the harmonic conjugate of O with
respect to the diameter ends; equation (4) per image, differences (5) stacked into
``H phi = g`` (6) over n >= 4 images, least squares, then alpha, beta from (4). Zero skew,
no distortion. Two variants: the diameter ends of the largest ring only (the paper), and
every ring (a 1-D projective fit along each diameter line).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from calibration.detection.conics import fit_line
from calibration.detection.observations import TargetObservation

__all__ = ["MIN_VIEWS", "PaperEstimate", "paper_intrinsics", "view_vanishing_points"]

#: Fewest views for the intrinsics, by either method.
MIN_VIEWS = 4


@dataclass
class PaperEstimate:
    """One variant of the paper's closed-form intrinsics (zero skew, no distortion).

    ``ok`` False with ``reason`` when the linear system is degenerate or gives a negative
    alpha^2 / beta^2.
    """

    variant: str
    ok: bool
    reason: str = ""
    K: NDArray = field(default_factory=lambda: np.eye(3))
    vanishing_points: list[tuple[NDArray, NDArray]] = field(default_factory=list)

    def __bool__(self) -> bool:
        return bool(self.ok)


def _to_xy(p: NDArray) -> NDArray:
    return np.asarray(p[:2], dtype=np.float64) / p[2]


def paper_intrinsics(
    vanishing_points: list[tuple[NDArray, NDArray]], variant: str = "diameter_ends"
) -> PaperEstimate:
    """Equations (4)-(6): K from the vanishing points (p, q) of n >= 4 views.

    Differences of consecutive views' equation (4) give ``H phi = g`` with
    ``phi = (u0, v0 alpha^2 / beta^2, alpha^2 / beta^2)``; then ``v0 = phi[1] / phi[2]`` (the
    paper prints ``y'/x'``, a typo: ``y' = v0 z'``) and ``alpha^2`` from (4) averaged over the
    views, ``beta^2 = alpha^2 / z'``.
    """
    vps = [(np.asarray(p, float), np.asarray(q, float)) for p, q in vanishing_points]
    finite = [
        (p, q)
        for p, q in vps
        if abs(p[2]) > 1e-12 * np.linalg.norm(p) and abs(q[2]) > 1e-12 * np.linalg.norm(q)
    ]
    if len(finite) < MIN_VIEWS:
        return PaperEstimate(
            variant,
            False,
            f"expected >= {MIN_VIEWS} views with finite vanishing points, got {len(finite)}",
            vanishing_points=vps,
        )
    pq = np.array([np.r_[_to_xy(p), _to_xy(q)] for p, q in finite])  # up, vp, uq, vq
    su = pq[:, 0] + pq[:, 2]
    sv = pq[:, 1] + pq[:, 3]
    pu = pq[:, 0] * pq[:, 2]
    pv = pq[:, 1] * pq[:, 3]
    H = np.column_stack([-np.diff(su), -np.diff(sv), np.diff(pv)])
    g = -np.diff(pu)
    if np.linalg.matrix_rank(H, tol=1e-9 * max(np.abs(H).max(), 1.0)) < 3:
        return PaperEstimate(
            variant, False, "H is rank deficient: views too alike", vanishing_points=vps
        )
    phi, *_ = np.linalg.lstsq(H, g, rcond=None)
    u0, yp, zp = (float(v) for v in phi)
    if zp <= 0:
        return PaperEstimate(
            variant,
            False,
            f"alpha^2/beta^2 = {zp:.3g} <= 0: inconsistent views",
            vanishing_points=vps,
        )
    v0 = yp / zp
    a2 = -np.mean((u0 - pq[:, 0]) * (u0 - pq[:, 2]) + zp * (v0 - pq[:, 1]) * (v0 - pq[:, 3]))
    if a2 <= 0:
        return PaperEstimate(
            variant, False, f"alpha^2 = {a2:.3g} <= 0: inconsistent views", vanishing_points=vps
        )
    alpha = float(np.sqrt(a2))
    beta = float(np.sqrt(a2 / zp))
    K = np.array([[alpha, 0.0, u0], [0.0, beta, v0], [0.0, 0.0, 1.0]])
    return PaperEstimate(variant, True, "", K, vps)


def _axis_vanishing_point(obs: TargetObservation, axis: str) -> NDArray | None:
    """Vanishing point of one diameter from every ring's ends: 1-D projective fit ``s -> t``."""
    col = 0 if axis == "x" else 1
    other = 1 - col
    sel = np.abs(obs.points_target[:, other]) < 1e-9
    s = obs.points_target[sel, col]
    pts = obs.points_px[sel]
    if len(s) < 4 or obs.center_px is None:
        return None
    o = np.asarray(obs.center_px, float)
    line = fit_line(pts)
    d = np.array([-line[1], line[0]])
    far = pts[np.argmax(s)]
    if float((far - o) @ d) < 0:
        d = -d
    t = (pts - o) @ d
    # t (c s + 1) = a s + b
    A = np.column_stack([s, np.ones_like(s), -s * t])
    (a, _, c), *_ = np.linalg.lstsq(A, t, rcond=None)
    # s -> infinity: t -> a / c, the point o + (a / c) d, homogeneous
    return np.array([c * o[0] + a * d[0], c * o[1] + a * d[1], c])


def view_vanishing_points(obs: TargetObservation) -> tuple[NDArray, NDArray, str] | None:
    """The vanishing points (p, q) of one view's diameters x and y, and which rings gave them.

    The paper's are the harmonic conjugates of O with respect to the largest ring's diameter
    ends A, B and C, D (:attr:`TargetObservation.vanishing_points`). Where one of those ends
    lies outside the image or is not found, every ring's ends found along each diameter give
    them (:func:`_axis_vanishing_point`): a 1-D projective fit of their image positions to
    their radii in the spec (so it relies on the rings' labels, as the rest of the
    calibration does), the harmonic property of A, O, B generalised to every ring.

    Parameters
    ----------
    obs : TargetObservation
        A concentric-circles observation.

    Returns
    -------
    tuple of (ndarray, shape (3,); ndarray, shape (3,); str) or None
        p, q (homogeneous pixels) and ``"diameter_ends"`` or ``"all_rings"``; None where
        neither way applies (fewer than four points on a diameter).
    """
    vp = obs.vanishing_points
    if "p" in vp and "q" in vp:
        return np.asarray(vp["p"], float), np.asarray(vp["q"], float), "diameter_ends"
    p, q = _axis_vanishing_point(obs, "x"), _axis_vanishing_point(obs, "y")
    if p is None or q is None:
        return None
    return p, q, "all_rings"


def _paper_variants(obs_list: list[TargetObservation]) -> dict[str, PaperEstimate]:
    ends, rings = [], []
    for ob in obs_list:
        vp = ob.vanishing_points
        if "p" in vp and "q" in vp:
            ends.append((vp["p"], vp["q"]))
        px, qy = _axis_vanishing_point(ob, "x"), _axis_vanishing_point(ob, "y")
        if px is not None and qy is not None:
            rings.append((px, qy))
    return {
        "diameter_ends": paper_intrinsics(ends, "diameter_ends"),
        "all_rings": paper_intrinsics(rings, "all_rings"),
    }
