"""Projective geometry of conics and lines in the image, for the concentric-circles target.

Conics are symmetric 3x3 matrices ``C`` with ``x^T C x = 0`` for homogeneous image points
``x = (u, v, 1)``; lines are 3-vectors ``l`` with ``l . x = 0``. The images of concentric
circles form a pencil whose member pairs share the image of the common centre as the
eigenvector of ``C1^-1 C2`` with the non-repeated eigenvalue (the ratio of the squared radii);
the polar of that centre is the vanishing line of the target plane.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from scanner.core.conventions import check_points
from scanner.core.jit import njit

__all__ = [
    "circle_tilt_deg",
    "conic_from_coefficients",
    "conic_ray_distances",
    "fit_conic",
    "fit_line",
    "harmonic_conjugate",
    "intersect_lines",
    "line_conic_intersections",
    "line_through",
    "pencil_center",
    "pencil_member",
    "sampson_distances",
]


def _normalizer(points: NDArray) -> NDArray:
    """Hartley normalisation: centroid to the origin, mean distance sqrt(2)."""
    c = points.mean(axis=0)
    s = np.sqrt(2.0) / max(float(np.mean(np.linalg.norm(points - c, axis=1))), 1e-12)
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def conic_from_coefficients(a: ArrayLike) -> NDArray:
    """Symmetric matrix of ``a u^2 + b uv + c v^2 + d u + e v + f``, coefficients ``(6,)``."""
    a, b, c, d, e, f = np.asarray(a, dtype=np.float64)
    return np.array([[a, b / 2, d / 2], [b / 2, c, e / 2], [d / 2, e / 2, f]])


def sampson_distances(conic: NDArray, points_px: NDArray) -> NDArray:
    """First-order geometric (Sampson) distance of ``(M, 2)`` points to a conic, pixels, signed."""
    u, v = points_px[:, 0], points_px[:, 1]
    # x^T C for x = (u, v, 1): its first two entries are half the gradient
    cu = conic[0, 0] * u + conic[1, 0] * v + conic[2, 0]
    cv = conic[0, 1] * u + conic[1, 1] * v + conic[2, 1]
    cw = conic[0, 2] * u + conic[1, 2] * v + conic[2, 2]
    alg = cu * u + cv * v + cw
    return alg / np.maximum(2.0 * np.sqrt(cu * cu + cv * cv), 1e-300)


def fit_conic(points_px: ArrayLike, geometric: bool = True) -> NDArray:
    """Fit a conic to ``(M, 2)`` image points, M >= 5.

    Algebraic least squares in Hartley-normalised coordinates, then (``geometric``) a
    refinement minimising the Sampson distances, which is the geometric distance to first
    order. Returns the conic with unit Frobenius norm.

    Notes
    -----
    The Sampson distance ``alg / |grad|`` is homogeneous of degree 0 in the six
    coefficients: their scale is free. The refinement moves them only across it, in the five
    directions orthogonal to the algebraic solution ``a0`` (``a = a0 + B z``), so that its
    Jacobian has full rank and Levenberg-Marquardt stops after a few evaluations (3-6 on
    the detector's rings, against 12-17 with all six coefficients free, at the same or a
    lower RMS).
    """
    p = check_points(points_px, min_count=5, name="points_px", dim=2)
    T = _normalizer(p)
    q = p @ T[:2, :2].T + T[:2, 2]
    u, v = q[:, 0], q[:, 1]
    design = np.column_stack([u * u, u * v, v * v, u, v, np.ones_like(u)])
    if len(design) < 6:  # (five points: a zero row gives the sixth right-singular vector)
        design = np.vstack([design, np.zeros((6 - len(design), 6))])
    _, _, vt = np.linalg.svd(design, full_matrices=False)
    a0 = vt[-1]
    if geometric and len(p) > 6:
        basis = vt[:-1].T  # (6, 5): orthonormal, orthogonal to a0
        # The gradient of the conic at each point: d(alg)/du and d(alg)/dv, linear in a.
        d_grad_u = np.column_stack([2 * u, v, np.zeros_like(u), np.ones_like(u), 0 * u, 0 * u])
        d_grad_v = np.column_stack([0 * u, u, 2 * v, 0 * u, np.ones_like(u), 0 * u])
        design_b, d_grad_u_b, d_grad_v_b = design @ basis, d_grad_u @ basis, d_grad_v @ basis
        alg0, gu0, gv0 = design @ a0, d_grad_u @ a0, d_grad_v @ a0

        def parts(z: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
            alg = alg0 + design_b @ z
            gu, gv = gu0 + d_grad_u_b @ z, gv0 + d_grad_v_b @ z
            n = np.sqrt(np.maximum(gu * gu + gv * gv, 1e-300))
            return alg, gu, gv, n

        def resid(z: NDArray) -> NDArray:
            alg, _, _, n = parts(z)
            return alg / n

        def jac(z: NDArray) -> NDArray:
            alg, gu, gv, n = parts(z)
            d_n = (gu[:, None] * d_grad_u_b + gv[:, None] * d_grad_v_b) / n[:, None]
            return design_b / n[:, None] - (alg / (n * n))[:, None] * d_n

        sol = least_squares(resid, np.zeros(5), jac=jac, method="lm", x_scale="jac")
        a0 = a0 + basis @ sol.x
    cn = conic_from_coefficients(a0 / np.linalg.norm(a0))
    conic = T.T @ cn @ T
    return conic / np.linalg.norm(conic)


def fit_line(points_px: ArrayLike) -> NDArray:
    """Total-least-squares line through ``(M, 2)`` points: ``(a, b, c)``, ``a^2 + b^2 = 1``."""
    p = check_points(points_px, min_count=2, name="points_px", dim=2)
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[-1]
    return np.array([n[0], n[1], -float(n @ c)])


def line_through(point_px: ArrayLike, angle_rad: float) -> NDArray:
    """The line ``(3,)`` through ``point_px`` ``(2,)`` along the direction ``angle_rad`` (from
    the image's x axis towards its y axis), homogeneous with ``a^2 + b^2 = 1``."""
    normal = np.array([-np.sin(angle_rad), np.cos(angle_rad)])
    return np.array([normal[0], normal[1], -float(normal @ np.asarray(point_px, float))])


def intersect_lines(l1: ArrayLike, l2: ArrayLike) -> NDArray:
    """Homogeneous intersection ``(3,)`` of two lines ``(3,)``: ``np.cross(l1, l2)``.

    (Written out: the detector asks for thousands per image, and ``np.cross`` takes about
    60 us for two 3-vectors; the same products and differences, so the same bits.)
    """
    a = np.asarray(l1, float)
    b = np.asarray(l2, float)
    if a.shape != (3,) or b.shape != (3,):
        return np.cross(a, b)
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def line_conic_intersections(line: ArrayLike, conic: NDArray) -> NDArray:
    """The 0 or 2 real intersections of a line and a conic, ``(k, 2)`` pixels."""
    ln = np.asarray(line, dtype=np.float64)
    n = ln[:2] / np.linalg.norm(ln[:2])
    c0 = -ln[2] / np.linalg.norm(ln[:2]) * n  # foot of the origin on the line
    d = np.array([-n[1], n[0]])
    p0 = np.array([c0[0], c0[1], 1.0])
    dh = np.array([d[0], d[1], 0.0])
    a = dh @ conic @ dh
    b = 2 * dh @ conic @ p0
    c = p0 @ conic @ p0
    disc = b * b - 4 * a * c
    if disc < 0 or abs(a) < 1e-300:
        return np.zeros((0, 2))
    sq = np.sqrt(disc)
    # Numerically stable roots.
    qq = -0.5 * (b + np.copysign(sq, b))
    ts = [qq / a, c / qq if qq != 0 else -b / (2 * a)]
    return np.array([c0 + t * d for t in sorted(ts)])


def pencil_center(c1: NDArray, c2: NDArray) -> tuple[NDArray, float]:
    """Image of the common centre of two concentric circles from their image conics.

    Returns
    -------
    center : ndarray, shape (3,)
        Homogeneous, the eigenvector of ``c1^-1 c2`` with the non-repeated eigenvalue.
    ratio : float
        The non-repeated eigenvalue divided by the mean of the other two (the conics' scale
        is lost): for exact images of circles of radii r1 (``c1``) and r2 (``c2``) it equals
        ``r2^2 / r1^2``.
    """
    m = np.linalg.solve(c1, c2)
    w, v = np.linalg.eig(m)
    w = np.real_if_close(w, tol=1e6)
    # The repeated pair is the closest pair of eigenvalues.
    pairs = [(0, 1, 2), (0, 2, 1), (1, 2, 0)]
    i, j, k = min(pairs, key=lambda t: abs(w[t[0]] - w[t[1]]))
    center = np.real(v[:, k])
    ratio = float(np.real(w[k]) / np.real(0.5 * (w[i] + w[j])))
    return center / (center[2] if abs(center[2]) > 1e-300 else 1.0), ratio


def pencil_member(c1: NDArray, r1: float, c2: NDArray, r2: float, r: float) -> NDArray:
    """Image of the circle of radius ``r`` concentric with two whose image conics are given.

    The images of concentric circles of radius ``r`` are ``A - r^2 B`` for one pair of
    conics (the circular points' and the vanishing line's, mapped into the image). Each
    given conic carries its own unknown scale; their ratio is the repeated eigenvalue of
    ``c1^-1 c2``, which puts both on one scale and gives ``A`` and ``B``.

    Parameters
    ----------
    c1, c2 : ndarray, shape (3, 3)
        Image conics of the circles of radii ``r1`` and ``r2`` (any scale, ``r1 != r2``).
    r1, r2, r : float
        The radii (any unit, the same for all three).

    Returns
    -------
    ndarray, shape (3, 3)
        The conic of radius ``r``, unit Frobenius norm, its upper-left 2x2 block of
        non-negative trace (whatever the signs of ``c1`` and ``c2``).
    """
    w = np.linalg.eigvals(np.linalg.solve(c1, c2))
    pairs = [(0, 1), (0, 2), (1, 2)]
    i, j = min(pairs, key=lambda t: abs(w[t[0]] - w[t[1]]))
    rho = float(np.real(0.5 * (w[i] + w[j])))
    g1 = rho * np.asarray(c1, dtype=np.float64)
    b = (g1 - c2) / (r2**2 - r1**2)
    member = g1 + r1**2 * b - r**2 * b
    # One sign for every member (an ellipse's quadratic part positive), so that signed
    # distances to members predicted from different pairs can be compared.
    member = member / np.linalg.norm(member)
    return -member if np.trace(member[:2, :2]) < 0 else member


def circle_tilt_deg(
    conic: NDArray, centre_px: ArrayLike, principal_px: ArrayLike
) -> tuple[float, float] | None:
    """Tilt of a circle's plane from its line of sight, from the circle's image alone.

    The polar of the image of the circle's centre is the plane's vanishing line; it meets
    the conic at the plane's circular points, which lie on the image of the absolute conic
    ``K^-T K^-1``. With square pixels and the principal point given, that fixes the focal
    length; the plane's normal ``K^T l`` and the ray ``K^-1 o`` then give the tilt. The
    image's flatness alone does not: off the principal point the image plane foreshortens
    the image by the ray's own obliquity as well (a target tilted 64.6 deg 28 deg off the
    axis is imaged as flat as one tilted 67 deg on it).

    Parameters
    ----------
    conic : ndarray, shape (3, 3)
        The circle's image conic (any scale).
    centre_px : array_like, shape (2,)
        The image of the circle's centre (for concentric circles, their pencil's centre).
    principal_px : array_like, shape (2,)
        The principal point assumed, px.

    Returns
    -------
    (float, float) or None
        The angle between the plane's normal and the line of sight through the centre (deg)
        and the focal length that gave it (px); None where the circular points give no
        positive focal length (a nearly frontal view: the vanishing line far outside, the
        tilt near 0 and ill-determined, or a principal point far off).
    """
    c = np.asarray(conic, dtype=np.float64)
    o = np.array([*np.asarray(centre_px, dtype=np.float64), 1.0])
    u0, v0 = (float(x) for x in np.asarray(principal_px, dtype=np.float64))
    # In coordinates centred on the principal point the absolute conic's image is
    # diag(1, 1, f^2) and the ray to o is (x, y, f).
    shift = np.array([[1.0, 0.0, u0], [0.0, 1.0, v0], [0.0, 0.0, 1.0]])
    c = shift.T @ c @ shift
    o = np.linalg.solve(shift, o)
    line = c @ o
    # two points spanning the vanishing line, and the line's crossings with the conic
    p1 = np.cross(line, [line[1], -line[0], 0.0])
    p2 = np.array([line[1], -line[0], 0.0])
    a, b, k = float(p2 @ c @ p2), float(p1 @ c @ p2), float(p1 @ c @ p1)
    if abs(a) < 1e-300 or a * k - b * b <= 0:
        return None  # (the line meets the conic in real points: not an ellipse's polar)
    circular = p1 + complex(-b, np.sqrt(a * k - b * b)) / a * p2
    # circular . diag(1, 1, f^2) . circular = 0: x^2 + y^2 + f^2 w^2 = 0
    xy = circular[0] ** 2 + circular[1] ** 2
    w2 = circular[2] ** 2
    if abs(w2) < 1e-300:
        return None
    f2 = float(-(xy * np.conj(w2)).real / abs(w2) ** 2)
    if not np.isfinite(f2) or f2 <= 0.0:
        return None
    f = float(np.sqrt(f2))
    normal = np.array([line[0] * f, line[1] * f, line[2]])  # K^T l, K = diag(f, f, 1)
    ray = np.array([o[0] / o[2], o[1] / o[2], f])
    cos_tilt = abs(float(normal @ ray)) / (np.linalg.norm(normal) * np.linalg.norm(ray))
    return float(np.degrees(np.arccos(min(cos_tilt, 1.0)))), f


def harmonic_conjugate(a: ArrayLike, b: ArrayLike, o: ArrayLike) -> NDArray:
    """Harmonic conjugate of ``o`` with respect to ``a`` and ``b`` (collinear pixels).

    Returns the homogeneous point ``(3,)`` x with cross ratio (a, b; o, x) = -1; for ``o`` the
    image of the midpoint of a segment, x is the segment's vanishing point (at infinity, third
    coordinate 0, when the segment is fronto-parallel).
    """
    a, b, o = (np.asarray(x, dtype=np.float64) for x in (a, b, o))
    d = b - a
    length = float(np.linalg.norm(d))
    if length < 1e-12:
        raise ValueError("harmonic_conjugate: expected distinct points a and b")
    d = d / length
    ta, tb, to = 0.0, length, float((o - a) @ d)
    num = tb * (to - ta) + ta * (to - tb)
    den = 2 * to - ta - tb
    return np.array([den * a[0] + num * d[0], den * a[1] + num * d[1], den])


@njit(cache=True, nogil=True, error_model="numpy")
def _ray_roots(c00, c01_c10, c11, cp0, cp1, cc, dx, dy):  # pragma: no cover - compiled
    out = np.empty(dx.size)
    for k in range(dx.size):
        # the quadratic in t, term by term as NumPy's array expressions take them
        a = c00 * dx[k] * dx[k] + c01_c10 * dx[k] * dy[k] + c11 * dy[k] * dy[k]
        b = 2.0 * (dx[k] * cp0 + dy[k] * cp1)
        disc = b * b - 4 * a * cc
        sq = np.sqrt(disc)
        t1 = (-b + sq) / (2 * a)
        t2 = (-b - sq) / (2 * a)
        t = t1 if t1 > 0 else t2
        out[k] = t if disc >= 0 and t > 0 else np.nan
    return out


def conic_ray_distances(conic: NDArray, c: ArrayLike, dirs: NDArray) -> NDArray:
    """Where the rays ``c + t dir`` meet a conic: the positive ``t`` per direction.

    Of the quadratic ``a t^2 + b t + c = 0``'s roots, ``(-b + sqrt(b^2 - 4ac)) / 2a`` where
    it is positive (the larger root for ``a > 0``, a conic and its negative giving the
    other), else ``(-b - sqrt(b^2 - 4ac)) / 2a``; NaN where that is not positive or the ray
    misses the conic. The conic is taken in float64. (The quadratic's terms per direction are
    compiled:
    the detector asks for thousands of these per image, each a dozen array operations on a
    few directions in NumPy; the same arithmetic, so the same bits.)

    Parameters
    ----------
    conic : ndarray, shape (3, 3)
    c : array_like, shape (2,)
        The rays' origin, px.
    dirs : ndarray, shape (N, 2)
        Their directions (unit or not: ``t`` is in their lengths).

    Returns
    -------
    ndarray, shape (N,)
    """
    conic = np.asarray(conic, dtype=np.float64)
    p0 = np.array([c[0], c[1], 1.0], dtype=np.float64)
    cp = conic @ p0
    cc = float(p0 @ cp)
    d = np.asarray(dirs, dtype=np.float64)
    if conic.shape != (3, 3) or d.ndim != 2 or d.shape[1] != 2:
        raise ValueError(
            f"conic, dirs: expected shapes (3, 3) and (N, 2), got {conic.shape}, {d.shape}"
        )
    return _ray_roots(
        float(conic[0, 0]),
        float(conic[0, 1] + conic[1, 0]),
        float(conic[1, 1]),
        float(cp[0]),
        float(cp[1]),
        cc,
        np.ascontiguousarray(d[:, 0]),
        np.ascontiguousarray(d[:, 1]),
    )
