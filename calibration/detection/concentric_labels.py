"""Concentric-circles detector, naming the points: local crossings and the orientation marker.

Step 6 of :mod:`calibration.detection.concentric`: which diameter end is A, decided by the
orientation disc (:func:`_label_by_marker`); and the crossings of rings with the diameter
lines, refined by local quadratic fits where lens distortion bends the curves
(:func:`_local_crossing`), named by ring and axis (:func:`_named_points`).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.detection.concentric_rays import _sample
from calibration.detection.concentric_rings import (
    _conic_normals,
    _pencil_offsets,
    _pencil_predictions,
    _unit_line,
    pencil_tolerance_px,
)
from calibration.detection.conics import line_conic_intersections, sampson_distances
from scanner.core.targets import ConcentricCirclesTarget


def _axis_dir(ln: NDArray, sign: float) -> NDArray:
    return sign * np.array([-ln[1], ln[0]]) / np.linalg.norm(ln[:2])


def _locally_biased(resid: NDArray, pts: NDArray, near: NDArray, reach: float) -> bool:
    """Whether a global fit's residuals near ``near`` are significantly off zero (the curve is
    bent there, e.g. by lens distortion), so a local fit is worth its extra noise."""
    sel = np.linalg.norm(pts - near, axis=1) < reach
    if sel.sum() < 6:
        return False
    r = resid[sel]
    sem = float(np.std(r)) / np.sqrt(sel.sum())
    # Neighbouring edge points are correlated (blur): a generous threshold.
    return abs(float(np.mean(r))) > max(5.0 * sem, 0.03)


def _local_quadratic(
    pts: NDArray, line: NDArray, near: NDArray, reach: float, two_sided: bool = True
):
    """Fit ``across = c0 + c1 along + c2 along^2`` to the points within ``reach`` of ``near``
    in the frame of ``line``; returns (origin, along dir, across dir, coefficients) or None."""
    ln = _unit_line(line)
    n = ln[:2]
    e = np.array([-n[1], n[0]])
    sel = np.linalg.norm(pts - near, axis=1) < reach
    if sel.sum() < 6:
        return None
    d = pts[sel] - near
    a, b = d @ e, d @ n
    if np.ptp(a) < 0.5 * reach:
        return None
    if two_sided and (a.min() > -0.2 * reach or a.max() < 0.2 * reach):
        return None  # a ring needs points on both sides of the crossing
    A = np.column_stack([np.ones_like(a), a, a * a])
    coef, *_ = np.linalg.lstsq(A, b, rcond=None)
    return near, e, n, coef


def _local_crossing(
    pts1: NDArray, line1: NDArray, pts2: NDArray, line2: NDArray, near: NDArray, reach: float
) -> NDArray | None:
    """Crossing of two measured curves near ``near`` from local quadratic fits."""
    f1 = _local_quadratic(pts1, line1, near, reach)
    f2 = _local_quadratic(pts2, line2, near, reach, two_sided=False)
    if f1 is None or f2 is None:
        return None
    o1, e1, n1, c1 = f1
    o2, e2, n2, c2 = f2

    def point1(a: float) -> NDArray:
        return o1 + a * e1 + (c1[0] + c1[1] * a + c1[2] * a * a) * n1

    def gap(a: float) -> float:
        p = point1(a)
        s2 = float((p - o2) @ e2)
        return float((p - o2) @ n2) - (c2[0] + c2[1] * s2 + c2[2] * s2 * s2)

    # Newton on the position along curve 1 (any crossing angle, unlike alternating projections).
    a = float((near - o1) @ e1)
    for _ in range(30):
        f = gap(a)
        df = (gap(a + 1e-3) - f) / 1e-3
        if abs(df) < 1e-9:
            return None
        step = f / df
        a -= step
        if abs(step) < 1e-7:
            break
    if abs(gap(a)) > 1e-4:
        return None
    return point1(a)


def _combine_centre(
    o_lines: NDArray, o_pencil: NDArray, conics: dict[int, NDArray], axis_lines: list[NDArray]
) -> NDArray:
    """The image of O: the pencil's centre and the lines' crossing are both exact without
    lens distortion; their mean halves the noise of either."""
    return 0.5 * (o_lines + o_pencil)


def _label_by_marker(
    img: NDArray,
    bg: NDArray,
    target: ConcentricCirclesTarget,
    center: NDArray,
    ends: list[NDArray],
    conics: dict[int, NDArray],
    radii: NDArray,
    axis_lines: list[NDArray],
    line_darkness: float | None = None,
    paper_level: float | None = None,
) -> tuple[int, float, float, NDArray] | str:
    """Decide which end is A by the orientation disc; C follows (z out of the face).

    ``line_darkness`` (``1 - I / paper`` on the printed rings' centre lines, from this
    image) scales what counts as dark: a disc of solid ink is at least as dark as a line,
    whatever the print's contrast. ``paper_level`` (the background on the rings): a
    candidate place whose surroundings are far darker is off the card.

    Returns (index of the x line in ``axis_lines``, sign of +x along the x line's direction,
    same for y, marker px) or a reason string.
    """
    h, w = img.shape
    r_big = radii[max(conics)]
    e = _ends_in_image_order(center, ends)
    m = target.orientation_marker
    mr = m.diameter_mm / 2
    scores = []
    candidates = []
    for i in range(4):
        a, b, cc, dd = e[i], e[(i + 2) % 4], e[(i - 1) % 4], e[(i + 1) % 4]
        src = np.array([[0, 0], [r_big, 0], [-r_big, 0], [0, r_big], [0, -r_big]], np.float64)
        dst = np.array([center, a, b, cc, dd], np.float64)
        H, _ = cv2.findHomography(src, dst, 0)
        if H is None:
            scores.append(np.nan)
            candidates.append(None)
            continue
        mc = _apply_h(H, np.array([m.center_mm]))[0]
        ring_pts = np.array(
            [
                [m.center_mm[0] + 0.5 * mr * np.cos(t), m.center_mm[1] + 0.5 * mr * np.sin(t)]
                for t in np.linspace(0, 2 * np.pi, 8, endpoint=False)
            ]
            + [list(m.center_mm)]
        )
        inner = _apply_h(H, ring_pts)
        outer_pts = np.array(
            [
                [m.center_mm[0] + 1.6 * mr * np.cos(t), m.center_mm[1] + 1.6 * mr * np.sin(t)]
                for t in np.linspace(0, 2 * np.pi, 12, endpoint=False)
            ]
        )
        outer = _apply_h(H, outer_pts)
        allp = np.vstack([inner, outer])
        if not (
            np.all(allp[:, 0] >= 0)
            and np.all(allp[:, 0] <= w - 1)
            and np.all(allp[:, 1] >= 0)
            and np.all(allp[:, 1] <= h - 1)
        ):
            scores.append(np.nan)
            candidates.append((a, cc, mc))
            continue
        vin = _sample(img, inner[:, 0], inner[:, 1])
        bgv = _sample(bg, inner[:, 0], inner[:, 1])
        vout = _sample(img, outer[:, 0], outer[:, 1])
        if paper_level is not None and float(np.median(vout)) < 0.5 * paper_level:
            # Not on the card's paper (dark surroundings): no marker can be printed there.
            scores.append(np.nan)
            candidates.append((a, cc, mc))
            continue
        ref = max(float(np.median(vout)), float(np.median(bgv)) * 0.5, 1e-6)
        # Every point inside the disc must be dark (the brightest decides), around it paper.
        # (the second brightest: one noisy sample does not decide)
        scores.append(1.0 - float(np.sort(vin)[-2]) / ref)
        candidates.append((a, cc, mc))
    sc = np.asarray(scores, dtype=np.float64)
    if np.all(np.isnan(sc)):
        return "orientation marker not visible (outside the image for every labelling)"
    best = int(np.nanargmax(sc))
    others = np.delete(sc, best)
    dark = 1.0 if line_darkness is None else float(np.clip(line_darkness, 0.0, 1.0))
    if sc[best] < min(0.3, 0.5 * dark):
        return f"orientation marker not visible (darkest candidate contrast {sc[best]:.2f})"
    if np.any(np.isnan(others)) and sc[best] < min(0.5, 0.8 * dark):
        return (
            "orientation marker ambiguous: a weak candidate while another candidate position "
            "lies outside the image"
        )
    if np.any(np.isfinite(others)) and np.nanmax(others) > 0.3 * sc[best]:
        return "orientation marker ambiguous: more than one dark disc where the marker may be"
    a, cc, mc = candidates[best]
    return (*_labelling(a, cc, center, ends, axis_lines), mc)


def _ends_in_image_order(center: NDArray, ends: list[NDArray]) -> list[NDArray]:
    """The four ends of the diameters on the largest ring, by increasing image angle around O
    (clockwise on screen, v down). The four labellings of the target are cyclic rotations of
    this list: target x -> y is counter-clockwise on screen seen from the face, so if A is
    ``e[i]``, C is ``e[i - 1]``."""
    e = [ends[0][0], ends[1][0], ends[0][1], ends[1][1]]
    angs = [np.arctan2(p[1] - center[1], p[0] - center[0]) for p in e]
    return [e[i] for i in np.argsort(angs)]


def _labelling(
    a: NDArray, cc: NDArray, center: NDArray, ends: list[NDArray], axis_lines: list[NDArray]
) -> tuple[int, float, float]:
    """(index of the x line in ``axis_lines``, sign of +x along it, sign of +y along the y
    line) for A at ``a`` and C at ``cc``."""
    ix = 0 if min(np.linalg.norm(ends[0] - a, axis=1)) < 1e-6 else 1
    l_x, l_y = _unit_line(axis_lines[ix]), _unit_line(axis_lines[1 - ix])
    sx = 1.0 if float((a - center) @ _axis_dir(l_x, 1.0)) > 0 else -1.0
    sy = 1.0 if float((cc - center) @ _axis_dir(l_y, 1.0)) > 0 else -1.0
    return ix, sx, sy


def label_up_to_symmetry(
    center: NDArray, ends: list[NDArray], axis_lines: list[NDArray]
) -> tuple[int, float, float, None]:
    """A labelling without the marker: right-handed, but one of the target's four rotations
    by 90 deg about its normal (which one is unknown). Intrinsics and the light plane do not
    depend on it; a hand-eye does (:mod:`calibration.symmetry` resolves it from the robot's motion)."""
    e = _ends_in_image_order(center, ends)
    return (*_labelling(e[0], e[-1], center, ends, axis_lines), None)


def _apply_h(H: NDArray, pts: NDArray) -> NDArray:
    x = np.column_stack([pts, np.ones(len(pts))]) @ H.T
    return x[:, :2] / x[:, 2:3]


def _named_points(
    center: NDArray,
    conics: dict[int, NDArray],
    rings: dict[int, tuple[NDArray, NDArray, NDArray]],
    radii: NDArray,
    xy_lines: tuple[NDArray, NDArray],
    xy_signs: tuple[float, float],
    xy_points: tuple[NDArray, NDArray],
    spacing_px: float,
    size: tuple[int, int],
) -> tuple[list[NDArray], list[NDArray], list[str], dict[str, NDArray]]:
    """The target's points named in the image: O and each ring's crossings with the diameters.

    Parameters
    ----------
    center : ndarray, shape (2,)
        The image of O (px).
    conics : dict of int to ndarray, shape (3, 3)
        The measured rings' conics by ring index.
    rings : dict of int to tuple
        Each measured ring's centre-line points ``(N, 2)`` first.
    radii : ndarray, shape (K,)
        The spec's ring radii (mm).
    xy_lines : tuple of two ndarray, shape (3,)
        The x and y diameters' lines (unit normals).
    xy_signs : tuple of two float
        +1 or -1: which way along each line is the target's positive axis.
    xy_points : tuple of two ndarray, shape (M, 2)
        The points measured on each diameter.
    spacing_px : float
        The rings' smallest spacing in the image.
    size : tuple of int
        The image's (width, height).

    Returns
    -------
    points_px, points_target, names, named
        The image points ``(2,)``, their target points ``(3,)`` (mm) and names
        (``"O"``, ``"r{k}+x"``, ...), and the named points O, A, B, C, D that were seen.
    """
    w, h = size
    xline, yline = xy_lines
    sign_x, sign_y = xy_signs
    pts_x, pts_y = xy_points
    kmax = max(conics)
    # Lens distortion bends the lines and rings slightly: every crossing is refined by local
    # quadratic fits of the measured points around it (exact to second order).
    # O itself stays the mean of the pencil's centre and the lines' crossing: both use every
    # ring and line point, which beats a local fit at the noise level.
    named: dict[str, NDArray] = {"O": center}
    points_px = [center]
    points_t = [np.zeros(3)]
    names = ["O"]
    for k in sorted(conics):
        r = radii[k]
        # The other rings' pencil checks every named point (see below).
        predicted = _pencil_predictions(conics, radii, k)
        bias = float(np.median(_pencil_offsets(predicted, rings[k][0]))) if predicted else 0.0
        for axis_name, ln, sgn, axis_idx in (("x", xline, sign_x, 0), ("y", yline, sign_y, 1)):
            pts = line_conic_intersections(ln, conics[k])
            if len(pts) != 2:
                continue
            dirv = _axis_dir(ln, sgn)
            apts = pts_x if axis_name == "x" else pts_y
            for p in pts:
                side = 1.0 if float((p - center) @ dirv) > 0 else -1.0
                if k in rings:
                    ring_pts = rings[k][0]
                    nrm = _conic_normals(conics[k], p[None])[0]
                    ring_line = np.array([nrm[0], nrm[1], -float(nrm @ p)])  # the tangent
                    reach = max(15.0, 0.35 * float(np.linalg.norm(p - center)))
                    # Only where the ring was measured near the crossing: a conic extrapolated
                    # over a part hidden by a stripe or cut by the border may be far off
                    # there, though its ratios agree with the other rings.
                    seen = min(reach, max(15.0, 3.0 * spacing_px))
                    if np.min(np.linalg.norm(ring_pts - p, axis=1)) > seen:
                        continue
                    # ... and where the other rings' pencil puts this ring there too
                    if predicted and abs(
                        float(_pencil_offsets(predicted, p[None])[0]) - bias
                    ) > pencil_tolerance_px(spacing_px):
                        continue
                    biased = _locally_biased(
                        sampson_distances(conics[k], ring_pts), ring_pts, p, reach
                    ) or _locally_biased(apts @ ln[:2] + ln[2], apts, p, reach)
                    q = _local_crossing(ring_pts, ring_line, apts, ln, p, reach) if biased else None
                    if q is not None and np.linalg.norm(q - p) < 2.0:
                        p = q
                if not (0 <= p[0] <= w - 1 and 0 <= p[1] <= h - 1):
                    continue
                pt = np.zeros(3)
                pt[axis_idx] = side * r
                points_px.append(p)
                points_t.append(pt)
                names.append(f"r{k}{'+' if side > 0 else '-'}{axis_name}")
                if k == kmax:
                    key = {("x", 1.0): "A", ("x", -1.0): "B", ("y", 1.0): "C", ("y", -1.0): "D"}
                    named[key[(axis_name, side)]] = p
    return points_px, points_t, names, named
