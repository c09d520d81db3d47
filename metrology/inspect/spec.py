"""Inspection specs: the tolerance bands, regions and section cuts of a scan-to-CAD inspection.

A spec is a TOML file (``configs/inspect/*.toml``, or any path) loaded into frozen
dataclasses and validated once; errors name the file, the line and the key. Every
coordinate is in the **nominal's frame** (the part's CAD frame), mm::

    name = "bracket"
    lower_mm = -0.1                 # the global tolerance band of the signed deviation
    upper_mm = 0.1
    min_share_in_band = 0.99        # a region passes when this share of its points is in band
    outlier_limit_mm = 1.0          # farther from the nominal: an outlier (marked, not judged)

    [[regions]]
    name = "top face"
    normal = [0, 0, 1]              # mesh faces whose normal is within max_angle_deg of it
    max_angle_deg = 10
    lower_mm = -0.05                # a band of its own (the global band when omitted)
    upper_mm = 0.05

    [[regions]]
    name = "boss"
    box_min_mm = [20, 10, 0]        # or center_mm + radius_mm (a ball)
    box_max_mm = [40, 30, 30]

    [[sections]]
    name = "A-A"
    point_mm = [0, 0, 0]            # a plane through the part: its point and normal
    normal = [0, 1, 0]
    thickness_mm = 0.5              # points within half of it on each side are shown

    [alignment]
    method = "best_fit"             # best_fit (global search, then robust ICP) | rps
    region = ""                     # best-fit on one region's points only ("" for all)

A deviation is positive where material lies outside the nominal (too much material).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from scanner.core.config import load_config

__all__ = [
    "AlignmentSpec",
    "DatumSpec",
    "InspectionRegion",
    "InspectionSpec",
    "SectionSpec",
    "load_inspection_spec",
]

Vec3 = tuple[float, float, float]


def _finite_vec(values: Vec3 | None, where: str, *, nonzero: bool = False) -> None:
    if values is None:
        return
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{where}: expected finite numbers, got {list(values)}")
    if nonzero and float(np.linalg.norm(values)) < 1e-9:
        raise ValueError(f"{where}: expected a non-zero vector, got {list(values)}")


def _band(lower: float | None, upper: float | None, where: str) -> None:
    if lower is not None and lower > 0:
        raise ValueError(f"{where}lower_mm: expected <= 0, got {lower}")
    if upper is not None and upper < 0:
        raise ValueError(f"{where}upper_mm: expected >= 0, got {upper}")


@dataclass(frozen=True)
class InspectionRegion:
    """A part of the surface judged on its own band.

    Exactly one selector: a box (``box_min_mm``/``box_max_mm``), a ball (``center_mm`` and
    ``radius_mm``) or the nominal faces whose outward normal is within ``max_angle_deg`` of
    ``normal``; a point belongs to it by its position (box, ball) or by the face its closest
    nominal point lies on (normal).
    """

    name: str
    box_min_mm: Vec3 | None = None
    box_max_mm: Vec3 | None = None
    center_mm: Vec3 | None = None
    radius_mm: float | None = None
    normal: Vec3 | None = None
    max_angle_deg: float = 10.0
    lower_mm: float | None = None
    upper_mm: float | None = None

    def __post_init__(self) -> None:
        if not self.name.strip():
            raise ValueError("name: expected a non-empty string")
        box = self.box_min_mm is not None or self.box_max_mm is not None
        ball = self.center_mm is not None or self.radius_mm is not None
        by_normal = self.normal is not None
        if box + ball + by_normal != 1:
            raise ValueError(
                "expected one selector: box_min_mm + box_max_mm, center_mm + radius_mm, or "
                f"normal; got {box + ball + by_normal}"
            )
        if box:
            if self.box_min_mm is None or self.box_max_mm is None:
                raise ValueError("box_max_mm: a box needs box_min_mm and box_max_mm")
            _finite_vec(self.box_min_mm, "box_min_mm")
            _finite_vec(self.box_max_mm, "box_max_mm")
            if not all(lo < hi for lo, hi in zip(self.box_min_mm, self.box_max_mm)):
                raise ValueError(
                    f"box_max_mm: expected every coordinate above box_min_mm "
                    f"{list(self.box_min_mm)}, got {list(self.box_max_mm)}"
                )
        if ball:
            if self.center_mm is None or self.radius_mm is None:
                raise ValueError("radius_mm: a ball needs center_mm and radius_mm")
            _finite_vec(self.center_mm, "center_mm")
            if not (math.isfinite(self.radius_mm) and self.radius_mm > 0):
                raise ValueError(f"radius_mm: expected a positive number, got {self.radius_mm}")
        if by_normal:
            _finite_vec(self.normal, "normal", nonzero=True)
            if not (0 < self.max_angle_deg <= 90):
                raise ValueError(
                    f"max_angle_deg: expected a number in (0, 90], got {self.max_angle_deg}"
                )
        _band(self.lower_mm, self.upper_mm, "")

    @property
    def kind(self) -> Literal["box", "ball", "normal"]:
        if self.box_min_mm is not None:
            return "box"
        if self.center_mm is not None:
            return "ball"
        return "normal"

    def select(self, points_nominal: NDArray, face_normals: NDArray) -> NDArray:
        """Boolean mask ``(N,)``.

        Parameters
        ----------
        points_nominal : ndarray, shape (N, 3)
            Aligned points, nominal frame, mm.
        face_normals : ndarray, shape (N, 3)
            Unit outward normal of the nominal face closest to each point.
        """
        p = np.asarray(points_nominal, dtype=np.float64)
        if self.kind == "box":
            lo, hi = np.asarray(self.box_min_mm), np.asarray(self.box_max_mm)
            return np.all((p >= lo) & (p <= hi), axis=1)
        if self.kind == "ball":
            d = p - np.asarray(self.center_mm)
            return np.einsum("ij,ij->i", d, d) <= float(self.radius_mm) ** 2  # type: ignore[arg-type]
        n = np.asarray(self.normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        return np.asarray(face_normals) @ n >= math.cos(math.radians(self.max_angle_deg))

    def describe(self) -> str:
        if self.kind == "box":
            return f"box {list(self.box_min_mm or ())} .. {list(self.box_max_mm or ())}"
        if self.kind == "ball":
            return f"ball r={self.radius_mm:g} mm at {list(self.center_mm or ())}"
        return f"faces within {self.max_angle_deg:g} deg of normal {list(self.normal or ())}"


@dataclass(frozen=True)
class SectionSpec:
    """A section cut: the plane through ``point_mm`` with ``normal`` (nominal frame)."""

    name: str
    point_mm: Vec3
    normal: Vec3
    thickness_mm: float = 0.5

    def __post_init__(self) -> None:
        if not self.name.strip():
            raise ValueError("name: expected a non-empty string")
        _finite_vec(self.point_mm, "point_mm")
        _finite_vec(self.normal, "normal", nonzero=True)
        if not (math.isfinite(self.thickness_mm) and self.thickness_mm > 0):
            raise ValueError(f"thickness_mm: expected a positive number, got {self.thickness_mm}")

    def unit_normal(self) -> NDArray:
        n = np.asarray(self.normal, dtype=np.float64)
        return n / np.linalg.norm(n)


@dataclass(frozen=True)
class DatumSpec:
    """One datum of a 3-2-1 (RPS) alignment: a region whose points define it.

    ``kind`` "plane" locks 3 degrees of freedom (the primary), "line" 2 (the secondary: a
    plane region whose normal fixes the in-plane rotation), "point" 1 (the tertiary: a plane
    region fixing the last translation). Each datum's region is given like an
    :class:`InspectionRegion` (box, ball or faces by normal), in the nominal frame.
    """

    kind: Literal["plane", "line", "point"]
    region: InspectionRegion


@dataclass(frozen=True)
class AlignmentSpec:
    """How the cloud is aligned to the nominal."""

    method: Literal["best_fit", "rps"] = "best_fit"
    region: str = ""
    """Name of a region to best-fit on (a local best-fit); "" fits on all points."""
    datums: tuple[DatumSpec, ...] = ()
    """The RPS datums (primary, secondary, tertiary) when ``method = "rps"``."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.method == "rps":
            kinds = tuple(d.kind for d in self.datums)
            if kinds != ("plane", "line", "point"):
                raise ValueError(
                    "method: rps expects three [[alignment.datums]] of kinds plane, line, "
                    f"point in that order, got {list(kinds) or 'none'}"
                )
        elif self.datums:
            raise ValueError(f"datums: only used with method = 'rps', got method {self.method!r}")


@dataclass(frozen=True)
class InspectionSpec:
    """Tolerances, regions, sections and alignment of an inspection (nominal frame, mm)."""

    name: str = "default"
    lower_mm: float = -0.1
    upper_mm: float = 0.1
    min_share_in_band: float = 0.99
    outlier_limit_mm: float = 1.0
    regions: tuple[InspectionRegion, ...] = ()
    sections: tuple[SectionSpec, ...] = ()
    alignment: AlignmentSpec = field(default_factory=AlignmentSpec)

    def __post_init__(self) -> None:
        _band(self.lower_mm, self.upper_mm, "")
        if not (0 < self.min_share_in_band <= 1):
            raise ValueError(
                f"min_share_in_band: expected a share in (0, 1], got {self.min_share_in_band}"
            )
        if not (math.isfinite(self.outlier_limit_mm) and self.outlier_limit_mm > 0):
            raise ValueError(
                f"outlier_limit_mm: expected a positive number, got {self.outlier_limit_mm}"
            )
        widest = max(abs(self.lower_mm), self.upper_mm)
        if self.outlier_limit_mm <= widest:
            raise ValueError(
                f"outlier_limit_mm: expected more than the band's width {widest:g}, "
                f"got {self.outlier_limit_mm:g}"
            )
        names = [r.name for r in self.regions]
        for i, r in enumerate(self.regions):
            if names.index(r.name) != i:
                raise ValueError(f"regions[{i}].name: duplicate region name {r.name!r}")
        if self.alignment.region and self.alignment.region not in names:
            raise ValueError(
                f"alignment.region: unknown region {self.alignment.region!r} "
                f"(expected one of {', '.join(names) or 'none defined'})"
            )

    def band_of(self, region: InspectionRegion) -> tuple[float, float]:
        """The region's band: its own bounds, else the global ones."""
        lower = self.lower_mm if region.lower_mm is None else region.lower_mm
        upper = self.upper_mm if region.upper_mm is None else region.upper_mm
        return lower, upper

    def region(self, name: str) -> InspectionRegion:
        for r in self.regions:
            if r.name == name:
                return r
        raise KeyError(name)


def load_inspection_spec(path: str | os.PathLike[str]) -> InspectionSpec:
    """Load and validate an inspection spec.

    Raises
    ------
    ConfigError
        ``"<file>, line <n>: <key>: <reason>"`` for a missing, unknown or wrong value.
    InputError
        The file is missing or not TOML.
    """
    return load_config(InspectionSpec, path)
