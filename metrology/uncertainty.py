"""The combined standard uncertainty of each measured value, with its budget (GUM).

A measured value (a diameter, a distance, a flatness) comes from features fitted to cloud
points; the points come from stripe pixels, a calibration and robot stops. Each source of
error is carried through the same fits that made the value, with the same points:

- **calibration**: the calibration file's covariance (``covariance`` key), linearised along
  its principal directions: each one-sigma direction re-triangulates the points from their
  own pixels and stops, the features follow, and the value's changes add in
  quadrature (exact for a value linear in the calibration over its sigma, which the small
  corrections are);
- **robot repeatability**: every stop missed by an independent random motion of the flange
  (the calibration's estimate of the robot's repeatability), by Monte Carlo;
- **stripe noise and the fit**: a wild bootstrap of the fits' residuals that flips the sign of
  all residuals of one stop together, so that the noise's correlation along a profile (one
  stop's stripe shares its exposure, speckle and pose) is kept instead of assumed away;
- **the instrument's verified errors** (the plan's ``instrument``: PS for diameters, SD for
  distances), type B; the bound holds the sources above, so only what they leave of it is
  added.

The features follow each draw to first order (:mod:`metrology.fits.linear`) instead of being
fitted again.

``u`` is the root sum of squares; ``U = k u`` with ``k = 2``. What could not be included is
named (for example a cloud without its stops: no calibration or robot share).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from metrology.budget import COVERAGE_FACTOR, Contribution, Uncertainty
from metrology.fits import CylinderFit, Fit, PlaneFit, SphereFit
from metrology.fits.linear import LinearisedFit, linearise
from metrology.measure import MeasurementReport, evaluate_measurement, fit_feature
from scanner.core.tolerance import STATUS_NOT_PROVEN, STATUS_PASS
from scanner.scanning.geometry import ScanGeometry

__all__ = [
    "UncertaintyConfig",
    "attach_uncertainties",
    "deviation_calibration_share",
    "measurement_uncertainties",
]


@dataclass(frozen=True)
class UncertaintyConfig:
    """How the budget is evaluated.

    Attributes
    ----------
    draws : int
        Bootstrap draws of the noise.
    robot_draws : int
        Monte Carlo draws of the robot's misses (a few ms each: 64 give its u within about
        9 %, one sigma; 16 within 18 %).
    seed : int
        Seed of every draw and sample (a report is reproducible).
    systematic_points : int
        The calibration's share moves the points smoothly: the features are fitted again to
        at most this many of their points, evenly spread over the stops (the noise share
        takes them all). A smooth move of 500 points of a feature gives its change within a
        few per cent of all of them.
    robot_points : int
        The robot's share moves each stop by its own miss, which a small sample of a stop's
        points overstates: at most this many of a feature's points, evenly spread over its
        stops (5000 gives the share of all points within the Monte Carlo's own scatter).
    linearised : bool
        Move planes, spheres and cylinders to first order in their points' moves
        (:mod:`metrology.fits.linear`) instead of fitting them again in every draw; the same
        budget (``tests/metrology/test_uncertainty.py``) at about a third of the cost.
    """

    draws: int = 16
    seed: int = 0
    systematic_points: int = 500
    robot_points: int = 5000
    robot_draws: int = 64
    linearised: bool = True

    def __post_init__(self) -> None:
        if self.draws < 4:
            raise ValueError(f"uncertainty draws: expected at least 4, got {self.draws}")
        if self.robot_draws < 4:
            raise ValueError(f"robot draws: expected at least 4, got {self.robot_draws}")
        if min(self.systematic_points, self.robot_points) < 1:
            raise ValueError(
                "uncertainty sample sizes: expected at least 1 point, got "
                f"{self.systematic_points} and {self.robot_points}"
            )


#: Degrees of freedom of each linearised surface (its parameters).
_DEGREES: dict[type, int] = {PlaneFit: 3, SphereFit: 4, CylinderFit: 5}


@dataclass
class _Features:
    """The fitted features a plan's measurements use: their specs, inlier indices, fits."""

    specs: dict[str, Any]
    indices: dict[str, NDArray]
    fits: dict[str, Fit] = field(default_factory=dict)


def _even_sample(idx: NDArray, n: int, stop: NDArray | None, rng: np.random.Generator) -> NDArray:
    """At most ``n`` of the point indices ``idx`` ``(M,)``, sorted: every ``M / n``-th in the
    order of their stops (``stop`` ``(N,)``, a point's stop; None: the order of ``idx``), from
    a random start, so that each stop keeps its share of the points to within one.

    A random draw gives each stop a multinomial count instead, and whole stops moved
    independently (the robot's misses) then move a fit by more than all its points would.
    """
    if len(idx) <= n:
        return idx
    order = idx if stop is None else idx[np.lexsort((idx, stop[idx]))]
    step = len(idx) / n
    picks = np.floor(rng.uniform(0.0, step) + step * np.arange(n)).astype(np.int64)
    return np.sort(order[np.minimum(picks, len(idx) - 1)])


def _residual_normals(fit: Fit, points: NDArray) -> tuple[NDArray, NDArray] | None:
    """``(residuals (M,), unit directions (M, 3))``: ``points - r n`` lie on the fitted surface."""
    if isinstance(fit, SphereFit):
        q = points - fit.center_mm
        dist = np.linalg.norm(q, axis=1)
        return dist - fit.radius_mm, q / dist[:, None]
    if isinstance(fit, PlaneFit):
        return points @ fit.normal + fit.d_mm, np.broadcast_to(fit.normal, points.shape)
    if isinstance(fit, CylinderFit):
        q = points - fit.point_mm
        radial = q - np.outer(q @ fit.axis, fit.axis)
        dist = np.linalg.norm(radial, axis=1)
        return dist - fit.radius_mm, radial / dist[:, None]
    return None


def noise_range_p95(
    residuals: NDArray,
    points: NDArray,
    rng: np.random.Generator,
    scale_mm: tuple[float, float] = (1.0, 3.0),
    draws: int = 2000,
    max_points: int = 8000,
    max_pairs: int = 100_000,
) -> float | None:
    """The 95th percentile of the range of ``len(residuals)`` samples of the noise alone.

    The noise is told from the form by its scale: between points ``scale_mm`` apart (beyond
    the stripe noise's own correlation along a profile, well under a form's wavelength) a
    smooth form hardly changes, so ``(r[j] - r[i]) / sqrt(2)`` samples the noise only,
    profile-to-profile offsets included. The ranges of draws of ``n`` values from that sample
    give the distribution of the range a perfect feature would show; each draw's largest and
    smallest value are drawn directly from their order statistics (the largest of ``n`` draws
    from ``m`` sorted values has index ``ceil(m U^(1/n)) - 1``), taken as independent, which
    they are for the ``n`` of a feature. Form on scales under ``scale_mm[1]`` is taken for
    noise.

    Returns None when fewer than 30 such pairs are found.
    """
    n = len(residuals)
    sub = rng.choice(n, min(n, max_points), replace=False)
    near = points[sub]
    pairs = cKDTree(near).query_pairs(scale_mm[1], output_type="ndarray")
    if len(pairs) > max_pairs:  # a dense patch: plenty of noise samples from fewer pairs
        pairs = pairs[rng.integers(0, len(pairs), max_pairs)]
    if len(pairs):
        step = near[pairs[:, 0]] - near[pairs[:, 1]]
        pairs = pairs[np.einsum("ij,ij->i", step, step) >= scale_mm[0] ** 2]
    if len(pairs) < 30:
        return None
    r = residuals[sub]
    noise = np.sort((r[pairs[:, 0]] - r[pairs[:, 1]]) / math.sqrt(2.0))
    m = len(noise)
    top = np.ceil(m * rng.uniform(size=draws) ** (1.0 / n)).astype(np.int64) - 1
    bottom = m - np.ceil(m * rng.uniform(size=draws) ** (1.0 / n)).astype(np.int64)
    # (independent extremes can cross for a tiny n: a range is never negative)
    ranges = np.maximum(noise[np.clip(top, 0, m - 1)] - noise[np.clip(bottom, 0, m - 1)], 0.0)
    return float(np.quantile(ranges, 0.95))


def _values(
    report: MeasurementReport,
    features: _Features,
    moves: dict[str, NDArray | Fit],
    linear: dict[str, LinearisedFit | None] | None = None,
) -> NDArray:
    """Every measurement's value with its features fitted again to moved points.

    ``moves`` holds, by feature name, its points moved ``(M, 3)``, or, for a feature with a
    linearisation in ``linear``, the changes of its residuals along the normals ``(M,)``, or
    the feature's fit already updated. A feature with a linearisation (made at the same
    points, unmoved) is updated to first order instead of refitted. A minimum-zone form is not solved again: its
    change is taken as the change of the least-squares range (the linear programme would cost
    more than all the rest).
    """
    fits = dict(features.fits)
    for name, pts in moves.items():
        if isinstance(pts, Fit):
            fits[name] = pts
            continue
        lin = None if linear is None else linear.get(name)
        if lin is not None:
            fits[name] = lin.shifted(pts) if pts.ndim == 1 else lin.moved(pts)
            continue
        fit = fit_feature(features.specs[name], pts, None, start=features.fits[name])
        ref = features.fits[name]
        if fit and ref.min_zone_mm is not None:
            fit = dataclasses.replace(
                fit, min_zone_mm=ref.min_zone_mm + fit.range_mm - ref.range_mm
            )
        fits[name] = fit
    out = []
    for m in report.measurements:
        if any(name not in fits for name in m.spec.features):
            out.append(math.nan)
            continue
        row = evaluate_measurement(m.spec, fits)
        out.append(math.nan if row.actual is None else float(row.actual))
    return np.asarray(out, dtype=np.float64)


def measurement_uncertainties(
    report: MeasurementReport,
    geometry: ScanGeometry | None,
    config: UncertaintyConfig | None = None,
    not_included: tuple[str, ...] = (),
) -> list[Uncertainty | None]:
    """The uncertainty of each of ``report``'s measurements (None where it has no value).

    Parameters
    ----------
    report : MeasurementReport
        Its features' fits and inliers are the starting point; the cloud is its points.
    geometry : ScanGeometry or None
        Each point's stop and the calibration (with its ``covariance``); ``None`` when the
        cloud's origin is not known: only the noise share, with independent points.
    config : UncertaintyConfig, optional
    not_included : tuple of str
        Sources the caller knows are missing (named in every result).

    Returns
    -------
    list of Uncertainty or None, one per measurement
    """
    config = config or UncertaintyConfig()
    rng = np.random.default_rng(config.seed)
    # the samples' starts from their own stream: a sample's size leaves the draws as they are
    sampling = np.random.default_rng([config.seed, 1])
    used = {name for m in report.measurements for name in m.spec.features}
    ok = [f for f in report.features if f.spec.name in used and f.ok]
    feats = _Features(
        specs={f.spec.name: dataclasses.replace(f.spec, seed=0, min_zone=False) for f in ok},
        indices={f.spec.name: f.inlier_indices for f in ok},
        fits={f.spec.name: f.fit for f in report.features},
    )
    if not feats.indices:  # no feature a measurement uses was fitted: no value to qualify
        return [None] * len(report.measurements)
    cloud = report.points_base
    base_points = {name: cloud[idx] for name, idx in feats.indices.items()}
    budget: list[list[Contribution]] = [[] for _ in report.measurements]
    missing = list(not_included)
    # what is missing for one measurement only (refits that failed)
    own_missing: list[list[str]] = [[] for _ in report.measurements]

    def add(source: str, method: str, deltas: NDArray) -> None:
        """``deltas`` (draws, measurements) of values from the reference, NaN where a refit
        failed: the source counts from the draws that worked when they are most of them, and
        is named as missing otherwise."""
        for i, row in enumerate(budget):
            d = deltas[:, i]
            ok = np.isfinite(d)
            if ok.all():
                row.append(Contribution(source, float(np.sqrt(np.mean(d**2))), method))
            elif ok.sum() >= max(3, 0.75 * len(d)):
                rms = float(np.sqrt(np.mean(d[ok] ** 2) * len(d) / ok.sum()))
                row.append(
                    Contribution(source, rms, f"{method}; {len(d) - ok.sum()} refits failed")
                )
            else:
                own_missing[i].append(f"{source} ({len(d) - ok.sum()} of {len(d)} refits failed)")

    def spread(
        draw: Callable[[], dict[str, NDArray | Fit]],
        linear: dict[str, LinearisedFit | None] | None,
        draws: int = config.draws,
    ) -> NDArray:
        """Sample deviations (draws, measurements), scaled so that their RMS is the std."""
        vals = np.array([_values(report, feats, draw(), linear) for _ in range(draws)])
        return (vals - np.nanmean(vals, axis=0)) * math.sqrt(draws / (draws - 1))

    # calibration
    covariance = None if geometry is None else geometry.calibration.covariance
    stops = None if geometry is None else geometry.frame_index
    sample = {
        n: _even_sample(idx, config.systematic_points, stops, sampling)
        for n, idx in feats.indices.items()
    }

    def linearised(points: dict[str, NDArray]) -> dict[str, LinearisedFit | None] | None:
        if not config.linearised:
            return None
        return {n: linearise(feats.fits[n], pts) for n, pts in points.items()}

    linear_all = linearised(base_points)
    # the sampled points of all features in one array (one call per draw for all of them)
    names = list(sample)
    all_idx = np.concatenate([sample[n] for n in names]) if names else np.zeros(0, np.int64)
    ends = np.cumsum([len(sample[n]) for n in names])[:-1]
    linear_sample = linearised({n: cloud[idx] for n, idx in sample.items()})
    reference = _values(report, feats, base_points, linear_all)
    if geometry is None:
        missing.append("calibration (the cloud's stops are not known)")
    elif covariance is None:
        missing.append("calibration (the calibration file has no covariance)")
    else:
        as_is, moves = geometry.calibration_moves(cloud, all_idx)  # one call for all features

        def triangulated(move: NDArray) -> dict[str, NDArray]:
            return dict(zip(names, np.split(as_is + move, ends), strict=True))

        zero = _values(report, feats, triangulated(np.zeros(3)), linear_sample)
        deltas = np.array(
            [_values(report, feats, triangulated(m), linear_sample) - zero for m in moves]
        )
        if len(moves):
            # sum of squares over the directions: scale the RMS by sqrt(M)
            add(
                "calibration",
                f"linearised over {len(moves)} principal directions of the calibration's "
                "covariance",
                deltas * math.sqrt(len(moves)),
            )
        else:
            missing.append("calibration (its covariance is zero)")

    # Errors of one stop (the robot's miss, the exposure's noise and speckle along the
    # profile) show in the fits' residuals: a wild bootstrap that flips the sign of all
    # residuals of a stop together (one sign per stop for every feature) sees them all. The
    # robot's share of it is shown from the repeatability model, by Monte Carlo.
    flips: dict[str, tuple[NDArray, NDArray, NDArray, float]] = {}
    n_clusters = len(cloud) if geometry is None else len(geometry.base_from_flange)
    for name, idx in feats.indices.items():
        rn = _residual_normals(feats.fits[name], base_points[name])
        if rn is None:
            missing.append(f"stripe noise of {name} (no residual direction for its kind)")
            continue
        cluster = np.asarray(idx if geometry is None else geometry.frame_index[idx])
        # A fit's residuals are smaller than the errors that made them: the fit absorbed p of
        # the G clusters' worth of freedom. Residuals scaled by sqrt(G / (G - p)) restore the
        # errors' size (a cluster-level degrees-of-freedom correction); for a sphere seen by
        # 25 stops that is 9 %. Seen from p stops or fewer, nothing is left to resample.
        n_groups = len(np.unique(cluster))
        degrees = _DEGREES.get(type(feats.fits[name]), 0)
        if n_groups <= degrees:
            missing.append(f"stripe noise of {name} (seen from {n_groups} stops only)")
            continue
        inflate = math.sqrt(n_groups / (n_groups - degrees))
        flips[name] = (rn[0][:, None] * rn[1], cluster, base_points[name], inflate)

    # a linearised feature's response to whole stops flipping, in sums over its stops
    grouped = {
        name: lin.groups(flips[name][1])
        for name, lin in (linear_all or {}).items()
        if lin is not None and name in flips
    }

    def noise_draw() -> dict[str, NDArray | Fit]:
        out: dict[str, NDArray | Fit] = dict(base_points)
        sign = rng.choice([-1.0, 1.0], size=n_clusters)
        for name, (offset, cluster, pts, inflate) in flips.items():
            # each residual r becomes s c r: the points move by (s c - 1) r along the normal
            if name in grouped:
                out[name] = grouped[name].flipped(sign, inflate)
            else:
                out[name] = pts + (sign[cluster] * inflate - 1.0)[:, None] * offset
        return out

    robot_dev = None
    robot_method = ""
    if (
        geometry is not None
        and covariance is not None
        and (covariance.robot_rotation_deg > 0 or covariance.robot_translation_mm > 0)
    ):
        n_stops = len(geometry.base_from_flange)
        sr = math.radians(covariance.robot_rotation_deg)
        st = covariance.robot_translation_mm
        # Misses drawn stop by stop move a small sample's fit by more than the whole's: on a
        # randomised cell's spheres the robot's u from 500 random points came out 21-57 %
        # above all points' own (128 draws), from 500 even ones 8-11 % (256). So a larger even
        # sample: all of a sphere's points on the virtual cells, a table's spread over its
        # stops.
        # (refitted features, without the first-order update, keep the smaller sample)
        most = config.robot_points if config.linearised else config.systematic_points
        robot_idx = {n: _even_sample(feats.indices[n], most, stops, sampling) for n in names}
        robot_all = np.concatenate([robot_idx[n] for n in names] or [np.zeros(0, np.int64)])
        robot_ends = np.cumsum([len(robot_idx[n]) for n in names])[:-1]
        linear_robot = linearised({n: cloud[idx] for n, idx in robot_idx.items()})

        def robot_draw() -> dict[str, NDArray]:
            rv = rng.normal(0.0, sr, (n_stops, 3))
            tv = rng.normal(0.0, st, (n_stops, 3))
            moved = geometry.pose_moved(cloud, robot_all, rv, tv)
            return dict(zip(names, np.split(moved, robot_ends), strict=True))

        robot_dev = spread(robot_draw, linear_robot, config.robot_draws)
        robot_method = (
            f"Monte Carlo, {config.robot_draws} draws of independent misses per stop "
            f"({covariance.robot_rotation_deg:.4f} deg, {covariance.robot_translation_mm:.4f} mm "
            "per axis): part of the stop-clustered bootstrap, and its floor"
        )
    elif geometry is None or covariance is None:
        missing.append("robot repeatability (not known; points of one stop taken as independent)")
    if flips:
        clusters = "stops" if geometry is not None else "points (stops not known)"
        boot = spread(noise_draw, linear_all)
        method = (
            f"wild bootstrap of the residuals scaled by sqrt(G / (G - p)), {config.draws} draws, "
            f"clustered by {clusters}"
        )
        if robot_dev is None:
            add("stripe noise and fit", method, boot)
        else:
            # The bootstrap already holds the robot's misses: split, never add. With the few
            # stops a feature is seen from it can come out below the robot's share alone, which
            # the calibration knows: the errors of a stop are never taken as smaller than that
            # (on the modern cell this floor took the spacing's coverage from 89 % to 93 %).
            robot = np.sqrt(np.nanmean(robot_dev**2, axis=0))
            known = np.where(np.isfinite(robot), robot, 0.0)  # a failed robot share: no floor
            total = np.fmax(np.sqrt(np.nanmean(boot**2, axis=0)), known)
            rest = np.sqrt(np.maximum(total**2 - known**2, 0.0))
            add(
                "robot repeatability", robot_method, np.where(np.isfinite(robot_dev), robot, np.nan)
            )
            add(
                "stripe noise and fit",
                f"{method}, less the robot's share (the errors of a stop at least the robot's)",
                np.where(np.isfinite(boot), rest, np.nan),
            )
    elif robot_dev is not None:
        add("robot repeatability", robot_method, robot_dev)

    # a range (flatness, form) holds the noise's own range: a one-sided error no refit shows
    for i, m in enumerate(report.measurements):
        if m.spec.type not in ("flatness", "form") or m.spec.features[0] not in flips:
            continue
        name = m.spec.features[0]
        residuals, _ = _residual_normals(feats.fits[name], base_points[name])  # type: ignore[misc]
        upper = noise_range_p95(residuals, base_points[name], rng)
        if upper is not None:
            budget[i].append(
                Contribution(
                    "noise in the range",
                    upper / COVERAGE_FACTOR,
                    "95th percentile of the range of the noise alone (residual differences "
                    "of points 1-3 mm apart), as U",
                )
            )

    # The sensor's own biases on curved surfaces, as its verification measured them (type B).
    # Its bound holds the modelled sources too: the combined u is the larger of the two.
    inst = report.plan.instrument
    for i, m in enumerate(report.measurements):
        figure = {
            "diameter": ("probing_size_mm", "size"),
            "distance": ("sphere_spacing_mm", "length"),
        }
        if m.spec.type not in figure:
            continue
        key, what = figure[m.spec.type]
        value = getattr(inst, key)
        if value is None:
            own_missing[i].append(
                f"the instrument's {what} error (no instrument.{key} in the plan)"
            )
            continue
        # The verification bounds the instrument's whole error on such a value, the sources
        # above (calibration, robot, stripe noise) included: only the part of it they do not
        # explain is added, never the bound on top of them (that would count them twice).
        bound = value / math.sqrt(3.0)
        modelled = math.sqrt(sum(c.u**2 for c in budget[i]))
        budget[i].append(
            Contribution(
                f"instrument ({what} error)",
                math.sqrt(max(bound**2 - modelled**2, 0.0)),
                f"type B: +-{value:g} mm from the sensor's verification (plan instrument.{key}), "
                f"rectangular (u {bound:.4f} mm), less the sources above that it includes",
            )
        )

    results: list[Uncertainty | None] = []
    for value, row, own in zip(reference, budget, own_missing):
        if not math.isfinite(value) or not row:
            results.append(None)
            continue
        u = float(np.sqrt(sum(c.u**2 for c in row)))
        results.append(Uncertainty(u, tuple(row), not_included=(*missing, *own)))
    return results


def attach_uncertainties(
    report: MeasurementReport, uncertainties: list[Uncertainty | None]
) -> MeasurementReport:
    """``report`` with each measurement's uncertainty in its row (``u``, ``U``) and record;
    the rows' statuses then follow the plan's decision rule with that ``U``. Under guarded
    acceptance a ``U`` that misses a source (``not_included``) cannot prove conformity: such
    a row that would pass is ``not proven``, with the reason in its note."""
    if len(uncertainties) != len(report.measurements):
        raise ValueError(
            f"uncertainties: expected {len(report.measurements)}, got {len(uncertainties)}"
        )
    measurements = []
    for m, u in zip(report.measurements, uncertainties):
        if u is None:
            measurements.append(m)
            continue
        row = dataclasses.replace(m.row, u=u.u, U=u.U)
        if row.rule == "guarded" and u.not_included and row.final_status == STATUS_PASS:
            note = f"U incomplete: {'; '.join(u.not_included)}"
            row = dataclasses.replace(
                row, status=STATUS_NOT_PROVEN, note=f"{row.note}; {note}" if row.note else note
            )
        measurements.append(dataclasses.replace(m, row=row, uncertainty=u))
    return dataclasses.replace(report, measurements=measurements)


def deviation_calibration_share(
    geometry: ScanGeometry,
    points_cloud: NDArray,
    normals_cloud: NDArray,
    which: NDArray,
    max_points: int = 2000,
    seed: int = 0,
) -> tuple[float | None, str]:
    """The calibration's share of a point's deviation from a nominal surface it was aligned to.

    Each one-sigma principal direction of the calibration's covariance re-triangulates the
    points from their pixels; a point's deviation moves by ``n . dp``. The alignment to the
    nominal (a best fit) takes up the rigid part of those moves, so only what a rigid motion
    about the points' centre cannot explain is kept; the changes add in quadrature over the
    directions. The stripe noise and the robot's misses are not here: they are in the points'
    spread around the nominal already.

    Parameters
    ----------
    geometry : ScanGeometry
        Each point's stop and the calibration (with its ``covariance``).
    points_cloud : ndarray, shape (N, 3)
        The cloud as scanned (base frame), mm.
    normals_cloud : ndarray, shape (N, 3)
        The nominal's unit normal at each point's closest point, in the cloud's frame.
    which : ndarray of int
        The points to evaluate (for example those within the outlier limit).
    max_points : int
        At most this many of them, drawn at random (the share is smooth over the part).
    seed : int

    Returns
    -------
    (u, reason)
        The 95th percentile over the points of the one-sigma change, mm, and ``""``; or
        ``None`` and why it could not be given.
    """
    covariance = geometry.calibration.covariance
    if covariance is None:
        return None, "calibration (the calibration file has no covariance)"
    which = np.asarray(which)
    if len(which) > max_points:
        which = np.sort(np.random.default_rng(seed).choice(which, max_points, replace=False))
    if len(which) < 10:
        return None, f"calibration (only {len(which)} points to evaluate)"
    _, moves = geometry.calibration_moves(points_cloud, which)
    if not len(moves):
        return None, "calibration (its covariance is zero)"
    p = points_cloud[which]
    n = normals_cloud[which]
    # the alignment's first-order response: a small rotation w and shift t about the centre
    # move a deviation by n . (w x (p - c) + t)
    rigid = np.hstack([np.cross(p - p.mean(axis=0), n), n])
    total = np.zeros(len(which))
    for move in moves:
        change = np.einsum("ij,ij->i", n, move)
        taken, *_ = np.linalg.lstsq(rigid, change, rcond=None)
        total += (change - rigid @ taken) ** 2
    return float(np.quantile(np.sqrt(total), 0.95)), ""
