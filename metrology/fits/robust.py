"""The one robust fit loop every primitive runs, and the model interface it runs on.

In the manner of scikit-image's :func:`skimage.measure.ransac`, a primitive is a small
:class:`Model`: a hypothesis from a minimal sample, residuals, a least-squares refinement and
the result dataclass. :func:`robust_fit` does the rest for all of them:

1. **Robust detection** (when ``threshold_mm`` is given): MSAC (:func:`ransac`), a RANSAC
   variant that scores a hypothesis by its truncated squared distances, on a seeded random
   subsample of at most ``model.ransac_subsample`` points, with the iteration count adapted to
   the inlier ratio. For a big cloud of a ``presolve`` model the whole robust fit first runs
   on that subsample and its result's inliers, taken from the full cloud, start the rounds.
2. **Rounds**: least squares on the inliers alternated with the inlier set until the set is
   stable (at most ``model.max_rounds`` fits). The inlier band is the threshold, widened to
   :data:`BAND_SIGMAS` robust standard deviations of the residuals where the noise is wider
   (:func:`inlier_band`): a band narrower than the noise would clip the residuals and report
   the threshold as the form error.
3. **Result**: the model's dataclass from the last parameters and their inliers, or a failed
   fit (falsy, with a ``reason``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any, ClassVar, Generic, TypeVar

import numpy as np
from numpy.typing import NDArray

from metrology.fits.geometry import (
    SeedLike,
    extent,
    residual_stats,
    rng_from,
    subsample,
    take,
)
from metrology.fits.results import Fit

__all__ = [
    "BAND_SIGMAS",
    "CYLINDER_RANSAC_SUBSAMPLE",
    "MAX_ROUNDS",
    "RANSAC_SUBSAMPLE",
    "Model",
    "RadialModel",
    "check_threshold",
    "inlier_band",
    "radius_bounds",
    "ransac",
    "robust_fit",
]

log = logging.getLogger(__name__)

#: RANSAC hypotheses are scored on at most this many points (a seeded random subsample).
RANSAC_SUBSAMPLE = 20_000
#: The cylinder's RANSAC (two points and their normals) runs on at most this many points.
CYLINDER_RANSAC_SUBSAMPLE = 5_000
#: After RANSAC, least squares and the inlier set are alternated until the set is stable, at
#: most this many times.
MAX_ROUNDS = 6
#: After RANSAC the inlier band widens to this many robust standard deviations of the
#: residuals where the noise is wider than the threshold.
BAND_SIGMAS = 4.0

F = TypeVar("F", bound=Fit)
#: A model's parameters: a tuple of arrays and floats, e.g. ``(normal, d)`` for a plane.
Params = tuple[Any, ...]


class Model(Generic[F]):
    """A geometric primitive as :func:`robust_fit` sees it.

    Subclasses set the class attributes and implement :meth:`from_sample`,
    :meth:`residuals`, :meth:`refine` and :meth:`result` (and :meth:`from_fit` when
    ``presolve``). Parameters are a tuple (:data:`Params`) whose layout the model chooses.

    Attributes
    ----------
    result_type : type of Fit
        The dataclass a fit returns; a failed one is ``result_type(reason=...)``.
    min_points : int
        Fewest points, and fewest inliers, a fit needs.
    sample_size : int
        Points in a minimal sample (one RANSAC hypothesis).
    signed : bool
        Residuals are signed (the band's noise from their MAD) or distances (from their median,
        Rayleigh): see :func:`inlier_band`.
    presolve : bool
        A cloud of more than ``ransac_subsample`` points is first fitted whole (RANSAC and
        rounds) on a subsample; its inliers in the full cloud start the rounds.
    ransac_subsample : int
        RANSAC draws and scores hypotheses on at most this many points.
    max_rounds : int
        Most least-squares fits alternated with the inlier set.
    min_round_inliers : int
        An inlier update that would leave fewer points stops the rounds (the last set is kept).
    no_hypothesis : str
        The reason of a fit for which RANSAC found no hypothesis.
    """

    result_type: type[F]
    min_points: ClassVar[int]
    sample_size: ClassVar[int]
    signed: ClassVar[bool] = True
    presolve: ClassVar[bool] = False
    ransac_subsample: ClassVar[int] = RANSAC_SUBSAMPLE
    max_rounds: ClassVar[int] = MAX_ROUNDS
    min_round_inliers: ClassVar[int] = 0
    no_hypothesis: ClassVar[str] = "degenerate: RANSAC found no hypothesis"

    # ---------------------------------------------------------------- hypotheses (RANSAC)

    def check_cloud(self, points: NDArray) -> str:
        """Why the whole ``(N, 3)`` cloud cannot give a fit (checked before RANSAC), or ""."""
        return ""

    def sample_data(self, points: NDArray) -> NDArray:
        """The rows ``(N, k)`` RANSAC draws minimal samples from: the points themselves, or
        the points with more columns (e.g. their normals)."""
        return points

    def from_sample(self, sample: NDArray) -> Params | None:
        """Parameters from a minimal sample ``(sample_size, k)`` of :meth:`sample_data` rows,
        or None where the sample is degenerate."""
        raise NotImplementedError

    def hypotheses(self, points: NDArray) -> Callable[[NDArray], Params | None]:
        """RANSAC's estimator on ``points`` (N, 3): sample indices (sample_size,) to
        parameters, or None for a degenerate sample."""
        data = self.sample_data(points)
        return lambda idx: self.from_sample(data[idx])

    # ---------------------------------------------------------------- least squares

    def residuals(self, params: Params, points: NDArray) -> NDArray:
        """Residuals (N,) of ``(N, 3)`` points: signed distances, or distances if not
        ``signed``."""
        raise NotImplementedError

    def from_fit(self, fit: F) -> tuple[Params, NDArray]:
        """Parameters of a (presolved) fit and the residuals (M,) of its inliers that set the
        inlier band."""
        raise NotImplementedError

    def initial(self, points: NDArray, hint: Params | None, rng: np.random.Generator) -> Any:
        """Start of the rounds from the first inliers ``(M, 3)`` and the RANSAC (or presolved)
        parameters ``hint`` (None without RANSAC): parameters, None for no start (a
        closed-form :meth:`refine` needs none), or a reason (str) the fit fails."""
        return None

    def refine(self, points: NDArray, params: Any, rng: np.random.Generator) -> Params | str:
        """Least-squares parameters on the inliers ``(M, 3)`` from ``params`` (the previous
        round's, or :meth:`initial`'s), or a reason (str) the fit fails."""
        raise NotImplementedError

    # ---------------------------------------------------------------- results

    def result(self, params: Params, points: NDArray, mask: NDArray) -> F:
        """The fit of the last round's parameters on ``points[mask]`` (mask shape (N,))."""
        raise NotImplementedError

    def failure(self, reason: str) -> F:
        """A failed (falsy) fit saying why."""
        return self.result_type(reason=reason)

    def make(self, mask: NDArray, res: NDArray, cov: NDArray, **params: Any) -> F:
        """The result with inlier mask (N,), residuals (M,) and their RMS and range, the
        covariance (p, p) and the model's own fields."""
        rms, range_mm = residual_stats(res)
        return self.result_type(
            inliers=mask, residuals_mm=res, rms_mm=rms, range_mm=range_mm, cov=cov, **params
        )


class RadialModel(Model[F]):
    """A model with a radius, the last of its parameters (sphere, cylinder, circle).

    RANSAC keeps the hypotheses whose radius is within ``radius_range_mm`` (see
    :func:`radius_bounds`), and a big cloud is first fitted on a subsample (``presolve``).

    Parameters
    ----------
    radius_range_mm : (float, float), optional
        Radii a RANSAC hypothesis may have; without it, at most the cloud's extent.
    """

    presolve = True

    def __init__(self, radius_range_mm: tuple[float, float] | None = None) -> None:
        self.radius_range_mm = radius_range_mm

    def hypotheses(self, points: NDArray) -> Callable[[NDArray], Params | None]:
        estimate = super().hypotheses(points)
        lo, hi = radius_bounds(self.radius_range_mm, points)

        def bounded(idx: NDArray) -> Params | None:
            params = estimate(idx)
            return params if params is not None and lo <= params[-1] <= hi else None

        return bounded

    @staticmethod
    def radius_failure(
        finite: bool, radius: float, points: NDArray, limit: float, note: str
    ) -> str:
        """Why a radius is implausible for the ``(M, 3)`` inliers (non-finite parameters, or
        ``limit`` times their extent or more; ``note`` says what that means), or ""."""
        span = extent(points)
        if finite and radius < limit * span:
            return ""
        return f"degenerate: radius {radius:.4g} mm for points spanning {span:.4g} mm ({note})"


def check_threshold(threshold_mm: float | None) -> None:
    """Raise ValueError unless the threshold is None or a positive finite number."""
    if threshold_mm is not None and not (math.isfinite(threshold_mm) and threshold_mm > 0):
        raise ValueError(f"threshold_mm: expected a positive number or None, got {threshold_mm}")


def radius_bounds(radius_range_mm: tuple[float, float] | None, sub: NDArray) -> tuple[float, float]:
    """Radii a RANSAC hypothesis may have: the given range, else up to the extent of the
    sample ``sub`` (N, 3) (a sphere or cylinder much larger than the cloud is a plane in
    disguise)."""
    if radius_range_mm is None:
        return 0.0, extent(sub)
    lo, hi = (float(r) for r in radius_range_mm)
    if not (0 <= lo < hi and math.isfinite(hi)):
        raise ValueError(f"radius_range_mm: expected 0 <= min < max, got {radius_range_mm}")
    return lo, hi


def inlier_band(threshold_mm: float, residuals: NDArray, signed: bool = True) -> float:
    """Inlier band after RANSAC: the threshold, or :data:`BAND_SIGMAS` robust standard
    deviations of the current inliers' residuals (M,) when the noise is wider (a band narrower
    than the noise would clip the residuals and report the threshold as the form error).

    ``signed``: residuals are signed (MAD estimate); otherwise they are 2-D distances (line,
    circle), whose median is ``1.1774 sigma`` (Rayleigh).
    """
    r = np.asarray(residuals, dtype=np.float64)
    if r.size < 10:
        return threshold_mm
    if signed:
        sigma = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    else:
        sigma = float(np.median(np.abs(r))) / 1.1774
    return max(threshold_mm, BAND_SIGMAS * sigma)


def ransac(
    n: int,
    sample_size: int,
    estimate: Callable[[NDArray], Any],
    distances: Callable[[Any], NDArray],
    threshold: float,
    rng: np.random.Generator,
    max_iterations: int,
    confidence: float = 0.999,
) -> Any:
    """MSAC over ``n`` points: the hypothesis with the smallest sum of truncated squared
    distances, or None.

    Parameters
    ----------
    n, sample_size : int
        Points to draw from, and points in a minimal sample.
    estimate : callable
        Sample indices (sample_size,) to a hypothesis, or None for a degenerate sample.
    distances : callable
        A hypothesis to the non-negative distances (n,) of all points.
    threshold : float
        Inlier distance; larger distances cost ``threshold^2``.
    rng : Generator
        Draws the samples.
    max_iterations : int
        Most hypotheses; fewer once ``confidence`` is reached for the best inlier ratio.
    """
    best, best_cost = None, math.inf
    needed = max_iterations
    it = 0
    t2 = threshold * threshold
    while it < min(needed, max_iterations):
        it += 1
        idx = rng.choice(n, size=sample_size, replace=False)
        model = estimate(idx)
        if model is None:
            continue
        d = distances(model)
        if not np.all(np.isfinite(d)):
            continue
        cost = float(np.minimum(d * d, t2).sum())
        if cost < best_cost:
            best, best_cost = model, cost
            w = float(np.count_nonzero(d < threshold)) / n
            if w >= 1.0:
                needed = it
            elif w > 0:
                denom = math.log(max(1e-300, 1.0 - w**sample_size))
                if denom < 0:
                    needed = min(needed, math.ceil(math.log(1.0 - confidence) / denom))
    log.debug("RANSAC: %d iterations, cost %.4g", it, best_cost)
    return best


def robust_fit(
    model: Model[F],
    points: NDArray,
    threshold_mm: float | None = None,
    *,
    seed: SeedLike = 0,
    max_iterations: int = 1000,
    start: F | None = None,
) -> F:
    """Fit ``model`` to ``points`` by least squares, after RANSAC when ``threshold_mm`` is
    given (see the module's description).

    Parameters
    ----------
    model : Model
        The primitive, with its options (e.g. the radius range).
    points : ndarray, shape (N, 3)
        Points, mm, float64 and finite (as :func:`scanner.core.conventions.check_points`
        returns them).
    threshold_mm : float, optional
        RANSAC inlier distance; without it every point is an inlier.
    seed : int or Generator
        Seeds RANSAC and the subsamples (a fit is repeatable).
    max_iterations : int
        Most RANSAC hypotheses.
    start : Fit, optional
        A fit of nearly the same points (without RANSAC) to start the least squares from,
        instead of the closed-form or searched start: refitting slightly moved points.

    Returns
    -------
    Fit
        ``model.result_type``: the fit, or a failed fit (falsy) whose ``reason`` says why.
    """
    check_threshold(threshold_mm)
    n = len(points)
    if n < model.min_points:
        return model.failure(f"too few points: expected at least {model.min_points}, got {n}")
    reason = model.check_cloud(points)
    if reason:
        return model.failure(reason)
    rng = rng_from(seed)
    mask, hint = np.ones(n, dtype=bool), None
    if start is not None and start and hasattr(model, "from_fit"):
        hint = model.from_fit(start)[0]
    if threshold_mm is not None:
        detected = _detect(model, points, threshold_mm, rng, max_iterations)
        if isinstance(detected, Fit):
            return detected
        mask, hint = detected
    return _rounds(model, points, mask, hint, threshold_mm, rng)


def _detect(
    model: Model[F],
    points: NDArray,
    threshold_mm: float,
    rng: np.random.Generator,
    max_iterations: int,
) -> F | tuple[NDArray, Params]:
    """Step 1: the first inlier mask (N,) and the parameters it came from, or a failed fit."""
    n = len(points)
    sub = points[subsample(n, model.ransac_subsample, rng)]
    if model.presolve and n > model.ransac_subsample:
        pre = robust_fit(model, sub, threshold_mm, seed=rng, max_iterations=max_iterations)
        if not pre:
            return pre
        params, res = model.from_fit(pre)
        band = inlier_band(threshold_mm, res, signed=model.signed)
    else:
        params = ransac(
            len(sub), model.sample_size, model.hypotheses(sub),
            lambda m: np.abs(model.residuals(m, sub)), threshold_mm, rng, max_iterations,
        )  # fmt: skip
        if params is None:
            return model.failure(model.no_hypothesis)
        band = threshold_mm
    return np.abs(model.residuals(params, points)) < band, params


def _rounds(
    model: Model[F],
    points: NDArray,
    mask: NDArray,
    hint: Params | None,
    threshold_mm: float | None,
    rng: np.random.Generator,
) -> F:
    """Steps 2 and 3: least squares alternated with the inlier mask (N,), then the result."""
    rounds = model.max_rounds if threshold_mm is not None else 1
    params: Any = None
    for rnd in range(rounds):
        count = int(np.count_nonzero(mask))
        if count < model.min_points:
            return model.failure(
                f"too few inliers: expected at least {model.min_points}, got {count}"
            )
        inl = take(points, mask)
        if rnd == 0:
            params = model.initial(inl, hint, rng)
            if isinstance(params, str):
                return model.failure(params)
        params = model.refine(inl, params, rng)
        if isinstance(params, str):
            return model.failure(params)
        if threshold_mm is None or rnd == rounds - 1:
            break  # (on the last round keep the mask the parameters belong to)
        dist = model.residuals(params, points)
        new = np.abs(dist) < inlier_band(threshold_mm, dist[mask], signed=model.signed)
        if np.array_equal(new, mask) or np.count_nonzero(new) < model.min_round_inliers:
            break
        mask = new
    return model.result(params, points, mask)
