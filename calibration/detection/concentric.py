"""Detection of the concentric-circles target in one grey image.

The pipeline, every geometric fact coming from the target spec:

1. *Darkness map*: ``D = 1 - I / background`` with the background from a grey closing, so
   uneven light, vignetting and a bright laser stripe do not look like printed lines.
2. *Candidate centres*: the long straight thin dark lines (Hough) are candidates for the two
   diameters; each crossing of two of them is a candidate image of O.
3. *Ring labelling along rays*: from a candidate centre, rays in every direction cross the
   images of the rings in order (each ring's image is a convex curve around the image of
   O). A ray's first crossings are accepted only when they obey the 1-D projectivity
   ``t = a r / (1 + b r)`` of the known radii, which labels the rings and rejects rays that
   a laser stripe, the diameter lines or clutter disturb.
4. *Pencil*: conics fitted to each ring; the image of O is the eigenvector of ``C_i^-1 C_j``
   with the non-repeated eigenvalue, which must equal ``(r_j / r_i)^2`` of the spec.
5. *Sub-pixel*: for every ring, profiles along the conic's normals are sampled (bicubic) and
   the centre line of the printed line found as the fixed point of a symmetric-window
   centroid; the conic is refitted (algebraic, then Sampson distance) with outlier rejection.
   The diameter lines are located the same way between the rings.
6. *Labelling*: the orientation disc, looked for where each of the four candidate labellings
   puts it, must be dark at exactly one of them; A is that end, and C follows from z out of
   the face. Any doubt gives ``ok=False`` with a reason.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from calibration.detection.conics import (
    fit_conic,
    fit_line,
    harmonic_conjugate,
    intersect_lines,
    line_conic_intersections,
    pencil_center,
    sampson_distances,
)
from calibration.detection.observations import AxisObservation, RingObservation, TargetObservation
from scanner.core.images import to_gray_float
from scanner.core.targets import ConcentricCirclesTarget

__all__ = ["ConcentricDetectorSettings", "detect_concentric"]

log = logging.getLogger(__name__)

KIND = "concentric_circles"


@dataclass(frozen=True)
class ConcentricDetectorSettings:
    """Tuning of :func:`detect_concentric` (defaults suit 0.3 to 20 Mpx images)."""

    max_tilt_deg: float = 65.0
    """Views more oblique than this (ring images flatter than cos of it) are refused."""
    min_rings: int = 3
    """Fewest rings with a fitted conic for a detection."""
    ray_step_px: float = 0.125
    """Sampling step of the sub-pixel profiles."""
    max_conic_rms_px: float = 0.6
    """Rings whose refitted conic leaves a larger RMS are dropped."""
    min_arc_fraction: float = 0.25
    """A ring needs edge points over at least this fraction of its directions."""


# --------------------------------------------------------------------------------------------
# Image preparation


def _darkness(img: NDArray, kernel_px: int) -> tuple[NDArray, NDArray]:
    """Darkness ``1 - I / background`` (>= 0) and the background, closing with ``kernel_px``."""
    k = int(kernel_px) | 1
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    img32 = img.astype(np.float32)
    bg = cv2.morphologyEx(img32, cv2.MORPH_CLOSE, se)
    bg = np.maximum(bg, img32)
    # Unlit or dark surroundings are not target paper: no printed line can be seen there.
    lit = float(np.percentile(bg, 75))
    d = 1.0 - img32 / np.maximum(bg, 1e-6)
    d[bg < 0.3 * lit] = 0.0
    return np.clip(d, 0.0, 1.0).astype(np.float64), bg.astype(np.float64)


def _bright_mask(img: NDArray, kernel_px: int) -> NDArray:
    """1 where the image is clearly brighter than the paper around it (laser stripe, glare).

    The paper level is a median over a window wider than thin lines, bright or dark.
    """
    k = max(int(kernel_px) * 2 + 1, 15) | 1
    scale = 255.0 / max(float(img.max()), 1e-6)
    u8 = np.clip(img * scale, 0, 255).astype(np.uint8)
    paper = cv2.medianBlur(u8, min(k, 255)).astype(np.float64) / scale
    bright = img > paper * 1.12 + 0.02 * float(np.median(paper))
    bright = cv2.dilate(bright.astype(np.uint8), np.ones((3, 3), np.uint8))
    return bright.astype(np.float64)


def _noise_threshold(d: NDArray) -> float:
    med = float(np.median(d))
    mad = float(np.median(np.abs(d - med))) * 1.4826
    return max(0.06, med + 6.0 * mad)


# --------------------------------------------------------------------------------------------
# Candidate centres


def _hough_lines(mask: NDArray, min_votes: int, max_lines: int = 8) -> list[tuple[float, float]]:
    lines = cv2.HoughLines(mask, 1.0, np.pi / 720, max(min_votes, 10))
    if lines is None:
        return []
    h, w = mask.shape
    mid = np.array([w / 2, h / 2, 1.0])
    out: list[tuple[float, float]] = []
    for rho, theta in lines[:, 0, :]:
        dup = False
        l1 = _line_from_hough(rho, theta)
        for r2, t2 in out:
            dth = abs((theta - t2 + np.pi / 2) % np.pi - np.pi / 2)
            if dth > np.radians(4):
                continue
            l2 = _line_from_hough(r2, t2)
            x = intersect_lines(l1, l2)
            crossing_inside = abs(x[2]) > 1e-12 and (
                -w / 2 <= x[0] / x[2] <= 1.5 * w and -h / 2 <= x[1] / x[2] <= 1.5 * h
            )
            if crossing_inside or abs(float(l1 @ mid) - float(l2 @ mid)) < 15:
                dup = True
                break
        if not dup:
            out.append((float(rho), float(theta)))
        if len(out) >= max_lines:
            break
    return out


def _line_from_hough(rho: float, theta: float) -> NDArray:
    return np.array([np.cos(theta), np.sin(theta), -rho])


def _sample(img: NDArray, u: NDArray, v: NDArray, order: int = 1) -> NDArray:
    return ndimage.map_coordinates(img, [v, u], order=order, mode="constant", cval=0.0)


def _ray_peaks(profile: NDArray, thr: float) -> list[int]:
    """Indices of the maxima of the runs above ``thr`` of a 1-D profile."""
    above = profile > thr
    if not above.any():
        return []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], above.astype(np.int8), [0]])))
    starts, ends = edges[::2], edges[1::2]
    # A run touching the start is the centre's own crossing of the diameter lines.
    return [int(s + np.argmax(profile[s:e])) for s, e in zip(starts, ends) if s > 0]


def _projective_fit(r: NDArray, t: NDArray) -> tuple[float, float, float]:
    """Fit ``t = a r / (1 + b r)``; returns a, b and the largest residual in pixels."""
    A = np.column_stack([r, -r * t])
    sol, *_ = np.linalg.lstsq(A, t, rcond=None)
    a, b = float(sol[0]), float(sol[1])
    denom = 1 + b * r
    if np.any(denom <= 0.05) or a <= 0:
        return a, b, np.inf
    return a, b, float(np.max(np.abs(a * r / denom - t)))


def _rays_from(
    d: NDArray, c: NDArray, angles: NDArray, step: float = 1.0
) -> tuple[NDArray, NDArray, NDArray]:
    """Darkness profiles along rays from ``c``: (profiles (R, S), t (S,), valid (R, S))."""
    h, w = d.shape
    tmax = float(np.hypot(w, h))
    t = np.arange(1.0, tmax, step)
    du, dv = np.cos(angles), np.sin(angles)
    u = c[0] + du[:, None] * t[None, :]
    v = c[1] + dv[:, None] * t[None, :]
    valid = (u >= 1) & (u <= w - 2) & (v >= 1) & (v <= h - 2)
    prof = _sample(d, u.ravel(), v.ravel()).reshape(u.shape)
    prof[~valid] = 0.0
    return prof, t, valid


def _label_rays(
    d: NDArray,
    c: NDArray,
    radii: NDArray,
    thr: float,
    axis_angles: list[float],
    n_rays: int = 96,
) -> tuple[list[list[tuple[float, NDArray]]], int]:
    """Ring crossings labelled by the 1-D projectivity along rays from ``c``.

    Returns per ring a list of (angle, point px) and the number of consistent rays.
    """
    angles = np.linspace(0, 2 * np.pi, n_rays, endpoint=False) + 0.013
    keep = np.ones(n_rays, bool)
    for a in axis_angles:
        diff = np.abs((angles - a + np.pi) % (2 * np.pi) - np.pi)
        keep &= diff > np.radians(6)
    angles = angles[keep]
    prof, t, _ = _rays_from(d, c, angles)
    per_ring: list[list[tuple[float, NDArray]]] = [[] for _ in radii]
    good = 0
    for i, ang in enumerate(angles):
        peaks = _ray_peaks(prof[i], thr)
        m = min(len(peaks), len(radii))
        if m < 3:
            continue
        tp = t[np.asarray(peaks[:m])]
        _, _, err = _projective_fit(radii[:m], tp)
        if err > 1.5 + 0.01 * tp[-1]:
            continue
        good += 1
        dirv = np.array([np.cos(ang), np.sin(ang)])
        for k in range(m):
            per_ring[k].append((float(ang), c + tp[k] * dirv))
    return per_ring, good


# --------------------------------------------------------------------------------------------
# Sub-pixel location of a printed line's centre along profiles


def _locate_centres(
    coef: NDArray,
    points: NDArray,
    normals: NDArray,
    half_window: float,
    search: float,
    step: float,
    bright: NDArray | None = None,
) -> tuple[NDArray, NDArray, NDArray]:
    """Sub-pixel centre of a dark line near each of ``points`` along its ``normals``.

    ``coef`` is the cubic-spline prefiltered darkness image. Returns (offset along the normal,
    peak contrast above the local baseline, ok mask).
    """
    span = search + half_window + 1.0
    tau = np.arange(-span, span + step / 2, step)
    u = points[:, 0:1] + normals[:, 0:1] * tau[None, :]
    v = points[:, 1:2] + normals[:, 1:2] * tau[None, :]
    prof = ndimage.map_coordinates(coef, [v.ravel(), u.ravel()], order=3, prefilter=False)
    prof = prof.reshape(u.shape)
    inside = np.abs(tau) <= search
    start = np.where(inside[None, :], prof, -np.inf).argmax(axis=1)
    c = tau[start]
    n = len(points)
    rows = np.arange(n)
    for _ in range(12):
        lo, hi = c - half_window, c + half_window
        base = 0.5 * (_interp_rows(tau, prof, lo, rows) + _interp_rows(tau, prof, hi, rows))
        win = (tau[None, :] >= lo[:, None]) & (tau[None, :] <= hi[:, None])
        wgt = np.where(win, np.maximum(prof - base[:, None], 0.0), 0.0)
        s = wgt.sum(axis=1)
        c_new = np.where(s > 0, (wgt * tau[None, :]).sum(axis=1) / np.maximum(s, 1e-300), c)
        c_new = np.clip(c_new, -search, search)
        if np.max(np.abs(c_new - c)) < 1e-4:
            c = c_new
            break
        c = c_new
    peak = _interp_rows(tau, prof, c, rows)
    base = 0.5 * (
        _interp_rows(tau, prof, c - half_window, rows)
        + _interp_rows(tau, prof, c + half_window, rows)
    )
    contrast = peak - base
    ok = np.isfinite(c) & (np.abs(c) < search) & (contrast > 0)
    if bright is not None:
        # A profile touching something brighter than the paper (laser stripe, glare) is biased.
        hit = ndimage.map_coordinates(bright, [v.ravel(), u.ravel()], order=0, mode="constant")
        ok &= ~hit.reshape(u.shape).any(axis=1)
    return c, contrast, ok


def _interp_rows(tau: NDArray, prof: NDArray, x: NDArray, rows: NDArray) -> NDArray:
    step = tau[1] - tau[0]
    f = (x - tau[0]) / step
    i0 = np.clip(np.floor(f).astype(int), 0, len(tau) - 2)
    w1 = np.clip(f - i0, 0.0, 1.0)
    return prof[rows, i0] * (1 - w1) + prof[rows, i0 + 1] * w1


def _conic_point_on_ray(conic: NDArray, c: NDArray, dirs: NDArray) -> NDArray:
    """Positive t where ``c + t dir`` meets the conic, per direction (NaN if none)."""
    p0 = np.array([c[0], c[1], 1.0])
    dh = np.column_stack([dirs, np.zeros(len(dirs))])
    a = np.einsum("ij,jk,ik->i", dh, conic, dh)
    b = 2 * dh @ (conic @ p0)
    cc = float(p0 @ conic @ p0)
    disc = b * b - 4 * a * cc
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(disc)
        t1 = (-b + sq) / (2 * a)
        t2 = (-b - sq) / (2 * a)
    t = np.where(t1 > 0, t1, t2)
    t = np.where((disc >= 0) & (t > 0), t, np.nan)
    return t


def _conic_normals(conic: NDArray, pts: NDArray) -> NDArray:
    x = np.column_stack([pts, np.ones(len(pts))])
    g = (x @ conic)[:, :2]
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def _conic_axes_ratio(conic: NDArray) -> float:
    """minor/major axis ratio of an ellipse conic (0 if not an ellipse)."""
    a = conic[:2, :2]
    w = np.linalg.eigvalsh(a)
    if w[0] * w[1] <= 0:
        return 0.0
    w = np.abs(w)
    return float(np.sqrt(min(w) / max(w)))


def _ellipse_ok(conic: NDArray, c: NDArray) -> bool:
    a = conic[:2, :2]
    if np.linalg.det(a) <= 0:
        return False
    x = np.array([c[0], c[1], 1.0])
    # The centre must be inside: sign of x^T C x opposite to the sign of the quadratic part.
    return float(x @ conic @ x) * float(np.trace(a)) < 0


# --------------------------------------------------------------------------------------------
# The detector


def detect_concentric(
    image: NDArray,
    target: ConcentricCirclesTarget,
    settings: ConcentricDetectorSettings | None = None,
) -> TargetObservation:
    """Find, label and measure the concentric-circles target in one grey image.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        8/16-bit or float grey image (colour is reduced to grey).
    target : ConcentricCirclesTarget
        The spec: ring diameters, line width, orientation marker.
    settings : ConcentricDetectorSettings, optional

    Returns
    -------
    TargetObservation
        With rings (sub-pixel centre-line points and conics), both diameter lines, O, A-D,
        the vanishing points p, q, the marker, and the exact correspondences
        O, (+-r, 0, 0), (0, +-r, 0) per ring; or falsy with the reason.
    """
    s = settings or ConcentricDetectorSettings()
    img = to_gray_float(image)
    h, w = img.shape
    size = (int(w), int(h))
    if min(h, w) < 32:
        return TargetObservation.failed(f"image too small ({w}x{h})", size, KIND)
    radii = np.asarray(target.ring_radii_mm, dtype=np.float64)

    kernel = max(9, min(h, w) // 40)
    d, bg = _darkness(img, kernel)
    thr = _noise_threshold(d)
    mask = (d > thr).astype(np.uint8) * 255
    lines = _hough_lines(mask, min_votes=int(0.08 * min(h, w)))
    if len(lines) < 2:
        return TargetObservation.failed("no pair of diameter lines found", size, KIND)

    # -- candidate centres from pairs of long lines, scored by consistent ring rays
    best = None
    for i in range(len(lines)):
        for j in range(i + 1, len(lines)):
            (r1, t1), (r2, t2) = lines[i], lines[j]
            ang = abs((t1 - t2 + np.pi / 2) % np.pi - np.pi / 2)
            if ang < np.radians(12):
                continue
            l1, l2 = _line_from_hough(r1, t1), _line_from_hough(r2, t2)
            x = intersect_lines(l1, l2)
            if abs(x[2]) < 1e-12:
                continue
            c = x[:2] / x[2]
            if not (0 <= c[0] < w and 0 <= c[1] < h):
                continue
            axis_angles = [t1 + np.pi / 2, t1 - np.pi / 2, t2 + np.pi / 2, t2 - np.pi / 2]
            per_ring, good = _label_rays(d, c, radii, thr, axis_angles)
            if best is None or good > best[0]:
                best = (good, c, per_ring, (l1, l2), axis_angles)
    if best is None or best[0] < 12:
        return TargetObservation.failed(
            "no ring pencil found (no pair of lines with rings around their crossing)", size, KIND
        )
    _, c, per_ring, (l1, l2), axis_angles = best

    # -- initial conics and the pencil centre
    conics: dict[int, NDArray] = {}
    for k, pts in enumerate(per_ring):
        if len(pts) >= 8:
            angs = np.array([p[0] for p in pts])
            spread = np.ptp(np.unwrap(np.sort(angs)))
            if spread < np.pi / 2:
                continue
            conic = fit_conic(np.array([p[1] for p in pts]), geometric=False)
            if _ellipse_ok(conic, c):
                conics[k] = conic
    if len(conics) < s.min_rings:
        return TargetObservation.failed(
            f"no ring pencil found: {len(conics)} rings fitted, expected >= {s.min_rings}",
            size,
            KIND,
        )
    c = _pencil_centre(conics, radii, c)
    if c is None:
        return TargetObservation.failed(
            "no ring pencil found: the ring conics are not images of the spec's concentric "
            "circles (radius ratios disagree)",
            size,
            KIND,
        )

    # -- line width in px estimate, for windows
    spacing_px = _min_spacing_px(conics, c)
    line_frac = target.line_width_mm / float(np.min(np.diff(radii)))
    half_window = max(1.5, 1.6 * line_frac * spacing_px + 2.0)
    # Finer darkness map now that the scale is known (kernel several line widths, < spacing).
    kernel2 = int(np.clip(4 * half_window + 3, 9, max(9, 0.8 * spacing_px)))
    if kernel2 != kernel:
        d, bg = _darkness(img, kernel2)
    coef = ndimage.spline_filter(d, order=3)
    bright = _bright_mask(img, kernel2)

    # -- sub-pixel rings
    axis_lines = [l1 / np.linalg.norm(l1[:2]), l2 / np.linalg.norm(l2[:2])]
    rings: dict[int, tuple[NDArray, NDArray, NDArray]] = {}
    for _ in range(2):
        rings = {}
        n_rays = int(np.clip(_perimeter_px(conics[max(conics)], c) / 3.0, 180, 1440))
        angles = np.linspace(0, 2 * np.pi, n_rays, endpoint=False)
        dirs = np.column_stack([np.cos(angles), np.sin(angles)])
        for k in sorted(conics):
            res = _refine_ring(
                coef,
                conics[k],
                c,
                dirs,
                angles,
                axis_lines,
                half_window,
                spacing_px,
                s,
                (w, h),
                bright,
            )
            if res is not None:
                rings[k] = res
        if len(rings) < s.min_rings:
            return TargetObservation.failed(
                f"no ring pencil found: {len(rings)} rings measured, expected >= {s.min_rings}",
                size,
                KIND,
            )
        # The refitted conics replace the coarse ones; the pencil gives the centre again.
        conics = {k: v[1] for k, v in rings.items()}
        c_new = _pencil_centre(conics, radii, c)
        if c_new is None:
            return TargetObservation.failed(
                "no ring pencil found: refined ring conics disagree with the spec's radius ratios",
                size,
                KIND,
            )
        c = c_new
        # Refine the diameter lines from the rings' geometry.
        axis_res = _refine_axes(coef, axis_lines, c, conics, radii, half_window, (w, h), bright)
        if axis_res is None:
            return TargetObservation.failed(
                "diameter lines not measurable between the rings", size, KIND
            )
        axis_lines, axis_pts = axis_res
        # (A ring the coarse ray labelling missed is not recovered: only measured rings count.)

    ratio = min(_conic_axes_ratio(cn) for cn in conics.values())
    if ratio < np.cos(np.radians(s.max_tilt_deg)):
        return TargetObservation.failed(
            f"too oblique: ring images flattened to {ratio:.2f}, "
            f"expected >= {np.cos(np.radians(s.max_tilt_deg)):.2f} (tilt <= {s.max_tilt_deg} deg)",
            size,
            KIND,
        )

    # -- centre O: intersection of the diameter lines, checked against the pencil centre
    x = intersect_lines(axis_lines[0], axis_lines[1])
    o_lines = x[:2] / x[2]
    if np.linalg.norm(o_lines - c) > max(2.0, 0.05 * spacing_px):
        return TargetObservation.failed(
            f"diameter lines cross {np.linalg.norm(o_lines - c):.1f} px from the ring pencil's "
            "centre: not the target's diameters",
            size,
            KIND,
        )
    center = _combine_centre(o_lines, c, conics, axis_lines)

    # -- ends of each ring on both lines, in a consistent orientation
    kmax = max(conics)
    ends = []
    for ln in axis_lines:
        pts = line_conic_intersections(ln, conics[kmax])
        if len(pts) != 2:
            return TargetObservation.failed("diameter line misses the largest ring", size, KIND)
        ends.append(pts)
    labelled = _label_by_marker(img, bg, target, center, ends, conics, radii, axis_lines)
    if isinstance(labelled, str):
        return TargetObservation.failed(labelled, size, KIND)
    ix, sign_x, sign_y, marker_px = labelled
    xline, yline = _unit_line(axis_lines[ix]), _unit_line(axis_lines[1 - ix])

    # Lens distortion bends the lines and rings slightly: every crossing is refined by local
    # quadratic fits of the measured points around it (exact to second order).
    # O itself stays the mean of the pencil's centre and the lines' crossing: both use every
    # ring and line point, which beats a local fit at the noise level.
    pts_x, pts_y = axis_pts[ix], axis_pts[1 - ix]
    named: dict[str, NDArray] = {"O": center}
    points_px = [center]
    points_t = [np.zeros(3)]
    names = ["O"]
    for k in sorted(conics):
        r = radii[k]
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

    vps: dict[str, NDArray] = {}
    if all(n in named for n in "ABCD"):
        vps["p"] = harmonic_conjugate(named["A"], named["B"], center)
        vps["q"] = harmonic_conjugate(named["C"], named["D"], center)

    ring_obs = [
        RingObservation(
            radius_mm=float(radii[k]),
            edge_points_px=rings[k][0],
            conic=conics[k],
            index=int(k),
        )
        for k in sorted(rings)
    ]
    ax_pts_x, ax_pts_y = axis_pts[ix], axis_pts[1 - ix]
    axes = [
        AxisObservation("x", ax_pts_x, _unit_line(xline)),
        AxisObservation("y", ax_pts_y, _unit_line(yline)),
    ]
    return TargetObservation(
        ok=True,
        reason="",
        image_size=size,
        kind=KIND,
        points_px=np.asarray(points_px, dtype=np.float64),
        points_target=np.asarray(points_t, dtype=np.float64),
        point_names=names,
        rings=ring_obs,
        axis_points=axes,
        center_px=center,
        named_px=named,
        vanishing_points=vps,
        marker_px=marker_px,
    )


def _unit_line(ln: NDArray) -> NDArray:
    return ln / np.linalg.norm(ln[:2])


def _axis_dir(ln: NDArray, sign: float) -> NDArray:
    return sign * np.array([-ln[1], ln[0]]) / np.linalg.norm(ln[:2])


def _perimeter_px(conic: NDArray, c: NDArray) -> float:
    angles = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    t = _conic_point_on_ray(conic, c, dirs)
    t = np.where(np.isfinite(t), t, np.nanmedian(t))
    return float(np.sum(t) * 2 * np.pi / 64)


def _min_spacing_px(conics: dict[int, NDArray], c: NDArray) -> float:
    angles = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    ts = {k: _conic_point_on_ray(cn, c, dirs) for k, cn in conics.items()}
    keys = sorted(ts)
    gaps = [np.nanmin((ts[b] - ts[a]) / (b - a)) for a, b in itertools.pairwise(keys)]
    gaps.append(float(np.nanmin(ts[keys[0]])) / (keys[0] + 1))
    return float(max(np.nanmin(gaps), 3.0))


def _pencil_centre(conics: dict[int, NDArray], radii: NDArray, c0: NDArray) -> NDArray | None:
    """Image of O from the pencil of ring conics; None if the radius ratios disagree."""
    keys = sorted(conics)
    centres, bad = [], 0
    for a in range(len(keys)):
        for b in range(a + 1, len(keys)):
            i, j = keys[a], keys[b]
            try:
                ctr, ratio = pencil_center(conics[i], conics[j])
            except np.linalg.LinAlgError:
                bad += 1
                continue
            expect = (radii[j] / radii[i]) ** 2
            if not np.isfinite(ratio) or abs(ratio / expect - 1) > 0.05 + 0.02 * expect:
                bad += 1
                continue
            centres.append(ctr[:2])
    if not centres or bad > len(centres):
        return None
    centres_a = np.asarray(centres)
    med = np.median(centres_a, axis=0)
    if np.linalg.norm(med - c0) > 50 + 0.1 * np.linalg.norm(c0):
        return None
    return med


def _refine_ring(
    coef: NDArray,
    conic: NDArray,
    c: NDArray,
    dirs: NDArray,
    angles: NDArray,
    axis_lines: list[NDArray],
    half_window: float,
    spacing_px: float,
    s: ConcentricDetectorSettings,
    size: tuple[int, int],
    bright: NDArray | None = None,
) -> tuple[NDArray, NDArray, NDArray] | None:
    """Sub-pixel centre-line points of one ring and its refitted conic."""
    w, h = size
    t = _conic_point_on_ray(conic, c, dirs)
    ok = np.isfinite(t)
    pts = c + t[ok, None] * dirs[ok]
    # Away from the image border and from the diameter lines.
    margin = half_window + 3
    inside = (
        (pts[:, 0] > margin)
        & (pts[:, 0] < w - 1 - margin)
        & (pts[:, 1] > margin)
        & (pts[:, 1] < h - 1 - margin)
    )
    clear = np.ones(len(pts), bool)
    for ln in axis_lines:
        dist = np.abs(pts @ ln[:2] + ln[2])
        clear &= dist > 1.5 * half_window + 2
    pts = pts[inside & clear]
    if len(pts) < 16:
        return None
    normals = _conic_normals(conic, pts)
    search = max(1.0, min(0.3 * spacing_px, 3.0 * half_window))
    off, contrast, good = _locate_centres(
        coef, pts, normals, half_window, search, s.ray_step_px, bright
    )
    med = np.median(contrast[good]) if good.any() else 0.0
    good &= contrast > 0.5 * med
    found = pts + off[:, None] * normals
    found = found[good]
    if len(found) < max(16, s.min_arc_fraction * len(dirs) * 0.5):
        return None
    conic_new = fit_conic(found)
    for _ in range(3):
        dist = sampson_distances(conic_new, found)
        sig = 1.4826 * np.median(np.abs(dist)) + 1e-3
        keep = np.abs(dist) < max(4 * sig, 0.05)
        if keep.all():
            break
        found = found[keep]
        if len(found) < 16:
            return None
        conic_new = fit_conic(found)
    rms = float(np.sqrt(np.mean(sampson_distances(conic_new, found) ** 2)))
    if rms > s.max_conic_rms_px or not _ellipse_ok(conic_new, c):
        return None
    return found, conic_new, np.array([rms])


def _refine_axes(
    coef: NDArray,
    axis_lines: list[NDArray],
    c: NDArray,
    conics: dict[int, NDArray],
    radii: NDArray,
    half_window: float,
    size: tuple[int, int],
    bright: NDArray | None = None,
) -> tuple[list[NDArray], list[NDArray]] | None:
    """Sub-pixel points on both diameter lines, between the rings; refitted lines."""
    w, h = size
    keys = sorted(conics)
    new_lines, new_pts = [], []
    for ln in axis_lines:
        ln = _unit_line(ln)
        # Re-anchor the line through the current centre (keeps its direction).
        ln = np.array([ln[0], ln[1], -(ln[0] * c[0] + ln[1] * c[1])])
        dirv = np.array([-ln[1], ln[0]])
        samples = []
        for sgn in (1.0, -1.0):
            ts = [0.0]
            for k in keys:
                t = _conic_point_on_ray(conics[k], c, (sgn * dirv)[None, :])[0]
                ts.append(float(t) if np.isfinite(t) else np.nan)
            ts_a = np.asarray(ts)
            for a, b in itertools.pairwise(ts_a):
                if not (np.isfinite(a) and np.isfinite(b)):
                    continue
                gap = b - a
                clear = half_window + 1.5
                if gap < 2 * clear + 2:
                    continue
                n = max(1, int((gap - 2 * clear) / 2))
                for tt in np.linspace(a + clear, b - clear, n):
                    samples.append(c + sgn * tt * dirv)
        if len(samples) < 4:
            return None
        pts = np.asarray(samples)
        inside = (
            (pts[:, 0] > half_window + 3)
            & (pts[:, 0] < w - half_window - 4)
            & (pts[:, 1] > half_window + 3)
            & (pts[:, 1] < h - half_window - 4)
        )
        pts = pts[inside]
        if len(pts) < 4:
            return None
        normals = np.tile(ln[:2], (len(pts), 1))
        off, contrast, good = _locate_centres(
            coef, pts, normals, half_window, max(1.0, 2 * half_window), 0.125, bright
        )
        med = np.median(contrast[good]) if good.any() else 0.0
        good &= contrast > 0.5 * med
        found = (pts + off[:, None] * normals)[good]
        if len(found) < 4:
            return None
        line = fit_line(found)
        for _ in range(3):
            dist = found @ line[:2] + line[2]
            sig = 1.4826 * np.median(np.abs(dist)) + 1e-3
            keep = np.abs(dist) < max(4 * sig, 0.05)
            if keep.all() or keep.sum() < 4:
                break
            found = found[keep]
            line = fit_line(found)
        new_lines.append(line)
        new_pts.append(found)
    return new_lines, new_pts


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
) -> tuple[int, float, float, NDArray] | str:
    """Decide which end is A by the orientation disc; C follows (z out of the face).

    Returns (index of the x line in ``axis_lines``, sign of +x along the x line's direction,
    same for y, marker px) or a reason string.
    """
    h, w = img.shape
    r_big = radii[max(conics)]
    # Four ends around O in image order; candidate labellings are cyclic rotations.
    e = [ends[0][0], ends[1][0], ends[0][1], ends[1][1]]
    angs = [np.arctan2(p[1] - center[1], p[0] - center[0]) for p in e]
    order = np.argsort(angs)  # increasing image angle (clockwise on screen, v down)
    e = [e[i] for i in order]
    # Target x -> y is counter-clockwise on screen when looking at the face, i.e. decreasing
    # image angle: if A = e[i], then C = e[i - 1].
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
        ref = max(float(np.median(vout)), float(np.median(bgv)) * 0.5, 1e-6)
        # Every point inside the disc must be dark (the brightest decides), around it paper.
        scores.append(1.0 - float(np.max(vin)) / ref)
        candidates.append((a, cc, mc))
    sc = np.asarray(scores, dtype=np.float64)
    if np.all(np.isnan(sc)):
        return "orientation marker not visible (outside the image for every labelling)"
    best = int(np.nanargmax(sc))
    others = np.delete(sc, best)
    if sc[best] < 0.3:
        return f"orientation marker not visible (darkest candidate contrast {sc[best]:.2f})"
    if np.any(np.isnan(others)) and sc[best] < 0.5:
        return (
            "orientation marker ambiguous: a weak candidate while another candidate position "
            "lies outside the image"
        )
    if np.any(np.isfinite(others)) and np.nanmax(others) > 0.3 * sc[best]:
        return "orientation marker ambiguous: more than one dark disc where the marker may be"
    a, cc, mc = candidates[best]
    ix = 0 if min(np.linalg.norm(ends[0] - a, axis=1)) < 1e-6 else 1
    l_x, l_y = _unit_line(axis_lines[ix]), _unit_line(axis_lines[1 - ix])
    sx = 1.0 if float((a - center) @ _axis_dir(l_x, 1.0)) > 0 else -1.0
    sy = 1.0 if float((cc - center) @ _axis_dir(l_y, 1.0)) > 0 else -1.0
    return ix, sx, sy, mc


def _apply_h(H: NDArray, pts: NDArray) -> NDArray:
    x = np.column_stack([pts, np.ones(len(pts))]) @ H.T
    return x[:, :2] / x[:, 2:3]
