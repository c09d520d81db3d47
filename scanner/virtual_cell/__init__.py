"""The virtual cell: a simulated robot, camera, laser and scene, and the ground truth.

It stands in for the real cell wherever one is not at hand (``scanner demo``, every accuracy
test): images are rendered by inverse mapping (pixel samples -> exactly undistorted rays ->
nearest analytic surface -> shading) with anti-aliased edges, optical blur, vignetting, shot and
read noise, laser speckle and saturation, so that code tested here meets real captures.

Cells are described in ``configs/cells/*.toml`` (``paper``: the paper's camera, light plane and
hand-eye; ``modern``: a 1280x1024 distorted lens, another laser and target) and targets in
``configs/targets/*.toml``.

API
---
``load_cell(name_or_path) -> CellConfig``
    A validated cell; ``cell.camera_model()`` is the shared :class:`~scanner.core.camera.CameraModel`,
    ``cell.target_spec()`` the printed target, ``cell.laser.normal``/``.d``/``.origin`` the
    light plane and projector origin (camera frame), ``cell.robot.flange_from_cam_matrix()``
    and ``cell.robot.base_from_target()`` the hand-eye and the target on the table.
``render_target_image(cell, cam_from_target, rng, target=None, laser=False) -> image``
    The target held in front of the camera (laser off), uint8 or uint16 ``(H, W)``.
    ``rng=None`` renders noise-free; ``target`` prints another spec (e.g. a chessboard).
``render_laser_image(cell, scene_or_base_from_cam, rng) -> (image, StripeTruth)``
    A laser image (ambient dimmed) of a :class:`Scene` (``hand_held_scene``,
    ``posed_target_scene``, ``sweep_scene``) or of the sweep scene seen from ``base_from_cam``,
    with the exact stripe centres ``truth.uv`` ``(M, 2)`` and their surfaces.
``simulate_cell(cell, out_dir, seed=0, target=None, sweep_frames=None, workers=2)``
    Writes ``calibration/``, ``check/``, ``sweep/`` (``scan-session/1``), ``truth.json``,
    ``<session>_stripes.npz`` and ``calibration_true.json``; returns the :class:`CellTruth`.
``read_truth(path) -> CellTruth``
    The truth of a simulation: camera, light plane, hand-eye, target placement, objects,
    per frame the true and reported poses and the true ``cam_from_target``.
``scanner.virtual_cell.quick``
    Small fast fixtures for unit tests elsewhere: ``quick_cell``, ``target_frame``,
    ``laser_frame``, ``quick_simulation``.

Sessions
--------
``calibration``: rows without pose where the target is held by hand (``stage`` hand_held in the
truth), rows without pose whose diameter A-O-B lies in the light plane (the paper's light-plane
stage), rows with pose and the target fixed on the table, among them rows where the robot put
the stripe through O, A or C (``aim`` column of frames.csv, a hint only). ``check``: posed rows
whose stripe crosses O. ``sweep``: a linear sweep over a sphere bar and a plate on a table.
The pose in ``frames.csv`` is the commanded one; the truth also holds the actual one (the
robot's repeatability error).
"""

from scanner.virtual_cell.capture import (
    hand_held_scene,
    posed_target_scene,
    render_laser_image,
    render_target_image,
    sweep_scene,
)
from scanner.virtual_cell.cell import CellConfig, cell_names, load_cell, load_target
from scanner.virtual_cell.render import Scene, StripeTruth
from scanner.virtual_cell.simulate import simulate_cell
from scanner.virtual_cell.truth import CellTruth, read_truth

__all__ = [
    "CellConfig",
    "CellTruth",
    "Scene",
    "StripeTruth",
    "cell_names",
    "hand_held_scene",
    "load_cell",
    "load_target",
    "posed_target_scene",
    "read_truth",
    "render_laser_image",
    "render_target_image",
    "simulate_cell",
    "sweep_scene",
]
