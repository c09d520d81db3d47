"""The laser fan's apex (``laser_origin_cam``) from the shadows in the calibration's laser frames.

A line projector sends its fan from one point, the origin, lying on the light plane. Where the
fan grazes an edge (the card's edge when the target is held in front of the table, or a
raised target's edge) the surface behind lies in the edge's shadow, and the lit stripe starts
again where the fan's ray past the edge meets it. Both ends are on the light plane and so
triangulate without knowing either surface: the near stripe's end ``P1`` (on the edge) and the
far stripe's start ``P2`` (the shadow's edge) lie on one ray from the origin. Every such pair is
a line in the light plane through the origin; two lines from different views cross at it, many
lines give it with an uncertainty.

Not every gap is a shadow. Where the edge hides the far surface from the camera (the camera's
view, not the laser's, ends the far stripe), ``P1 -> P2`` misses the origin by millimetres to
centimetres; such lines are left out by consensus: the origin is taken where the most lines
meet within their own uncertainty, every pair's crossing being a hypothesis.

Each end's uncertainty is the footprint of half a pixel at its depth (the stripe's end is found
to a scan line), perpendicular to the line; a line's uncertainty at the origin follows from its
two ends by extrapolation. The origin's covariance is the weighted least-squares one, scaled by
the fit's reduced chi-square when that exceeds one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations, pairwise

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from scanner.core.camera import CameraModel, intersect_rays_with_plane
from scanner.core.outcome import Outcome
from scanner.formats.calibration_file import LightPlane

__all__ = ["LaserOriginResult", "ShadowLine", "estimate_laser_origin", "shadow_lines"]

LINK_PX = 4.0
"""Stripe points closer than this in the image belong to one stretch of stripe."""
MIN_STRETCH_POINTS = 15
"""A stretch of stripe shorter than this (print edges, speckle) is not used."""
END_POINTS = 10
"""The points at a stretch's end whose line refines the end point."""
JUMP_STEPS = 20
"""A gap between stretches counts as a depth jump above this many of their point spacings."""
CLEAR_PX = 8.0
"""A stretch's end is a real end when no stripe peak continues it this far beyond it."""
BORDER_PX = 3.0
"""A stretch ending this close to the image border leaves the image: no edge there."""
END_SIGMA_PX = 0.5
"""One-sigma uncertainty of a stretch's end along the stripe, pixels."""
INLIER_SIGMAS = 3.0
MAX_ORIGIN_MM = 1000.0
"""A laser origin farther from the camera than this is not a line scanner's."""
MIN_LINES = 3
END_BIAS_PRIOR_PX = 1.0
"""One-sigma prior of the ends' common bias along the stripe, pixels."""
NEAR_FAR_BIAS_PX = 0.5
"""One-sigma difference between the near and the far ends' bias along the stripe, pixels."""


@dataclass(frozen=True)
class ShadowLine:
    """Two triangulated ends across a depth jump of one laser frame's stripe.

    Attributes
    ----------
    frame_id : int
    near_cam, far_cam : ndarray, shape (3,)
        The end nearer to the camera and the one farther, camera frame, mm, on the light plane.
    near_sigma_mm, far_sigma_mm : float
        One-sigma uncertainty of each end across the line, mm.
    near_step_cam, far_step_cam : ndarray, shape (3,)
        One pixel outwards along each stretch at its end, mm: where a pixel's worth of bias in
        locating the ends (blur, partly lit pixels) moves them.
    """

    frame_id: int
    near_cam: NDArray
    far_cam: NDArray
    near_sigma_mm: float
    far_sigma_mm: float
    near_step_cam: NDArray
    far_step_cam: NDArray


@dataclass
class LaserOriginResult(Outcome):
    """The laser origin estimated from shadow lines, or a failed estimate (falsy) with ``reason``.

    Attributes
    ----------
    origin_cam : ndarray, shape (3,)
        The fan's apex, camera frame, mm, on the light plane.
    covariance_mm2 : ndarray, shape (3, 3)
        Its covariance (rank 2: within the light plane).
    std_mm : float
        One-sigma uncertainty of the position within the plane (the larger principal axis).
    lines, inliers : int
        Candidate lines found and those that meet at the origin.
    frames : list of int
        Laser frames giving an inlier line.
    chi2_reduced : float
        The inliers' weighted residuals' mean square (1 when the stated end uncertainty fits).
    end_bias_px, end_bias_std_px : float
        How far outwards the stripe's ends were found, estimated with the origin, pixels.
    near_cam, far_cam : ndarray, shape (L, 3)
        Every candidate line's ends, camera frame, mm (for the report's figure).
    inlier : ndarray of bool, shape (L,)
        The lines that meet at the origin.
    """

    origin_cam: NDArray = field(default_factory=lambda: np.full(3, np.nan))
    covariance_mm2: NDArray = field(default_factory=lambda: np.full((3, 3), np.nan))
    std_mm: float = float("nan")
    lines: int = 0
    inliers: int = 0
    frames: list[int] = field(default_factory=list)
    chi2_reduced: float = float("nan")
    end_bias_px: float = float("nan")
    end_bias_std_px: float = float("nan")
    near_cam: NDArray = field(default_factory=lambda: np.zeros((0, 3)))
    far_cam: NDArray = field(default_factory=lambda: np.zeros((0, 3)))
    inlier: NDArray = field(default_factory=lambda: np.zeros(0, bool))

    def quality(self) -> dict[str, object]:
        """The record the calibration file's ``quality.laser_origin`` carries."""
        if not self:
            return {"method": "shadow edges", "estimated": False, "reason": self.reason}
        return {
            "method": "shadow edges",
            "estimated": True,
            "origin_cam_mm": self.origin_cam.tolist(),
            "covariance_mm2": self.covariance_mm2.tolist(),
            "std_mm": self.std_mm,
            "lines": self.lines,
            "inliers": self.inliers,
            "frames": self.frames,
            "chi2_reduced": self.chi2_reduced,
            "end_bias_px": self.end_bias_px,
            "end_bias_std_px": self.end_bias_std_px,
        }


def _stretches(uv: NDArray) -> list[NDArray]:
    """Index arrays of the connected stretches of stripe, each ordered along the stripe."""
    pairs = cKDTree(uv).query_pairs(LINK_PX, output_type="ndarray")
    n = len(uv)
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    centred = uv - uv.mean(axis=0)
    along = centred @ np.linalg.svd(centred, full_matrices=False)[2][0]
    out = []
    for c in np.unique(label):
        idx = np.flatnonzero(label == c)
        if len(idx) >= MIN_STRETCH_POINTS:
            out.append(idx[np.argsort(along[idx])])
    out.sort(key=lambda idx: float(along[idx[0]]))
    return out


def _half_point_px(uv: NDArray, contrast: NDArray) -> float:
    """Where the stripe's contrast falls to half its plateau at the end of a stretch, pixels
    along it from its last point (negative: inside).

    ``uv`` (N, 2) and ``contrast`` (N,) are ordered towards the end. The plateau is the median
    contrast a little inside the end; past the last point the contrast is taken to fall to
    nothing at the next scan line. A stripe blurred over its end is seen a few pixels beyond it
    down to the detection threshold; its half point is where the edge is (for a symmetric blur
    of an unsaturated stripe).
    """
    inner = contrast[-4 * END_POINTS : -END_POINTS]
    if len(inner) < 3:
        return 0.0
    half = 0.5 * float(np.median(inner))
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))])
    s -= s[-1]
    tail_c, tail_s = contrast[-END_POINTS:], s[-END_POINTS:]
    above = np.flatnonzero(tail_c >= half)
    if len(above) == 0:
        return 0.0
    j = int(above[-1])
    if j == len(tail_c) - 1:
        spacing = float(tail_s[-1] - tail_s[-2])
        return spacing * (1.0 - half / max(float(tail_c[-1]), 1e-9))
    f = (tail_c[j] - half) / max(float(tail_c[j] - tail_c[j + 1]), 1e-9)
    return float(tail_s[j] + f * (tail_s[j + 1] - tail_s[j]))


def _end(points: NDArray, uv: NDArray, contrast: NDArray | None) -> tuple[NDArray, NDArray]:
    """The end of a stretch of ``points`` (N, 3) ordered towards it: the last point moved onto
    the local line and to the contrast's half point (:func:`_half_point_px`, when ``contrast``
    is given); and one pixel's step outwards along the line, mm (from the pixels ``uv``)."""
    tail = points[-END_POINTS:]
    c = tail.mean(axis=0)
    axis = np.linalg.svd(tail - c, full_matrices=False)[2][0]
    if axis @ (tail[-1] - tail[0]) < 0:
        axis = -axis
    px = float(np.linalg.norm(uv[-1] - uv[-len(tail)]))
    mm = float(np.linalg.norm(tail[-1] - tail[0]))
    step = axis * (mm / max(px, 1e-9))
    end = c + ((points[-1] - c) @ axis) * axis
    if contrast is not None:
        end = end + _half_point_px(uv, contrast) * step
    return end, step


def _continued(uv: NDArray, stretch_uv: NDArray) -> bool:
    """Whether a stripe peak lies just beyond the end of ``stretch_uv`` (ordered towards its
    end), on its line and within :data:`CLEAR_PX`."""
    tail = stretch_uv[-END_POINTS:]
    d = tail[-1] - tail[0]
    d /= max(float(np.linalg.norm(d)), 1e-9)
    w = uv - stretch_uv[-1]
    along = w @ d
    across = np.abs(w[:, 0] * d[1] - w[:, 1] * d[0])
    return bool(np.any((along > 1.5) & (along <= CLEAR_PX) & (across <= 2.0)))


def shadow_lines(
    uv_px: NDArray,
    camera: CameraModel,
    plane: LightPlane,
    frame_id: int = 0,
    contrast: NDArray | None = None,
) -> list[ShadowLine]:
    """The candidate shadow lines of one laser frame: the ends on either side of each depth jump.

    Parameters
    ----------
    uv_px : ndarray, shape (N, 2)
        Every stripe peak of the frame, distorted pixels.
    camera : CameraModel
    plane : LightPlane
        The calibrated light plane, camera frame.
    frame_id : int
    contrast : ndarray, shape (N,), optional
        Each peak's height above the background (grey levels): an end is then placed where
        the stripe's contrast falls to half, not at the last peak found (which a blurred
        bright stripe puts a pixel or two beyond the edge).

    Returns
    -------
    list of ShadowLine
        One per pair of neighbouring stretches whose ends are apart in depth by far more than
        their points' spacing; empty when the stripe has no such jump.
    """
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    if len(uv) < 2 * MIN_STRETCH_POINTS:
        return []
    pts = intersect_rays_with_plane(camera.rays(uv), plane.normal, plane.d)
    good = np.all(np.isfinite(pts), axis=1)
    uv, pts = uv[good], pts[good]
    con = None if contrast is None else np.asarray(contrast, dtype=np.float64)[good]
    if len(uv) < 2 * MIN_STRETCH_POINTS:
        return []
    focal = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
    stretches = _stretches(uv)
    out = []
    for a, b in pairwise(stretches):
        pa, pb = pts[a], pts[b]
        spacing = max(
            float(np.median(np.linalg.norm(np.diff(pa, axis=0), axis=1))),
            float(np.median(np.linalg.norm(np.diff(pb, axis=0), axis=1))),
        )
        end_a, step_a = _end(pa, uv[a], None if con is None else con[a])
        start_b, step_b = _end(pb[::-1], uv[b][::-1], None if con is None else con[b][::-1])
        if np.linalg.norm(start_b - end_a) < JUMP_STEPS * spacing:
            continue
        if not np.all(camera.in_image(uv[[a[-1], b[0]]], BORDER_PX)):
            continue  # a stretch leaving the image ends there, not at an edge
        if _continued(uv, uv[a]) or _continued(uv, uv[b][::-1]):
            continue  # a broken stretch (speckle, a dim stripe) goes on after a gap
        (near, near_step), (far, far_step) = sorted(
            [(end_a, step_a), (start_b, step_b)], key=lambda e: float(e[0][2])
        )
        out.append(
            ShadowLine(
                frame_id,
                near,
                far,
                float(np.linalg.norm(near)) / focal * END_SIGMA_PX,
                float(np.linalg.norm(far)) / focal * END_SIGMA_PX,
                near_step,
                far_step,
            )
        )
    return out


def _residuals(origin: NDArray, a: NDArray, b: NDArray, sa: NDArray, sb: NDArray) -> NDArray:
    """Signed distances of ``origin`` (2,) from the lines ``a -> b`` (L, 2), in their sigmas;
    infinite where the origin lies between the two ends (no ray from it passes both)."""
    ab = b - a
    length = np.linalg.norm(ab, axis=1)
    u = ab / length[:, None]
    w = origin - a
    t = np.einsum("ij,ij->i", w, u)
    across = u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]
    # Perpendicular error at the origin of a line through two uncertain ends.
    s2 = (sa * (t - length) / length) ** 2 + (sb * t / length) ** 2
    r = across / np.sqrt(s2)
    return np.where((t > 0) & (t < length), np.inf, r)


@dataclass(frozen=True)
class _Lines:
    """Shadow lines in the light plane's 2-D coordinates."""

    a: NDArray  # (L, 2) near ends
    b: NDArray  # (L, 2) far ends
    da: NDArray  # (L, 2) one pixel outwards at the near end
    db: NDArray  # (L, 2)
    sa: NDArray  # (L,) sigmas of the ends
    sb: NDArray
    frame: NDArray  # (L,) frame ids

    def residuals(
        self, x: NDArray, keep: NDArray | None = None, near_extra_px: float = 0.0
    ) -> NDArray:
        """Residuals (in sigmas) at ``x = (o1, o2, bias_px)``: the ends moved by the bias (the
        near ends by ``near_extra_px`` more)."""
        k = slice(None) if keep is None else keep
        a = self.a[k] + (x[2] + near_extra_px) * self.da[k]
        b = self.b[k] + x[2] * self.db[k]
        r = _residuals(x[:2], a, b, self.sa[k], self.sb[k])
        # A priori the bias is within a pixel or so (keeps it bounded where lines cannot tell).
        return np.append(r, x[2] / END_BIAS_PRIOR_PX) if keep is not None else r


def estimate_laser_origin(lines: list[ShadowLine], plane: LightPlane) -> LaserOriginResult:
    """Where the most shadow lines meet: the laser origin on the light plane, with covariance.

    The ends' common bias along the stripe (a blurred or partly lit end pixel still shows a
    peak) is estimated with the origin: one number in pixels for every end.

    Parameters
    ----------
    lines : list of ShadowLine
        Candidate lines of every laser frame (:func:`shadow_lines`).
    plane : LightPlane

    Returns
    -------
    LaserOriginResult
        Falsy with the reason when fewer than three lines from two frames meet, or they leave
        the origin undetermined.
    """
    n = np.asarray(plane.normal, dtype=np.float64)
    p0 = -plane.d * n
    e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    basis = np.column_stack([e1, np.cross(n, e1)])  # (3, 2)
    if len(lines) < MIN_LINES:
        return LaserOriginResult(
            False,
            f"expected shadow edges in the laser frames (a target held before the background, "
            f"or raised off it) giving at least {MIN_LINES} lines, got {len(lines)}",
            lines=len(lines),
        )
    ls = _Lines(
        np.array([(ln.near_cam - p0) @ basis for ln in lines]),
        np.array([(ln.far_cam - p0) @ basis for ln in lines]),
        np.array([ln.near_step_cam @ basis for ln in lines]),
        np.array([ln.far_step_cam @ basis for ln in lines]),
        np.array([ln.near_sigma_mm for ln in lines]),
        np.array([ln.far_sigma_mm for ln in lines]),
        np.array([ln.frame_id for ln in lines]),
    )
    a, b = ls.a, ls.b
    u = (b - a) / np.linalg.norm(b - a, axis=1)[:, None]

    # Consensus: every crossing of two lines from different frames is a hypothesis.
    best: tuple[int, float, NDArray] | None = None
    for i, j in combinations(range(len(lines)), 2):
        cross = u[i, 0] * u[j, 1] - u[i, 1] * u[j, 0]
        if abs(cross) < np.sin(np.radians(2.0)) or ls.frame[i] == ls.frame[j]:
            continue
        s = ((a[j, 0] - a[i, 0]) * u[j, 1] - (a[j, 1] - a[i, 1]) * u[j, 0]) / cross
        x = np.array([*(a[i] + s * u[i]), 0.0])
        if np.linalg.norm(x[:2] @ basis.T + p0) > MAX_ORIGIN_MM:
            continue
        r = np.abs(ls.residuals(x))
        inl = r < INLIER_SIGMAS
        score = (int(inl.sum()), -float(np.sum(r[inl] ** 2)))
        if best is None or score > best[:2]:
            best = (score[0], score[1], x)
    if best is None or best[0] < MIN_LINES:
        return LaserOriginResult(
            False,
            f"shadow lines: expected at least {MIN_LINES} from two frames meeting in one point, "
            f"got {0 if best is None else best[0]} of {len(lines)}",
            lines=len(lines),
        )
    x = best[2]
    inl = np.abs(ls.residuals(x)) < INLIER_SIGMAS
    for _ in range(5):
        # The covariance below needs the fit of exactly the lines it keeps.
        used = inl
        fit = least_squares(lambda p, m=used: ls.residuals(p, m), x, method="lm")
        x = fit.x
        inl = np.abs(ls.residuals(x)) < INLIER_SIGMAS
        if np.array_equal(inl, used):
            break
    inl = used
    res = fit.fun
    dof = max(1, int(inl.sum()) - 2)  # the bias's prior is one more residual
    chi2 = float(np.sum(res**2) / dof)
    try:
        cov = np.linalg.inv(fit.jac.T @ fit.jac) * max(1.0, chi2)
    except np.linalg.LinAlgError:
        return LaserOriginResult(False, "shadow lines: all parallel", lines=len(lines))
    # The ends' errors are not independent within a frame (one exposure, one pose): the
    # spread of the leave-one-frame-out estimates is taken when it is the larger.
    frames = sorted(set(ls.frame[inl].tolist()))
    if len(frames) >= 3:
        drops = []
        for fid in frames:
            keep = inl & (ls.frame != fid)
            drops.append(least_squares(lambda p, m=keep: ls.residuals(p, m), x, method="lm").x)
        dx = np.array(drops) - np.mean(drops, axis=0)
        jack = (len(frames) - 1) / len(frames) * dx.T @ dx
        if np.trace(jack[:2, :2]) > np.trace(cov[:2, :2]):
            cov = jack
    cov2 = cov[:2, :2]
    # The near and far ends need not share one bias (a saturated stripe's end spreads further
    # than a faint one's): what a difference of NEAR_FAR_BIAS_PX would move the origin by is
    # added as a type-B term.
    moved = least_squares(lambda p: ls.residuals(p, inl, NEAR_FAR_BIAS_PX), x, method="lm").x
    cov2 = cov2 + np.outer(moved[:2] - x[:2], moved[:2] - x[:2])
    std = float(np.sqrt(np.linalg.eigvalsh(cov2)[-1]))
    if len(frames) < 2 or not np.isfinite(std):
        return LaserOriginResult(
            False, "shadow lines: the meeting lines come from one frame", lines=len(lines)
        )
    return LaserOriginResult(
        True,
        origin_cam=x[:2] @ basis.T + p0,
        covariance_mm2=basis @ cov2 @ basis.T,
        std_mm=std,
        lines=len(lines),
        inliers=int(inl.sum()),
        frames=frames,
        chi2_reduced=chi2,
        end_bias_px=float(x[2]),
        end_bias_std_px=float(np.sqrt(cov[2, 2])),
        near_cam=np.array([ln.near_cam for ln in lines]),
        far_cam=np.array([ln.far_cam for ln in lines]),
        inlier=inl,
    )
