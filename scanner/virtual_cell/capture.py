"""What the virtual camera captures: scenes of a cell and the images rendered from them.

The two functions others use most:

* :func:`render_target_image` - the target lit, laser off, seen from ``cam_from_target``.
* :func:`render_laser_image` - the laser on, ambient dimmed, with the exact stripe truth.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import NDArray

from scanner.core.conventions import check_transform, make_transform
from scanner.core.targets import TargetSpec
from scanner.formats.meshes import read_mesh
from scanner.virtual_cell.cell import CellConfig, load_cell
from scanner.virtual_cell.render import (
    Laser,
    Scene,
    StripeTruth,
    expose,
    expose_colour,
    render_radiance,
    render_radiance_coarse_ambient,
    speckle_field,
    stripe_truth,
)
from scanner.virtual_cell.scene import (
    BoxSurface,
    CylinderSurface,
    MeshSurface,
    PlaneSurface,
    PrintedTarget,
    SphereSurface,
    Surface,
    object_from_euler,
)

__all__ = [
    "hand_held_scene",
    "posed_target_scene",
    "printed_target",
    "render_image_pair",
    "render_laser_image",
    "render_scene_image",
    "render_target_image",
    "sweep_scene",
]

TARGET_ID = "target"
TABLE_ID = "table"
BACKGROUND_ID = "background"


def printed_target(cell: CellConfig, target: TargetSpec | None = None) -> PrintedTarget:
    """The cell's printed target (or ``target`` printed the same way)."""
    pc = cell.printing
    return PrintedTarget(
        spec=target if target is not None else cell.target_spec(),
        paper_albedo=pc.paper_albedo,
        ink_albedo=pc.ink_albedo,
        card_margin_mm=pc.card_margin_mm,
        circle_grid_diameter_ratio=pc.circle_grid_diameter_ratio,
    )


def hand_held_scene(
    cell: CellConfig, cam_from_target: NDArray, target: TargetSpec | None = None
) -> Scene:
    """The target held anywhere in front of the camera, a dark wall behind it (world = cam)."""
    cam_from_target = check_transform(cam_from_target, "cam_from_target")
    pc = cell.printing
    card = PlaneSurface(cam_from_target, id=TARGET_ID, printed=printed_target(cell, target))
    behind = cam_from_target @ make_transform(np.eye(3), [0.0, 0.0, -pc.hand_held_background_mm])
    wall = PlaneSurface(behind, id=BACKGROUND_ID, albedo_value=pc.background_albedo)
    return Scene([card, wall], np.eye(4), paper_albedo=pc.paper_albedo)


def _table(cell: CellConfig) -> PlaneSurface:
    m = make_transform(np.eye(3), [0.0, 0.0, cell.sweep.table_z_mm])
    return PlaneSurface(m, id=TABLE_ID, albedo_value=cell.sweep.table_albedo)


def posed_target_scene(
    cell: CellConfig,
    base_from_cam: NDArray,
    target: TargetSpec | None = None,
    base_from_target: NDArray | None = None,
) -> Scene:
    """The target fixed on the table (``robot.target_*``), camera at ``base_from_cam``."""
    b_t = cell.robot.base_from_target() if base_from_target is None else base_from_target
    card = PlaneSurface(b_t, id=TARGET_ID, printed=printed_target(cell, target))
    return Scene(
        [card, _table(cell)],
        check_transform(base_from_cam, "base_from_cam"),
        paper_albedo=cell.printing.paper_albedo,
    )


def sweep_objects(cell: CellConfig) -> list[Surface]:
    """The sweep objects of the cell (base frame), table excluded."""
    out: list[Surface] = []
    for ob in cell.sweep.objects:
        if ob.type == "sphere":
            out.append(
                SphereSurface(
                    np.array(ob.center_mm), ob.diameter_mm, id=ob.id, albedo_value=ob.albedo
                )
            )
        elif ob.type == "cylinder":
            out.append(
                CylinderSurface(
                    np.array(ob.p0_mm),
                    np.array(ob.p1_mm),
                    ob.diameter_mm,
                    id=ob.id,
                    albedo_value=ob.albedo,
                )
            )
        elif ob.type == "mesh":
            out.append(_mesh_surface(ob.path, ob.center_mm, ob.euler_xyz_deg, ob.id, ob.albedo))
        else:
            m = object_from_euler(np.array(ob.center_mm), np.array(ob.euler_xyz_deg))
            out.append(BoxSurface(m, ob.size_mm, id=ob.id, albedo_value=ob.albedo))
    return out


@functools.lru_cache(maxsize=8)
def _mesh_surface(
    path: str, center_mm: tuple, euler_xyz_deg: tuple, surface_id: str, albedo: float
) -> MeshSurface:
    """A placed mesh part, read and indexed once per process (a sweep renders it per frame)."""
    m = object_from_euler(np.array(center_mm), np.array(euler_xyz_deg))
    return MeshSurface(read_mesh(path), m, id=surface_id, albedo_value=albedo)


def sweep_scene(cell: CellConfig, base_from_cam: NDArray) -> Scene:
    """The sweep objects on the table, camera at ``base_from_cam`` (world = base)."""
    return Scene(
        [*sweep_objects(cell), _table(cell)],
        check_transform(base_from_cam, "base_from_cam"),
        paper_albedo=cell.printing.paper_albedo,
    )


def render_scene_image(
    cell: CellConfig,
    scene: Scene,
    rng: np.random.Generator | None,
    laser: bool,
    ambient: float | None = None,
    coarse_ambient: bool = False,
) -> NDArray:
    """Render any scene: 8- or 16-bit image, grey ``(H, W)`` or, from a colour camera, BGR
    ``(H, W, 3)``; ``rng=None`` is noise-free.

    ``coarse_ambient`` (laser images only) shades the dim ambient light every other pixel and
    the laser band fully: about three times faster, for long sweeps.
    """
    im = cell.imaging
    if ambient is None:
        ambient = im.white_exposure * (im.laser_ambient if laser else 1.0)
    las_model = Laser.from_cell(cell, scene.world_from_cam) if laser else None
    if coarse_ambient and las_model is not None:
        amb, las = render_radiance_coarse_ambient(cell.camera, im, scene, ambient, las_model)
    else:
        amb, las = render_radiance(cell.camera, im, scene, ambient, las_model)
    if laser and rng is not None and cell.laser.speckle_contrast > 0:
        las = las * speckle_field(
            las.shape, cell.laser.speckle_contrast, cell.laser.speckle_size_px, rng
        )
    return _expose(cell, amb, las, rng)


def render_image_pair(
    cell: CellConfig, scene: Scene, rng: np.random.Generator | None
) -> tuple[NDArray, NDArray]:
    """Target image (laser off) and laser image (ambient dimmed) of one robot stop.

    One geometric pass serves both: the scene does not move between the two exposures, only
    the light changes (the two images get independent noise).
    """
    im = cell.imaging
    laser = Laser.from_cell(cell, scene.world_from_cam)
    amb, las = render_radiance(cell.camera, im, scene, im.white_exposure, laser)
    target_image = _expose(cell, amb, None, rng)
    if rng is not None and cell.laser.speckle_contrast > 0:
        las = las * speckle_field(
            las.shape, cell.laser.speckle_contrast, cell.laser.speckle_size_px, rng
        )
    laser_image = _expose(cell, amb * np.float32(im.laser_ambient), las, rng)
    return target_image, laser_image


def _expose(
    cell: CellConfig, ambient: NDArray, laser: NDArray | None, rng: np.random.Generator | None
) -> NDArray:
    """The camera's image of the ambient light and the laser: grey, or BGR (colour sensor)."""
    if cell.camera.colour:
        las = np.zeros_like(ambient) if laser is None else laser
        return expose_colour(
            ambient, las, cell.laser.colour_response, cell.imaging, cell.camera.bit_depth, rng
        )
    radiance = ambient if laser is None else ambient + laser
    return expose(radiance, cell.imaging, cell.camera.bit_depth, rng)


def render_target_image(
    cell: CellConfig | str,
    cam_from_target: NDArray | Scene,
    rng: np.random.Generator | None,
    target: TargetSpec | None = None,
    laser: bool = False,
) -> NDArray:
    """Image of the printed target with the laser off (or on, ``laser=True``).

    Parameters
    ----------
    cell : CellConfig or str
        A cell or its name.
    cam_from_target : ndarray, shape (4, 4), or Scene
        Target pose (held by hand in front of a wall), or a prepared scene.
    rng : numpy Generator or None
        Noise source; None renders noise-free (blur and quantisation only).
    target : TargetSpec, optional
        Print this target instead of the cell's (e.g. a chessboard at the same poses).
    laser : bool
        Add the laser line (the image then has the full target lighting plus the line).

    Returns
    -------
    ndarray, shape (height, width), uint8 or uint16
    """
    cell = load_cell(cell)
    scene = (
        cam_from_target
        if isinstance(cam_from_target, Scene)
        else hand_held_scene(cell, cam_from_target, target)
    )
    ambient = cell.imaging.white_exposure
    return render_scene_image(cell, scene, rng, laser=laser, ambient=ambient)


def render_laser_image(
    cell: CellConfig | str,
    scene: Scene | NDArray,
    rng: np.random.Generator | None,
    truth_step_px: float = 0.5,
) -> tuple[NDArray, StripeTruth]:
    """Laser image (ambient dimmed) and the exact stripe centre curve in it.

    Parameters
    ----------
    cell : CellConfig or str
    scene : Scene or ndarray, shape (4, 4)
        A prepared scene, or ``base_from_cam`` of the sweep scene.
    rng : numpy Generator or None
        Noise and speckle source; None renders noise-free.
    truth_step_px : float
        Spacing of the true centre points along the stripe, about, pixels.

    Returns
    -------
    image : ndarray, shape (height, width), uint8 or uint16
    truth : StripeTruth
        ``truth.uv`` (M, 2) true stripe centres, distorted pixels; ``truth.surface`` indices.
    """
    cell = load_cell(cell)
    if not isinstance(scene, Scene):
        scene = sweep_scene(cell, np.asarray(scene, dtype=np.float64))
    image = render_scene_image(cell, scene, rng, laser=True)
    truth = stripe_truth(
        cell.camera, scene, Laser.from_cell(cell, scene.world_from_cam), truth_step_px
    )
    return image, truth
