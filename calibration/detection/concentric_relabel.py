"""The rays' ring crossings named again by one model of the whole target.

Each ray from a candidate centre names its crossings on its own, by the projectivity of the
radii that fits them best (:func:`~calibration.detection.ray_kernels.label_rays`). Where the
print is faint and a ray misses the inner rings, or the candidate centre is off O, a
projectivity fits the crossings as well a ring or two off, and whole sectors of rays are
named so: every ring's conic is then fitted to a mixture of rings (randomised views 16:11 and
19:76, whose fine stage measures them right from the true conics). Together the crossings pin
the target: the image of concentric circles is one homography's, seven parameters for every
ring. :func:`relabelled_pencil` fits it robustly to the crossings as named, names each
crossing by the ring nearest it under the fit, and fits again until the names settle.

A laser stripe over O hides every ray's start: a ray names its first crossing ring 0 whatever
ring it is, and where the stripe runs along the rays the inner rings are hidden on most of
them (randomised view 18:66: with O and the diameters given, 153 of 248 crossings named one
to three rings in). Such a ray is right but for a shift of all its names: where the rays
start under hidden print, the model is judged by each ray's names moved out by the shift that
agrees with it best (:func:`_shifted_names`). Half of the draws come from the rays that
crossed every ring, whose names cannot be shifted.

The detector's last pass only (:mod:`calibration.detection.concentric`): every view another
pass measures keeps its measurement, and what this pass proposes is judged by the fine stage's
checks like any other pencil.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from calibration.detection.concentric_rings import MIN_CONIC_POINTS, concentric_affine_linear

__all__ = ["relabelled_pencil"]

#: A crossing is named by the ring nearest it under the fit if it is within this fraction of
#: the smallest ring gap of it (a crossing a ring off lies a whole gap away); others are left
#: out of the next fit.
NAME_FRACTION = 0.3

#: Of the crossings the rays found, at least this share must be named in the end: the model
#: must explain most of what was seen, not a corner of it.
MIN_NAMED_SHARE = 0.5

#: Rounds of fitting and naming at most (the names settle in two or three).
MAX_ROUNDS = 8

#: Rays whose crossings start a draw, and draws: with half the rays named wrong, 40 draws of
#: four miss a draw of right rays once in 200.
SAMPLE_RAYS = 4
SAMPLES = 40

#: The draws whose affine models agree best that are fitted with the perspective too.
PERSPECTIVE_DRAWS = 5


def target_from_image(params: NDArray) -> NDArray:
    """The homography ``(3, 3)`` from the image to the target plane (mm) of the parameters.

    ``params = (a, b, d, ox, oy, vx, vy)``: the image point ``p`` maps to
    ``A (p - o) / (1 + v . (p - o))`` with ``A = [[a, b], [0, d]]`` (the target's rotation
    about O is not seen by concentric rings: ``A`` is upper triangular), ``o`` the image of O.
    """
    a, b, d, ox, oy, vx, vy = (float(x) for x in params)
    lin = np.array([[a, b], [0.0, d]])
    o = np.array([ox, oy])
    v = np.array([vx, vy])
    g = np.zeros((3, 3))
    g[:2, :2] = lin
    g[:2, 2] = -lin @ o
    g[2, :2] = v
    g[2, 2] = 1.0 - float(v @ o)
    return g


def _radius_mm(params: NDArray, pts: NDArray) -> tuple[NDArray, NDArray]:
    """Each point's radius on the target (mm) under the model, and its distance from o (px)."""
    q = pts - params[3:5]
    w = 1.0 + q @ params[5:7]
    x = q @ np.array([[params[0], 0.0], [params[1], params[2]]]) / w[:, None]
    return np.linalg.norm(x, axis=1), np.linalg.norm(q, axis=1)


def _residual_px(params: NDArray, pts: NDArray, r_mm: NDArray) -> NDArray:
    """Each point's miss of its ring ``r_mm`` under the model, px: ``(rho - r)`` mm along the
    ray from o, times the local px per mm (``|p - o| / rho``)."""
    rho, q = _radius_mm(params, pts)
    return (rho - r_mm) * q / np.maximum(rho, 1e-9)


def _residual_jacobian(params: NDArray, pts: NDArray, r_mm: NDArray) -> NDArray:
    """The ``(N, 7)`` derivatives of :func:`_residual_px` by ``(a, b, d, ox, oy, vx, vy)``.

    With ``q = p - o``, ``u = (a qx + b qy, d qy)``, ``w = 1 + v . q``, ``s = |u|`` and
    ``n = |q|``, the residual is ``n - r n |w| / s`` (``rho = s / |w|``). Written out, the fit
    costs one evaluation a step instead of eight (a numerical Jacobian of seven parameters),
    which matters on views of clutter, where fits of badly named crossings crawl on for
    hundreds of steps.
    """
    a, b, d = (float(x) for x in params[:3])
    q = pts - params[3:5]
    qx, qy = q[:, 0], q[:, 1]
    n = np.maximum(np.hypot(qx, qy), 1e-12)
    w = 1.0 + q @ params[5:7]
    aw, sw = np.abs(w), np.sign(w)
    u0, u1 = a * qx + b * qy, d * qy
    s = np.maximum(np.hypot(u0, u1), 1e-12)
    k = r_mm * n * aw / s**3  # d f / d s, over s
    jac = np.empty((len(pts), 7))
    jac[:, 0] = k * u0 * qx
    jac[:, 1] = k * u0 * qy
    jac[:, 2] = k * u1 * qy
    # d f / d q, and d f / d o = -d f / d q
    dn = q / n[:, None]
    ds = np.column_stack([u0 * a, u0 * b + u1 * d])  # s * d s / d q
    dq = (
        dn * (1.0 - r_mm * aw / s)[:, None]
        - (r_mm * n * sw / s)[:, None] * params[5:7]
        + k[:, None] * ds
    )
    jac[:, 3:5] = -dq
    jac[:, 5:7] = -(r_mm * n * sw / s)[:, None] * q
    return jac


#: Evaluations of a perspective fit to one draw's rays at most; a fit that has not converged
#: by then is dropped (as one that ran to least_squares' default of 700 was before). Such a
#: fit only starts the naming: on the randomised benchmark's views with a target it settled
#: within 70 where it mattered, while on views of clutter, where a draw's crossings pin the
#: perspective nowhere, it crawled on to 700 (half a second each, most of a target-free
#: view's time) and was dropped then. Over seeds 0-23 the cap changed no outcome.
DRAW_FIT_EVALUATIONS = 100


def _fit(
    params: NDArray,
    pts: NDArray,
    r_mm: NDArray,
    scale_px: float | None,
    max_evaluations: int | None = None,
) -> NDArray | None:
    """The model fitted to ``pts`` named ``r_mm``: robustly (Cauchy, ``scale_px``) or, for
    ``None``, by plain least squares; at most ``max_evaluations`` of the residuals (None:
    least_squares' default)."""
    loss = {} if scale_px is None else {"loss": "cauchy", "f_scale": scale_px}
    fit = least_squares(
        _residual_px,
        params,
        jac=_residual_jacobian,
        x_scale="jac",
        max_nfev=max_evaluations,
        args=(pts, r_mm),
        **loss,
    )
    if not fit.success or not np.all(np.isfinite(fit.x)):
        return None
    return fit.x


def _affine_start(pts: NDArray, r_mm: NDArray, c: NDArray) -> NDArray | None:
    """The model without its projective part (:func:`concentric_affine_linear`), ``A`` the
    upper triangular root of ``M = A^T A``."""
    linear = concentric_affine_linear(pts - c, r_mm)
    if linear is None:
        return None
    m, o = linear
    upper = np.linalg.cholesky(m).T
    return np.array([upper[0, 0], upper[0, 1], upper[1, 1], c[0] + o[0], c[1] + o[1], 0.0, 0.0])


def _shifted_names(
    rho_mm: NDArray, labels: NDArray, ray_of: NDArray, radii: NDArray, shift: bool = True
) -> tuple[NDArray, NDArray]:
    """The crossings' names, each ray's moved out by the number of rings that agrees best
    with a model, and whether the model agrees with each.

    Parameters
    ----------
    rho_mm : ndarray, shape (N,)
        Each crossing's radius on the target under the model.
    labels : ndarray, shape (N,), int
        The rings the rays named the crossings.
    ray_of : ndarray, shape (N,), int
        Each crossing's ray, ``0 .. R-1``.
    radii : ndarray, shape (K,)
        The spec's ring radii, mm.
    shift : bool
        False: every shift is 0 (the names as the rays gave them).

    Returns
    -------
    names : ndarray, shape (N,), int
        ``labels`` plus the ray's shift: of the shifts ``0 .. K-1`` that keep every name of
        the ray below ``K``, the one under which most of the ray's crossings lie within
        :data:`NAME_FRACTION` of a gap of their ring (the smallest one of a tie).
    agree : ndarray, shape (N,), bool
        Whether each crossing lies so under its new name.
    """
    k = len(radii)
    tol_mm = NAME_FRACTION * float(np.min(np.diff(radii)))
    if not shift:
        return labels, np.abs(rho_mm - radii[labels]) < tol_mm
    n_rays = int(ray_of.max()) + 1 if len(ray_of) else 0
    top = np.zeros(n_rays, dtype=np.int64)
    np.maximum.at(top, ray_of, labels)
    votes = np.full((k, n_rays), -1.0)
    for by in range(k):
        near = np.abs(rho_mm - radii[np.minimum(labels + by, k - 1)]) < tol_mm
        votes[by] = np.bincount(ray_of, weights=near, minlength=n_rays)
        votes[by, top + by >= k] = -1.0
    names = labels + np.argmax(votes, axis=0)[ray_of]
    return names, np.abs(rho_mm - radii[names]) < tol_mm


def _settle(
    params: NDArray,
    pts: NDArray,
    labels: NDArray,
    ray_of: NDArray,
    radii: NDArray,
    shift: bool,
) -> tuple[NDArray, NDArray, NDArray] | None:
    """From a model, fit and name the crossings in turn until the names settle: the model,
    every crossing's ring and whether it is named (within :data:`NAME_FRACTION` of a gap).
    The first names are the rays' own (each ray's shifted with ``shift``,
    :func:`_shifted_names`)."""
    gap_mm = float(np.min(np.diff(radii)))
    rho, q = _radius_mm(params, pts)
    scale_px = 0.25 * gap_mm * float(np.median(q / np.maximum(rho, 1e-9)))
    labels, named = _shifted_names(rho, labels, ray_of, radii, shift)
    for _ in range(MAX_ROUNDS):
        if named.sum() < MIN_NAMED_SHARE * len(pts):
            break
        fitted = _fit(params, pts[named], radii[labels[named]], scale_px)
        if fitted is None:
            return None
        params = fitted
        rho, _ = _radius_mm(params, pts)
        nearest = np.argmin(np.abs(rho[:, None] - radii[None, :]), axis=1)
        near = np.abs(rho - radii[nearest]) < NAME_FRACTION * gap_mm
        if np.array_equal(nearest[near], labels[near]) and np.array_equal(near, named):
            break
        labels, named = np.where(near, nearest, labels), near
    return params, labels, named


def relabelled_pencil(
    per_ring: list[list[tuple[float, NDArray]]],
    radii: NDArray,
    c: NDArray,
    min_rings: int,
    start_hidden: bool = False,
) -> tuple[dict[int, NDArray], NDArray] | str:
    """Ring conics and the image of O from one homography fitted to every ray crossing.

    Rays are named whole, so they are sampled whole (:data:`SAMPLE_RAYS`, :data:`SAMPLES`
    draws, seeded; the first half from the rays that crossed every ring, where there are
    enough): the draw whose affine model agrees with the most crossings as named (with
    ``start_hidden``, each ray's names shifted as :func:`_shifted_names` says), and the best
    of :data:`PERSPECTIVE_DRAWS` draws fitted with the perspective, each start the fit and the
    naming in turn; the one that names more crossings is kept.

    Parameters
    ----------
    per_ring : list of list of (float, ndarray, shape (2,))
        For every ring of the spec, the (ray angle, crossing px) the rays named it at
        (:func:`~calibration.detection.concentric_rays._label_rays`).
    radii : ndarray, shape (K,)
        The spec's ring radii, mm.
    c : ndarray, shape (2,)
        Where the rays came from (px).
    min_rings : int
        Fewest rings, each named at :data:`MIN_CONIC_POINTS` crossings or more over a quarter
        turn, for a pencil.
    start_hidden : bool
        Whether the rays start under hidden print (a stripe over ``c``): only then are a
        ray's names shifted as a whole (:func:`_shifted_names`). Elsewhere a ray sees its
        first ring, and shifts would only let clutter's crossings agree with more models.

    Returns
    -------
    tuple of (dict of int to ndarray, shape (3, 3); ndarray, shape (2,)), or str
        The image conic of each such ring (members of one pencil of concentric circles by
        construction) and ``o``, px; or why not.
    """
    radii = np.asarray(radii, dtype=np.float64)
    rows = [(a, p, k) for k, ring in enumerate(per_ring) for a, p in ring]
    if len(rows) < min_rings * MIN_CONIC_POINTS:
        return f"no ring pencil found: {len(rows)} ring crossings to name, too few"
    ray_angle = np.array([r[0] for r in rows])
    pts = np.array([r[1] for r in rows], dtype=np.float64).reshape(-1, 2)
    labels = np.array([r[2] for r in rows], dtype=np.int64)
    rays, ray_of = np.unique(ray_angle, return_inverse=True)
    rng = np.random.default_rng(0)

    def agreeing(model: NDArray) -> int:
        rho, _ = _radius_mm(model, pts)
        return int(np.sum(_shifted_names(rho, labels, ray_of, radii, start_hidden)[1]))

    # Affine models of the draws first (linear, cheap); the perspective fitted to the draws
    # of the best few (an affine model is a ring gap off over a tilted target, but ranks the
    # draws of right rays first). On a nearly frontal target a few noisy rays pin the
    # perspective badly and it may bend to a sector named wrong: the best of each kind is
    # followed through, and the one that names more crossings kept.
    draws: list[tuple[int, NDArray, NDArray]] = []
    every_ring = np.flatnonzero(np.bincount(ray_of) == len(radii))
    for draw in range(SAMPLES if len(rays) > SAMPLE_RAYS else 1):
        whole = len(every_ring) >= SAMPLE_RAYS and draw < SAMPLES // 2
        pool = every_ring if whole else np.arange(len(rays))
        pick = rng.choice(pool, size=min(SAMPLE_RAYS, len(pool)), replace=False)
        mine = np.isin(ray_of, pick)
        affine = _affine_start(pts[mine], radii[labels[mine]], c)
        if affine is not None:
            draws.append((agreeing(affine), affine, mine))
    draws.sort(key=lambda d: -d[0])
    best: list[tuple[int, NDArray] | None] = [draws[0][:2] if draws else None, None]
    for _, affine, mine in draws[:PERSPECTIVE_DRAWS]:
        fitted = _fit(affine, pts[mine], radii[labels[mine]], None, DRAW_FIT_EVALUATIONS)
        agree = agreeing(fitted) if fitted is not None else -1
        if fitted is not None and (best[1] is None or agree > best[1][0]):
            best[1] = (agree, fitted)
    # (a start naming fewer than MIN_NAMED_SHARE never came to name more, over the randomised
    # benchmark's views with and without a target: not followed, which halves the pass's
    # time on views of clutter)
    settled = [
        _settle(b[1], pts, labels, ray_of, radii, start_hidden)
        for b in best
        if b is not None and b[0] >= MIN_NAMED_SHARE * len(pts)
    ]
    settled = [s for s in settled if s is not None]
    if not settled:
        share = max((b[0] for b in best if b is not None), default=0)
        return (
            f"no ring pencil found: the rays' best model names {share} of {len(pts)} ring crossings"
        )
    params, labels, named = max(settled, key=lambda s: int(s[2].sum()))
    if named.sum() < MIN_NAMED_SHARE * len(pts):
        return (
            f"no ring pencil found: one homography names {int(named.sum())} of {len(pts)} ring "
            "crossings"
        )
    g = target_from_image(params)
    if abs(np.linalg.det(g)) < 1e-30 or params[0] <= 0 or params[2] <= 0:
        return "no ring pencil found: the ring crossings fit no homography"
    o = params[3:5].copy()
    conics: dict[int, NDArray] = {}
    for k in range(len(radii)):
        mine = pts[named & (labels == k)]
        if len(mine) < MIN_CONIC_POINTS:
            continue
        turn = np.sort(np.arctan2(mine[:, 1] - o[1], mine[:, 0] - o[0]))
        widest_gap = np.max(np.diff(np.concatenate([turn, turn[:1] + 2 * np.pi])))
        if 2 * np.pi - widest_gap < np.pi / 2:
            continue
        conic = g.T @ np.diag([1.0, 1.0, -(radii[k] ** 2)]) @ g
        conics[k] = conic / np.linalg.norm(conic)
    if len(conics) < min_rings:
        return (
            f"no ring pencil found: {len(conics)} rings named over a quarter turn by one "
            f"homography, expected >= {min_rings}"
        )
    return conics, o
