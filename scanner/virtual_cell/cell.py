"""Cell descriptions: ``configs/cells/*.toml`` and ``configs/targets/*.toml`` as dataclasses.

A cell is everything the simulator needs to stand in for a real robot cell: the camera (pinhole +
OpenCV distortion), the sensor's imaging chain (blur, vignetting, noise), the laser (its light
plane and origin in the camera frame), the printed target and its placement on the table, the
robot (hand-eye, repeatability), how calibration frames are captured, and the sweep scene.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from scanner.core.camera import CameraModel
from scanner.core.config import CONFIG_DIR, config_dirs, load_config, resolve_config
from scanner.core.conventions import make_transform, orthonormalize
from scanner.core.fileio import InputError
from scanner.core.targets import (
    ChessboardTarget,
    CircleGridTarget,
    ConcentricCirclesTarget,
    OrientationMarker,
    TargetSpec,
)
from scanner.scanning.coverage import SensorGeometry
from scanner.virtual_cell.scene import PrintedTarget

__all__ = [
    "CameraConfig",
    "CaptureConfig",
    "CellConfig",
    "ImagingConfig",
    "LaserConfig",
    "ObjectConfig",
    "PrintConfig",
    "RobotConfig",
    "SweepConfig",
    "TargetConfig",
    "cell_names",
    "load_cell",
    "load_target",
]

log = logging.getLogger(__name__)

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class CameraConfig:
    """Pinhole camera with OpenCV distortion ``(k1, k2, p1, p2, k3)``; pixels, 8 or 16 bit."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    bit_depth: int = 8
    colour: bool = False
    """A colour sensor: a Bayer mosaic (blue at even rows and columns), demosaiced by the
    camera; images are written as BGR. The laser's colour is ``laser.colour_response``."""

    def __post_init__(self) -> None:
        if self.width < 16 or self.height < 16:
            raise ValueError(
                f"camera: expected width, height >= 16, got {self.width}x{self.height}"
            )
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera: expected fx, fy > 0, got {self.fx}, {self.fy}")
        if self.bit_depth not in (8, 16):
            raise ValueError(f"camera.bit_depth: expected 8 or 16, got {self.bit_depth}")

    @property
    def K(self) -> NDArray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def model(self) -> CameraModel:
        return CameraModel(self.width, self.height, self.K, np.asarray(self.dist, dtype=float))

    def scaled(self, factor: float) -> CameraConfig:
        """The same lens on a sensor ``factor`` times coarser (for fast unit-test fixtures)."""
        w, h = round(self.width / factor), round(self.height / factor)
        sx, sy = w / self.width, h / self.height
        return CameraConfig(
            width=w,
            height=h,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            dist=self.dist,
            bit_depth=self.bit_depth,
            colour=self.colour,
        )


@dataclass(frozen=True)
class ImagingConfig:
    """The sensor chain: supersampling, optical blur, vignetting, noise and exposure.

    Radiance is expressed as a fraction of full scale (the white level): a value of 1 saturates.
    """

    supersample: int = 4
    """Edge pixels (printed edges, silhouettes, the laser band) get ``supersample**2`` samples."""
    psf_sigma_px: float = 0.7
    vignetting: float = 0.8
    """Strength of the cos^4 fall-off: gain = 1 - vignetting * (1 - cos^4(field angle))."""
    full_well_e: float = 12000.0
    """Electrons at full scale (sets the shot noise)."""
    read_noise_e: float = 6.0
    black_level_dn: float = 2.0
    """Offset added before quantisation, in 8-bit DN (scaled for 16 bit)."""
    white_exposure: float = 0.75
    """Level of the white card at the image centre in a target image (fraction of full scale)."""
    laser_ambient: float = 0.08
    """Ambient light in a laser image relative to a target image (the ambient is dimmed)."""

    def __post_init__(self) -> None:
        if not 1 <= self.supersample <= 8:
            raise ValueError(f"imaging.supersample: expected 1..8, got {self.supersample}")
        if self.psf_sigma_px < 0 or not 0 <= self.vignetting <= 1:
            raise ValueError("imaging: expected psf_sigma_px >= 0 and 0 <= vignetting <= 1")
        if self.full_well_e <= 0 or self.read_noise_e < 0:
            raise ValueError("imaging: expected full_well_e > 0 and read_noise_e >= 0")


@dataclass(frozen=True)
class LaserConfig:
    """The laser: light plane ``a x + b y + c z + d = 0`` in the camera frame (mm), its origin."""

    plane: tuple[float, float, float, float]
    origin_mm: Vec3
    """The point the fan is emitted from (camera frame, on the plane: projected onto it)."""
    sigma_mm: float = 0.25
    """Gaussian sigma of the line's cross-section, mm (see ``width_model``)."""
    width_model: Literal["surface", "sheet"] = "surface"
    """``surface``: sigma measured on the surface perpendicular to the line; ``sheet``: sigma of
    the light sheet's thickness (the line widens on surfaces the sheet meets obliquely)."""
    power: float = 2.0
    """Peak radiance of the line on white paper at ``reference_distance_mm``, normal incidence
    (fraction of full scale; above 1 saturates)."""
    reference_distance_mm: float = 500.0
    speckle_contrast: float = 0.25
    speckle_size_px: float = 1.5
    colour_response: Vec3 = (1.0, 0.1, 0.05)
    """Response of a colour camera's (red, green, blue) pixels to the laser, relative to
    their response to the white ambient light: a red laser, seen faintly through the green
    and blue filters' tails. ``power`` is the red pixels' level. Ignored by a mono camera."""

    def __post_init__(self) -> None:
        if len(self.colour_response) != 3 or min(self.colour_response) < 0:
            raise ValueError(
                f"laser.colour_response: expected three values >= 0, got {self.colour_response}"
            )
        n = np.asarray(self.plane[:3], dtype=float)
        if np.linalg.norm(n) < 1e-9 or self.plane[3] == 0:
            raise ValueError(
                "laser.plane: expected a non-zero normal and d != 0 (not through the camera)"
            )
        if self.sigma_mm <= 0 or self.power <= 0:
            raise ValueError("laser: expected sigma_mm > 0 and power > 0")
        off = float(self.normal @ np.asarray(self.origin_mm, dtype=float) + self.d)
        if abs(off) > 1.0:
            raise ValueError(
                f"laser.origin_mm: expected a point on the light plane (within 1 mm), "
                f"got {off:.3f} mm off it"
            )

    @property
    def normal(self) -> NDArray:
        """Unit normal of the light plane (camera frame)."""
        n = np.asarray(self.plane[:3], dtype=float)
        return n / np.linalg.norm(n)

    @property
    def d(self) -> float:
        return float(self.plane[3] / np.linalg.norm(self.plane[:3]))

    @property
    def origin(self) -> NDArray:
        """Laser origin projected exactly onto the light plane, camera frame, mm."""
        o = np.asarray(self.origin_mm, dtype=float)
        return o - (self.normal @ o + self.d) * self.normal


@dataclass(frozen=True)
class PrintConfig:
    """How the target and the scene look: albedos (0..1) and the card's white margin.

    The card's own settings default to those of a :class:`PrintedTarget`.
    """

    paper_albedo: float = PrintedTarget.paper_albedo
    ink_albedo: float = PrintedTarget.ink_albedo
    background_albedo: float = 0.2
    card_margin_mm: float = PrintedTarget.card_margin_mm
    circle_grid_diameter_ratio: float = PrintedTarget.circle_grid_diameter_ratio
    """Printed circle diameter of a circle grid as a fraction of its pitch."""
    hand_held_background_mm: float = 250.0
    """Frames without pose: distance from the target centre to a wall behind it."""


@dataclass(frozen=True)
class RobotConfig:
    """Hand-eye, target placement in the base frame, repeatability, pose convention."""

    flange_from_cam: tuple[tuple[float, ...], ...]
    target_position_mm: Vec3
    target_euler_xyz_deg: Vec3 = (0.0, 0.0, 0.0)
    repeatability_mm: float = 0.02
    repeatability_deg: float = 0.005
    rotation: str = "euler_xyz_deg"

    def __post_init__(self) -> None:
        m = np.asarray(self.flange_from_cam, dtype=float)
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        if m.shape != (4, 4):
            raise ValueError(f"robot.flange_from_cam: expected 3 or 4 rows of 4, got {m.shape}")

    def flange_from_cam_matrix(self) -> NDArray:
        """``flange_from_cam`` with its rotation block orthonormalised (printed tables)."""
        m = np.asarray(self.flange_from_cam, dtype=float)
        return make_transform(orthonormalize(m[:3, :3]), m[:3, 3])

    def base_from_target(self) -> NDArray:
        rot = Rotation.from_euler("xyz", self.target_euler_xyz_deg, degrees=True)
        return make_transform(rot, self.target_position_mm)


@dataclass(frozen=True)
class CaptureConfig:
    """How the calibration and check sessions are captured."""

    working_distance_mm: float
    hand_held_frames: int = 8
    light_plane_frames: int = 7
    posed_frames: int = 15
    aim_frames_each: int = 3
    check_frames: int = 9
    max_tilt_deg: float = 45.0
    posed_tilt_deg: tuple[float, float] = (10.0, 30.0)
    hand_held_distance: tuple[float, float] = (0.6, 1.15)
    """Range of the hand-held views' distance, times ``working_distance_mm``."""
    partial_view_fraction: float = 0.5
    """Share of hand-held views where the card may run partly out of the image."""

    def __post_init__(self) -> None:
        if self.working_distance_mm <= 0:
            raise ValueError(
                f"capture.working_distance_mm: expected > 0, got {self.working_distance_mm}"
            )
        counts = (
            self.hand_held_frames,
            self.light_plane_frames,
            self.posed_frames,
            self.aim_frames_each,
            self.check_frames,
        )
        if min(counts) < 0:
            raise ValueError(f"capture: expected frame counts >= 0, got {counts}")
        near, far = self.hand_held_distance
        if not 0.1 <= near <= far <= 5.0:
            raise ValueError(
                "capture.hand_held_distance: expected 0.1 <= near <= far <= 5 (times the "
                f"working distance), got {self.hand_held_distance}"
            )
        if not 0.0 <= self.partial_view_fraction <= 1.0:
            raise ValueError(
                f"capture.partial_view_fraction: expected 0..1, got {self.partial_view_fraction}"
            )
        lo, hi = self.posed_tilt_deg
        if not 0 <= lo <= hi < 80 or not 0 < self.max_tilt_deg < 80:
            raise ValueError(
                "capture: expected 0 <= posed_tilt_deg[0] <= posed_tilt_deg[1] < 80 and "
                f"0 < max_tilt_deg < 80, got {self.posed_tilt_deg}, {self.max_tilt_deg}"
            )


@dataclass(frozen=True)
class ObjectConfig:
    """One object of the sweep scene, base frame, mm.

    ``sphere``: ``center_mm``, ``diameter_mm``. ``cylinder``: ``p0_mm``, ``p1_mm`` (axis ends),
    ``diameter_mm``. ``box``: ``center_mm``, ``size_mm`` (x, y, z extents), ``euler_xyz_deg``.
    ``mesh``: ``path`` (STL, PLY or OBJ in mm; relative to the cell file, else to the config folders),
    placed by ``center_mm`` (where the mesh's origin goes) and ``euler_xyz_deg``.
    """

    type: Literal["sphere", "cylinder", "box", "mesh"]
    id: str
    center_mm: Vec3 = (0.0, 0.0, 0.0)
    diameter_mm: float = 0.0
    p0_mm: Vec3 = (0.0, 0.0, 0.0)
    p1_mm: Vec3 = (0.0, 0.0, 0.0)
    size_mm: Vec3 = (0.0, 0.0, 0.0)
    euler_xyz_deg: Vec3 = (0.0, 0.0, 0.0)
    albedo: float = 0.7
    path: str = ""

    def __post_init__(self) -> None:
        if self.type == "mesh" and not self.path:
            raise ValueError(f"objects {self.id}: a mesh object needs a path")
        if self.type in ("sphere", "cylinder") and self.diameter_mm <= 0:
            raise ValueError(f"objects {self.id}: expected diameter_mm > 0, got {self.diameter_mm}")
        if self.type == "box" and min(self.size_mm) <= 0:
            raise ValueError(f"objects {self.id}: expected size_mm > 0, got {self.size_mm}")
        if self.type == "cylinder" and np.allclose(self.p0_mm, self.p1_mm):
            raise ValueError(f"objects {self.id}: expected p0_mm != p1_mm")


@dataclass(frozen=True)
class SweepConfig:
    """A linear sweep over objects on a table (plane z = ``table_z_mm`` of the base frame)."""

    center_mm: Vec3
    """Base-frame point on the table the middle of the sweep looks at."""
    standoff_mm: float
    """Height of the camera above the table."""
    frames: int = 400
    step_mm: float = 0.3
    yaw_deg: float = 0.0
    """Rotation of the sensor about the base z axis."""
    table_z_mm: float = 0.0
    table_albedo: float = 0.3
    objects: tuple[ObjectConfig, ...] = ()

    def __post_init__(self) -> None:
        if self.frames < 1 or self.step_mm <= 0 or self.standoff_mm <= 0:
            raise ValueError(
                f"sweep: expected frames >= 1, step_mm > 0 and standoff_mm > 0, got "
                f"{self.frames}, {self.step_mm}, {self.standoff_mm}"
            )
        ids = [o.id for o in self.objects]
        if len(set(ids)) != len(ids) or "table" in ids:
            raise ValueError(f"sweep.objects: expected unique ids other than 'table', got {ids}")


@dataclass(frozen=True)
class TargetConfig:
    """A printed target (``configs/targets/*.toml``): converts to a :data:`TargetSpec`."""

    kind: Literal["concentric_circles", "chessboard", "circle_grid"]
    ring_diameters_mm: tuple[float, ...] = ()
    ring_count: int = 0
    ring_min_diameter_mm: float = 0.0
    ring_max_diameter_mm: float = 0.0
    line_width_mm: float = 0.6
    marker_diameter_mm: float = 8.0
    marker_center_mm: tuple[float, float] = (0.0, 0.0)
    inner_corners: tuple[int, int] = (0, 0)
    square_mm: float = 0.0
    grid: tuple[int, int] = (0, 0)
    pitch_mm: float = 0.0
    asymmetric: bool = False

    def spec(self) -> TargetSpec:
        if self.kind == "chessboard":
            return ChessboardTarget(inner_corners=self.inner_corners, square_mm=self.square_mm)
        if self.kind == "circle_grid":
            return CircleGridTarget(
                grid=self.grid, pitch_mm=self.pitch_mm, asymmetric=self.asymmetric
            )
        diam = self.ring_diameters_mm
        if not diam:
            if self.ring_count < 2:
                raise ValueError("target: expected ring_diameters_mm or ring_count >= 2")
            diam = tuple(
                float(round(d, 6))
                for d in np.linspace(
                    self.ring_min_diameter_mm, self.ring_max_diameter_mm, self.ring_count
                )
            )
        return ConcentricCirclesTarget(
            ring_diameters_mm=tuple(diam),
            line_width_mm=self.line_width_mm,
            orientation_marker=OrientationMarker(
                diameter_mm=self.marker_diameter_mm, center_mm=self.marker_center_mm
            ),
        )


@dataclass(frozen=True)
class CellConfig:
    """A whole virtual cell (``configs/cells/NAME.toml``)."""

    name: str
    camera: CameraConfig
    laser: LaserConfig
    robot: RobotConfig
    capture: CaptureConfig
    sweep: SweepConfig
    target: str
    """Name of a ``configs/targets/*.toml`` file or a path to one."""
    description: str = ""
    imaging: ImagingConfig = field(default_factory=ImagingConfig)
    printing: PrintConfig = field(default_factory=PrintConfig)

    def camera_model(self) -> CameraModel:
        return self.camera.model()

    def sensor_geometry(self) -> SensorGeometry:
        """The cell's true sensor (camera, light plane, laser origin, hand-eye) for planning."""
        return SensorGeometry(
            self.camera_model(),
            self.laser.normal,
            self.laser.d,
            self.laser.origin,
            self.robot.flange_from_cam_matrix(),
        )

    def target_spec(self) -> TargetSpec:
        return load_target(self.target)


def load_target(name_or_path: str | os.PathLike[str]) -> TargetSpec:
    """A target spec from ``configs/targets/<name>.toml`` or a TOML path."""
    path = resolve_config(name_or_path, "targets")
    return load_config(TargetConfig, path).spec()


def load_cell(name_or_path: str | os.PathLike[str] | CellConfig) -> CellConfig:
    """A cell from ``configs/cells/<name>.toml`` or a TOML path (a CellConfig passes through)."""
    if isinstance(name_or_path, CellConfig):
        return name_or_path
    path = resolve_config(name_or_path, "cells")
    cell = load_config(CellConfig, path)
    target = Path(cell.target)
    if not target.is_absolute() and (path.parent / target).is_file():
        cell = _replace(cell, target=str(path.parent / target))
    cell.target_spec()  # validate now, naming the file
    return _resolve_mesh_paths(cell, path)


def _resolve_mesh_paths(cell: CellConfig, cell_path: Path) -> CellConfig:
    """Mesh objects' paths made absolute: relative to the cell file, else to ``configs/``."""
    objects = []
    for ob in cell.sweep.objects:
        if ob.type == "mesh":
            given = Path(ob.path)
            tries = [given] if given.is_absolute() else [cell_path.parent / given]
            tries += [folder / given for folder in config_dirs()]
            found = next((t for t in tries if t.is_file()), None)
            if found is None:
                raise InputError(cell_path, f"objects {ob.id}: mesh {ob.path!r} not found")
            ob = dataclasses.replace(ob, path=str(found.resolve()))
        objects.append(ob)
    return _replace(cell, sweep=dataclasses.replace(cell.sweep, objects=tuple(objects)))


def _replace(cell: CellConfig, **changes: object) -> CellConfig:
    return dataclasses.replace(cell, **changes)  # type: ignore[arg-type]


def cell_names() -> list[str]:
    """Names of the cells shipped in ``configs/cells``."""
    return sorted(p.stem for p in (CONFIG_DIR / "cells").glob("*.toml"))
