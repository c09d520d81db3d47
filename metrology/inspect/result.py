"""What a scan-to-CAD inspection returns: the alignment, every point's deviation, the regions'
verdicts and the uncertainty, ready for the JSON of contract section 5, ``DEV.ply`` and the
report."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from metrology.inspect.spec import InspectionSpec
from scanner.formats.clouds import write_cloud
from scanner.formats.meshes import TriangleMesh

__all__ = [
    "AlignmentResult",
    "DeviationStats",
    "InspectionResult",
    "InspectionUncertainty",
    "RegionResult",
    "write_deviations",
]

Verdict = Literal["pass", "fail"]


@dataclass(frozen=True)
class AlignmentResult:
    """The pose found and how well it holds.

    Attributes
    ----------
    nominal_from_cloud : ndarray, shape (4, 4)
        Maps cloud points into the nominal's frame.
    method : str
        What found it, e.g. ``"fpfh-ransac + robust point-to-plane icp"``.
    rms_mm : float
        RMS of the point-to-surface residuals of the points used in the final fit.
    points_used : int
        Points that carried weight in the final fit (inside the robust loss's cut-off).
    iterations : int
        Iterations of the fine fit.
    converged : bool
    pose_u_mm : float
        1-sigma displacement of the part's farthest point caused by the pose's uncertainty
        (from the fit's covariance), mm.
    covariance : ndarray, shape (6, 6)
        Covariance of the small-motion pose parameters (rotation vector rad, translation mm)
        at the nominal's origin.
    candidates : int
        Distinct poses compared by the global search.
    runner_up_rms_mm : float or None
        RMS of the best pose that differs from the chosen one by more than a part-size
        tolerance; close to ``rms_mm`` means the part's symmetry leaves the pose ambiguous.
    ambiguous : bool
        The runner-up fits nearly as well (see ``warnings``).
    warnings : tuple of str
    """

    nominal_from_cloud: NDArray[np.float64]
    method: str
    rms_mm: float
    points_used: int
    iterations: int
    converged: bool
    pose_u_mm: float
    covariance: NDArray[np.float64]
    candidates: int = 1
    runner_up_rms_mm: float | None = None
    ambiguous: bool = False
    warnings: tuple[str, ...] = ()

    def __bool__(self) -> bool:
        return self.converged and not self.ambiguous


@dataclass(frozen=True)
class DeviationStats:
    """Statistics of signed deviations (mm) over a set of points, outliers excluded."""

    count: int
    mean: float
    rms: float
    std: float
    min: float
    max: float
    p01: float
    p99: float

    @classmethod
    def of(cls, deviation_mm: NDArray) -> DeviationStats:
        d = np.asarray(deviation_mm, dtype=np.float64)
        if d.size == 0:
            nan = float("nan")
            return cls(0, nan, nan, nan, nan, nan, nan, nan)
        p01, p99 = np.percentile(d, [1.0, 99.0])
        return cls(
            count=int(d.size),
            mean=float(d.mean()),
            rms=float(np.sqrt(np.mean(d * d))),
            std=float(d.std()),
            min=float(d.min()),
            max=float(d.max()),
            p01=float(p01),
            p99=float(p99),
        )

    def to_json(self) -> dict[str, float]:
        return {
            "mean": self.mean,
            "rms": self.rms,
            "min": self.min,
            "max": self.max,
            "p01": self.p01,
            "p99": self.p99,
        }


@dataclass(frozen=True)
class RegionResult:
    """One region judged against its band (``"all"`` is the whole part on the global band)."""

    name: str
    description: str
    lower_mm: float
    upper_mm: float
    stats: DeviationStats
    share_in_band: float
    status: Literal["pass", "fail", "no points"]
    outliers: int

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "selector": self.description,
            "lower_mm": self.lower_mm,
            "upper_mm": self.upper_mm,
            "points": self.stats.count,
            "outliers": self.outliers,
            "share_in_band": self.share_in_band,
            "deviation_mm": self.stats.to_json(),
            "status": self.status,
        }


@dataclass(frozen=True)
class InspectionUncertainty:
    """Standard uncertainty (1 sigma, mm) of one point's deviation, and its sources.

    ``noise_mm`` is the cloud's point noise (robust spread of the residuals of the fit,
    away from real form deviations; it holds the stripe noise and the robot's misses between
    stops); ``alignment_mm`` the largest 1-sigma shift of a point's deviation from the pose's
    covariance; ``calibration_mm`` the 95th percentile over the points of the calibration
    covariance's share after the alignment took up its rigid part
    (:func:`metrology.uncertainty.deviation_calibration_share`), ``None`` where the cloud's
    stops or the covariance are not known (named in ``not_included``); ``combined_mm`` their
    root sum of squares.
    """

    noise_mm: float
    alignment_mm: float
    combined_mm: float
    calibration_mm: float | None = None
    not_included: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {
            "noise_mm": self.noise_mm,
            "alignment_mm": self.alignment_mm,
            "calibration_mm": self.calibration_mm,
            "u_mm": self.combined_mm,
            "U_mm": 2.0 * self.combined_mm,
            "k": 2.0,
            "not_included": list(self.not_included),
        }


@dataclass
class InspectionResult:
    """A cloud inspected against a nominal mesh.

    Attributes
    ----------
    nominal : TriangleMesh
        The nominal surface, its own frame.
    spec : InspectionSpec
    alignment : AlignmentResult
    points_nominal : ndarray, shape (N, 3)
        Every input point, mapped into the nominal frame.
    deviation_mm : ndarray, shape (N,)
        Signed distance to the nominal surface, positive outside (too much material).
    outlier : ndarray, shape (N,), bool
        Farther than ``spec.outlier_limit_mm``: not judged, kept and marked.
    face_normals : ndarray, shape (N, 3)
        Outward normal of the nominal face closest to each point.
    stats : DeviationStats
        Over the non-outliers.
    regions : list of RegionResult
        ``"all"`` first (the global band), then the spec's regions in order.
    uncertainty : InspectionUncertainty
    verdict : "pass" or "fail"
    """

    nominal: TriangleMesh
    spec: InspectionSpec
    alignment: AlignmentResult
    points_nominal: NDArray[np.float64]
    deviation_mm: NDArray[np.float64]
    outlier: NDArray[np.bool_]
    face_normals: NDArray[np.float64]
    stats: DeviationStats
    regions: list[RegionResult]
    uncertainty: InspectionUncertainty
    verdict: Verdict
    nominal_path: str = ""
    cloud_path: str = ""
    spec_path: str = ""
    seconds: dict[str, float] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def points(self) -> int:
        return len(self.deviation_mm)

    def to_json(self) -> dict[str, Any]:
        """The ``scan-inspection/1`` record of contract section 5, with our extensions."""
        a = self.alignment
        return {
            "format": "scan-inspection/1",
            "nominal": self.nominal_path,
            "nominal_from_cloud": a.nominal_from_cloud.tolist(),
            "alignment": {
                "method": a.method,
                "rms_mm": a.rms_mm,
                "points_used": a.points_used,
                "iterations": a.iterations,
                "converged": a.converged,
                "pose_u_mm": a.pose_u_mm,
                "candidates": a.candidates,
                "runner_up_rms_mm": a.runner_up_rms_mm,
                "ambiguous": a.ambiguous,
                "warnings": list(a.warnings),
            },
            "deviation_mm": self.stats.to_json(),
            "points": self.points,
            "outliers": int(np.count_nonzero(self.outlier)),
            "verdict": self.verdict,
            "tolerance_mm": {"lower": self.spec.lower_mm, "upper": self.spec.upper_mm},
            "min_share_in_band": self.spec.min_share_in_band,
            "regions": [r.to_json() for r in self.regions],
            "uncertainty": self.uncertainty.to_json(),
            "cloud": self.cloud_path,
            "spec": self.spec_path,
            "seconds": dict(self.seconds),
            "provenance": self.provenance,
        }


def write_deviations(path: Path, result: InspectionResult) -> Path:
    """``DEV.ply``: every evaluated point (nominal frame), ``deviation_mm``, ``outlier``."""
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(result.points_nominal))
    cloud.point["deviation_mm"] = o3d.core.Tensor(
        result.deviation_mm.astype(np.float32).reshape(-1, 1)
    )
    cloud.point["outlier"] = o3d.core.Tensor(result.outlier.astype(np.uint8).reshape(-1, 1))
    meta = {
        "inspection": {
            "nominal": result.nominal_path,
            "cloud": result.cloud_path,
            "verdict": result.verdict,
        },
        "provenance": result.provenance,
    }
    return write_cloud(path, cloud, meta, frame="nominal")
