"""Small, fast virtual-cell fixtures for unit tests anywhere in the repository.

>>> from scanner.virtual_cell import quick
>>> cell = quick.quick_cell("paper", scale=2)            # 512x384, same lens geometry
>>> image, cam_from_target = quick.target_frame(cell, seed=0)
>>> out, truth = quick.quick_simulation(tmp_path)        # a few frames of every session

Everything is deterministic from the seed. ``scale`` shrinks the sensor (pixel count) but not
the optics: the same field of view, distortion, laser and scene.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from scanner.virtual_cell.capture import hand_held_scene, render_laser_image, render_target_image
from scanner.virtual_cell.cell import CellConfig, load_cell
from scanner.virtual_cell.poses import hand_held_view
from scanner.virtual_cell.render import StripeTruth
from scanner.virtual_cell.simulate import simulate_cell
from scanner.virtual_cell.truth import CellTruth

__all__ = ["laser_frame", "quick_cell", "quick_simulation", "target_frame"]


def quick_cell(
    name: str | CellConfig = "paper",
    scale: float = 2.0,
    sweep_frames: int = 6,
    noise_free: bool = False,
) -> CellConfig:
    """A cell with a ``scale`` times smaller sensor and a handful of frames per session.

    ``noise_free=True`` also switches off shot/read noise sources that do not depend on the
    generator (black level, vignetting), for tests that compare with projections exactly.
    """
    cell = load_cell(name)
    cap = dataclasses.replace(
        cell.capture,
        hand_held_frames=3,
        light_plane_frames=2,
        posed_frames=3,
        aim_frames_each=1,
        check_frames=2,
    )
    imaging = cell.imaging
    if noise_free:
        imaging = dataclasses.replace(imaging, vignetting=0.0, black_level_dn=0.0)
    return dataclasses.replace(
        cell,
        camera=cell.camera.scaled(scale) if scale != 1 else cell.camera,
        capture=cap,
        imaging=imaging,
        sweep=dataclasses.replace(cell.sweep, frames=sweep_frames, step_mm=cell.sweep.step_mm * 20),
    )


def target_frame(
    cell: CellConfig | str = "paper", seed: int = 0, noise: bool = True
) -> tuple[NDArray, NDArray]:
    """One hand-held target image and its true ``cam_from_target``."""
    cell = load_cell(cell)
    rng = np.random.default_rng(seed)
    cam_from_target = hand_held_view(cell, rng)
    image = render_target_image(cell, cam_from_target, rng if noise else None)
    return image, cam_from_target


def laser_frame(
    cell: CellConfig | str = "paper", seed: int = 0, noise: bool = True
) -> tuple[NDArray, StripeTruth, NDArray]:
    """One hand-held laser image: ``(image, stripe truth, cam_from_target)``."""
    cell = load_cell(cell)
    rng = np.random.default_rng(seed)
    cam_from_target = hand_held_view(cell, rng)
    image, truth = render_laser_image(
        cell, hand_held_scene(cell, cam_from_target), rng if noise else None
    )
    return image, truth, cam_from_target


def quick_simulation(
    out_dir: str | os.PathLike[str],
    cell: CellConfig | str = "paper",
    seed: int = 0,
    scale: float = 2.0,
    target: str | None = None,
) -> tuple[Path, CellTruth]:
    """Simulate a quick cell into ``out_dir`` (single process): ``(out_dir, truth)``."""
    qc = cell if isinstance(cell, CellConfig) else quick_cell(cell, scale)
    truth = simulate_cell(qc, out_dir, seed=seed, target=target, workers=1)
    return Path(out_dir), truth
