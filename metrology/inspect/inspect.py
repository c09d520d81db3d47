"""The whole scan-to-CAD inspection of one cloud: align, measure every point, judge.

>>> result = inspect_cloud(points_base, read_mesh("part.stl"), load_inspection_spec(spec))
>>> result.verdict, result.stats.rms, result.alignment.rms_mm
"""

from __future__ import annotations

import time

import numpy as np
from numpy.typing import NDArray

from metrology.fits.primitives import fit_plane
from metrology.inspect.align import AlignOptions, apply, best_fit, rps_frame
from metrology.inspect.result import (
    AlignmentResult,
    DeviationStats,
    InspectionResult,
    InspectionUncertainty,
    RegionResult,
)
from metrology.inspect.spec import DatumSpec, InspectionRegion, InspectionSpec
from metrology.inspect.surface import NominalSurface
from metrology.uncertainty import deviation_calibration_share
from scanner.formats.meshes import TriangleMesh
from scanner.scanning.geometry import ScanGeometry

__all__ = ["AlignmentFailed", "inspect_cloud", "judge_regions"]

#: Fewest points an inspection works with.
MIN_POINTS = 100


class AlignmentFailed(ValueError):
    """The cloud could not be aligned to the nominal (the message says why)."""


def _check_points(points_cloud: NDArray) -> NDArray[np.float64]:
    p = np.asarray(points_cloud, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < MIN_POINTS:
        raise ValueError(f"cloud: expected (N, 3) with N >= {MIN_POINTS}, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("cloud: expected finite coordinates, got NaN or inf")
    return p


def _rps(
    points_cloud: NDArray, surface: NominalSurface, coarse: AlignmentResult, spec: InspectionSpec
) -> AlignmentResult:
    """3-2-1 alignment on the spec's datum planes, starting from the best-fit's pose."""
    pose = coarse.nominal_from_cloud
    moved = apply(pose, points_cloud)
    near = surface.closest(moved)
    sampled, sampled_normals = surface.sample(60_000, np.random.default_rng(spec.alignment.seed))
    nominal_planes, measured_planes = [], []
    for i, datum in enumerate(spec.alignment.datums):
        measured = _datum_plane(moved, datum.region.select(moved, near.normals), datum, i, "scan")
        nominal = _datum_plane(
            sampled, datum.region.select(sampled, sampled_normals), datum, i, "nominal"
        )
        if measured[0] @ nominal[0] < 0:
            measured = (-measured[0], measured[1])
        nominal_planes.append(nominal)
        measured_planes.append(measured)
    try:
        correction = rps_frame(nominal_planes) @ np.linalg.inv(rps_frame(measured_planes))
    except np.linalg.LinAlgError:
        raise AlignmentFailed(
            "rps: the three datum planes do not meet in one point (parallel normals)"
        ) from None
    final = correction @ pose
    r = surface.closest(apply(final, points_cloud)).signed_mm
    inside = np.abs(r) < 0.5
    return AlignmentResult(
        nominal_from_cloud=final,
        method="rps 3-2-1 on datum planes (after a best-fit)",
        rms_mm=float(np.sqrt(np.mean(r[inside] ** 2))) if np.any(inside) else float("nan"),
        points_used=int(np.count_nonzero(inside)),
        iterations=coarse.iterations,
        converged=coarse.converged,
        pose_u_mm=coarse.pose_u_mm,
        covariance=coarse.covariance,
        candidates=coarse.candidates,
        runner_up_rms_mm=coarse.runner_up_rms_mm,
        ambiguous=coarse.ambiguous,
        warnings=coarse.warnings,
    )


def _datum_plane(
    points: NDArray, mask: NDArray, datum: DatumSpec, index: int, what: str
) -> tuple[NDArray, NDArray]:
    if np.count_nonzero(mask) < 10:
        raise AlignmentFailed(
            f"rps datum {index} ({datum.region.name}): {np.count_nonzero(mask)} {what} points "
            "in its region, expected at least 10"
        )
    fit = fit_plane(points[mask], threshold_mm=0.2)
    if not fit:
        raise AlignmentFailed(f"rps datum {index} ({datum.region.name}): {fit.reason}")
    return np.asarray(fit.normal), np.asarray(fit.centroid_mm)


def judge_regions(
    spec: InspectionSpec,
    points_nominal: NDArray,
    face_normals: NDArray,
    deviation_mm: NDArray,
    outlier: NDArray,
) -> list[RegionResult]:
    """``"all"`` on the global band, then each of the spec's regions on its own band."""
    everything = InspectionRegion(
        "all",
        box_min_mm=(-1e9, -1e9, -1e9),
        box_max_mm=(1e9, 1e9, 1e9),
    )
    results = []
    for region in (everything, *spec.regions):
        mask = (
            np.ones(len(deviation_mm), bool)
            if region is everything
            else region.select(points_nominal, face_normals)
        )
        judged = mask & ~outlier
        lower, upper = spec.band_of(region)
        d = deviation_mm[judged]
        share = float(np.mean((d >= lower) & (d <= upper))) if d.size else float("nan")
        status = "no points" if d.size == 0 else (
            "pass" if share >= spec.min_share_in_band else "fail"
        )  # fmt: skip
        results.append(
            RegionResult(
                name=region.name,
                description="every point" if region is everything else region.describe(),
                lower_mm=lower,
                upper_mm=upper,
                stats=DeviationStats.of(d),
                share_in_band=share,
                status=status,
                outliers=int(np.count_nonzero(mask & outlier)),
            )
        )
    return results


def _uncertainty(
    alignment: AlignmentResult,
    points_nominal: NDArray,
    normals: NDArray,
    deviation: NDArray,
    calibration: tuple[float | None, str] = (None, ""),
) -> InspectionUncertainty:
    """1-sigma of a point's deviation: the cloud's noise, the pose's covariance and the
    calibration's share ``(u or None, why not)``."""
    noise = 1.4826 * float(np.median(np.abs(deviation - np.median(deviation))))
    cal_u, why = calibration
    missing = () if cal_u is not None else (why or "calibration (the cloud's stops not known)",)
    cov = alignment.covariance
    if not np.all(np.isfinite(cov)):
        return InspectionUncertainty(
            noise, float("nan"), float("nan"), calibration_mm=cal_u, not_included=missing
        )
    step = max(1, len(points_nominal) // 20_000)
    p, n = points_nominal[::step], normals[::step]
    centre = p.mean(axis=0)
    # A small motion (w, t) about the fit's centre moves a point's deviation by n.(w x (p - c) + t).
    j = np.hstack([np.cross(p - centre, n), n])
    align = float(np.sqrt(np.max(np.einsum("ij,jk,ik->i", j, cov, j))))
    combined = float(np.sqrt(noise**2 + align**2 + (cal_u or 0.0) ** 2))
    return InspectionUncertainty(noise, align, combined, calibration_mm=cal_u, not_included=missing)


def inspect_cloud(
    points_cloud: NDArray,
    nominal: TriangleMesh,
    spec: InspectionSpec,
    *,
    options: AlignOptions | None = None,
    geometry: ScanGeometry | None = None,
    geometry_missing: str = "",
) -> InspectionResult:
    """Align ``points_cloud`` to ``nominal`` without a guess and judge every point's deviation.

    Parameters
    ----------
    points_cloud : ndarray, shape (N, 3)
        The scan in any frame, mm (N >= 100).
    nominal : TriangleMesh
        The CAD surface in the part's frame, mm, outward normals.
    spec : InspectionSpec
        Bands, regions, sections and the alignment method.
    options : AlignOptions, optional
        Settings of the global search and the fits.
    geometry : ScanGeometry, optional
        Each point's stop and the calibration it was scanned with: the uncertainty then holds
        the calibration covariance's share; ``geometry_missing`` says why there is none.

    Returns
    -------
    InspectionResult
        Every input point with its position in the nominal frame, its signed deviation and
        whether it is an outlier; stats, regions, verdict, uncertainty.

    Raises
    ------
    ValueError
        Not an (N, 3) finite cloud of at least 100 points.
    AlignmentFailed
        No pose was found (the cloud is not a scan of this part).
    """
    points = _check_points(points_cloud)
    options = options or AlignOptions(seed=spec.alignment.seed)
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    surface = NominalSurface(nominal)
    select = None
    if spec.alignment.region:
        select = spec.region(spec.alignment.region).select
    alignment = best_fit(points, surface, options, select=select)
    if not alignment.converged and alignment.method == "none":
        raise AlignmentFailed(f"no pose found: {'; '.join(alignment.warnings)}")
    if spec.alignment.method == "rps":
        alignment = _rps(points, surface, alignment, spec)
    seconds["align"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    points_nominal = apply(alignment.nominal_from_cloud, points)
    near = surface.closest(points_nominal)
    deviation = near.signed_mm
    outlier = np.abs(deviation) > spec.outlier_limit_mm
    kept = ~outlier
    if np.count_nonzero(kept) < MIN_POINTS:
        raise AlignmentFailed(
            f"only {np.count_nonzero(kept)} of {len(points)} points lie within "
            f"{spec.outlier_limit_mm:g} mm of the nominal after the alignment "
            f"(rms {alignment.rms_mm:.3g} mm): is this a scan of this part?"
        )
    regions = judge_regions(spec, points_nominal, near.normals, deviation, outlier)
    if geometry is not None and len(geometry.frame_index) == len(points):
        # the nominal's normals in the cloud's frame: n_cloud = R^T n_nominal
        rot = alignment.nominal_from_cloud[:3, :3]
        try:
            calibration = deviation_calibration_share(
                geometry, points, near.normals @ rot, np.flatnonzero(kept)
            )
        except (ValueError, np.linalg.LinAlgError) as exc:  # the deviations stand without it
            calibration = (None, f"calibration ({exc})")
    elif geometry is not None:
        calibration = (None, "calibration (the cloud's stops do not match its points)")
    else:
        calibration = (None, geometry_missing)
    uncertainty = _uncertainty(
        alignment, points_nominal[kept], near.normals[kept], deviation[kept], calibration
    )
    seconds["deviations"] = time.perf_counter() - t0
    failed = any(r.status == "fail" for r in regions)
    return InspectionResult(
        nominal=nominal,
        spec=spec,
        alignment=alignment,
        points_nominal=points_nominal,
        deviation_mm=deviation,
        outlier=outlier,
        face_normals=near.normals,
        stats=regions[0].stats,
        regions=regions,
        uncertainty=uncertainty,
        verdict="fail" if failed else "pass",
        seconds=seconds,
    )
