"""The virtual cell: a simulated robot, camera, laser and scene, and the ground truth.

(Full API notes below are completed as the package grows.)
"""

from scanner.virtual_cell.capture import (
    hand_held_scene,
    posed_target_scene,
    render_laser_image,
    render_target_image,
    sweep_scene,
)
from scanner.virtual_cell.cell import CellConfig, load_cell, load_target
from scanner.virtual_cell.render import Scene, StripeTruth

__all__ = [
    "CellConfig",
    "Scene",
    "StripeTruth",
    "hand_held_scene",
    "load_cell",
    "load_target",
    "posed_target_scene",
    "render_laser_image",
    "render_target_image",
    "sweep_scene",
]
