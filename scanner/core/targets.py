"""Calibration target specifications (the ``target`` object of ``session.json``).

Three kinds are accepted: the concentric-circles target of the method, and the standard
chessboard and circle grid that labs already own. Every geometric fact about a target comes
from its spec: ring count, diameters, line width and marker placement are never hard-coded.
All coordinates are in the target frame (mm, z = 0 on the printed face, z out of the face).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "ChessboardTarget",
    "CircleGridTarget",
    "ConcentricCirclesTarget",
    "OrientationMarker",
    "TargetSpec",
    "parse_target",
    "target_to_json",
]


@dataclass(frozen=True)
class OrientationMarker:
    """The filled disc that marks the +x end A of the diameter lines."""

    diameter_mm: float
    center_mm: tuple[float, float]


@dataclass(frozen=True)
class ConcentricCirclesTarget:
    """Concentric rings with a pair of orthogonal diameters along the target's x and y axes.

    ``ring_diameters_mm`` are the diameters of the ring centre lines, ascending. The largest is
    the known length AB = CD of the method; the diameter lines run from -R to +R.
    """

    ring_diameters_mm: tuple[float, ...]
    line_width_mm: float
    orientation_marker: OrientationMarker
    diameter_lines: str = "x and y axes, across the largest circle"
    kind: str = field(default="concentric_circles", init=False)

    def __post_init__(self) -> None:
        d = self.ring_diameters_mm
        if len(d) < 2:
            raise ValueError(f"ring_diameters_mm: expected at least 2 rings, got {len(d)}")
        if any(b <= a for a, b in itertools.pairwise(d)) or d[0] <= 0:
            raise ValueError("ring_diameters_mm: expected positive, strictly ascending diameters")
        if not 0 < self.line_width_mm < (d[1] - d[0]) / 2:
            raise ValueError(
                f"line_width_mm: expected 0 < width < half the ring spacing, got {self.line_width_mm}"
            )
        if self.orientation_marker.diameter_mm <= 0:
            raise ValueError("orientation_marker.diameter_mm: expected > 0")

    @property
    def radius_mm(self) -> float:
        """R, half the largest diameter: A = (R, 0, 0), C = (0, R, 0)."""
        return self.ring_diameters_mm[-1] / 2.0

    @property
    def ring_radii_mm(self) -> NDArray:
        return np.asarray(self.ring_diameters_mm, dtype=np.float64) / 2.0

    def named_points(self) -> dict[str, NDArray]:
        """O, A, B, C, D in the target frame, ``(3,)`` each."""
        r = self.radius_mm
        return {
            "O": np.zeros(3),
            "A": np.array([r, 0.0, 0.0]),
            "B": np.array([-r, 0.0, 0.0]),
            "C": np.array([0.0, r, 0.0]),
            "D": np.array([0.0, -r, 0.0]),
        }


@dataclass(frozen=True)
class ChessboardTarget:
    """Chessboard with ``inner_corners = (cols, rows)`` inner corners, square side ``square_mm``."""

    inner_corners: tuple[int, int]
    square_mm: float
    kind: str = field(default="chessboard", init=False)

    def __post_init__(self) -> None:
        if min(self.inner_corners) < 2 or self.square_mm <= 0:
            raise ValueError(
                f"chessboard: expected >= 2x2 inner corners and square_mm > 0, got "
                f"{self.inner_corners}, {self.square_mm}"
            )

    def object_points(self) -> NDArray:
        """Inner corners in the target frame, ``(cols*rows, 3)``, row-major as OpenCV finds them."""
        cols, rows = self.inner_corners
        jj, ii = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
        pts = np.stack([ii.ravel(), jj.ravel(), np.zeros(ii.size)], axis=1) * self.square_mm
        return pts.astype(np.float64)


@dataclass(frozen=True)
class CircleGridTarget:
    """Grid of filled circles, ``grid = (cols, rows)``, centre pitch ``pitch_mm``."""

    grid: tuple[int, int]
    pitch_mm: float
    asymmetric: bool = False
    kind: str = field(default="circle_grid", init=False)

    def __post_init__(self) -> None:
        if min(self.grid) < 2 or self.pitch_mm <= 0:
            raise ValueError(
                f"circle_grid: expected >= 2x2 circles and pitch_mm > 0, got {self.grid}, {self.pitch_mm}"
            )

    def object_points(self) -> NDArray:
        """Circle centres in the target frame, ``(cols*rows, 3)``, in OpenCV's order."""
        cols, rows = self.grid
        pts = []
        for j in range(rows):
            for i in range(cols):
                if self.asymmetric:
                    pts.append(((2 * i + j % 2) * self.pitch_mm, j * self.pitch_mm, 0.0))
                else:
                    pts.append((i * self.pitch_mm, j * self.pitch_mm, 0.0))
        return np.asarray(pts, dtype=np.float64)


TargetSpec = ConcentricCirclesTarget | ChessboardTarget | CircleGridTarget


def _pair(value: Any, key: str, cast: type) -> tuple:
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise ValueError(f"target.{key}: expected a list of 2 numbers, got {value!r}")
    return (cast(value[0]), cast(value[1]))


def parse_target(obj: Any) -> TargetSpec:
    """Parse and validate the ``target`` object of ``session.json``.

    Raises
    ------
    ValueError
        Naming the key that is missing or wrong, e.g. "target.kind: expected one of ...".
    """
    if not isinstance(obj, dict):
        raise ValueError(f"target: expected an object, got {type(obj).__name__}")
    kind = obj.get("kind")
    try:
        if kind == "concentric_circles":
            marker = obj["orientation_marker"]
            if not isinstance(marker, dict):
                raise ValueError("target.orientation_marker: expected an object")
            diam = obj["ring_diameters_mm"]
            if not isinstance(diam, list) or not diam:
                raise ValueError("target.ring_diameters_mm: expected a non-empty list")
            return ConcentricCirclesTarget(
                ring_diameters_mm=tuple(float(d) for d in diam),
                line_width_mm=float(obj["line_width_mm"]),
                orientation_marker=OrientationMarker(
                    diameter_mm=float(marker["diameter_mm"]),
                    center_mm=_pair(marker["center_mm"], "orientation_marker.center_mm", float),
                ),
                diameter_lines=str(
                    obj.get("diameter_lines", "x and y axes, across the largest circle")
                ),
            )
        if kind == "chessboard":
            return ChessboardTarget(
                inner_corners=_pair(obj["inner_corners"], "inner_corners", int),
                square_mm=float(obj["square_mm"]),
            )
        if kind == "circle_grid":
            return CircleGridTarget(
                grid=_pair(obj["grid"], "grid", int),
                pitch_mm=float(obj["pitch_mm"]),
                asymmetric=bool(obj.get("asymmetric", False)),
            )
    except KeyError as exc:
        raise ValueError(f"target: missing key {exc.args[0]!r} for kind {kind!r}") from None
    except (TypeError, ValueError) as exc:
        if str(exc).startswith("target"):
            raise
        raise ValueError(f"target: {exc}") from None
    raise ValueError(
        f"target.kind: expected 'concentric_circles', 'chessboard' or 'circle_grid', got {kind!r}"
    )


def target_to_json(target: TargetSpec) -> dict[str, Any]:
    """The ``session.json`` form of a target spec (inverse of :func:`parse_target`)."""
    if isinstance(target, ConcentricCirclesTarget):
        return {
            "kind": target.kind,
            "ring_diameters_mm": [float(d) for d in target.ring_diameters_mm],
            "line_width_mm": target.line_width_mm,
            "diameter_lines": target.diameter_lines,
            "orientation_marker": {
                "shape": "disc",
                "diameter_mm": target.orientation_marker.diameter_mm,
                "center_mm": list(target.orientation_marker.center_mm),
            },
        }
    if isinstance(target, ChessboardTarget):
        return {
            "kind": target.kind,
            "inner_corners": list(target.inner_corners),
            "square_mm": target.square_mm,
        }
    return {
        "kind": target.kind,
        "grid": list(target.grid),
        "pitch_mm": target.pitch_mm,
        "asymmetric": target.asymmetric,
    }
