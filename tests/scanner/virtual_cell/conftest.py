"""Shared fixtures of the virtual-cell tests."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from scanner.core.camera import CameraModel
from scanner.virtual_cell import load_cell
from scanner.virtual_cell.cell import CellConfig


def exact_cell(name: str) -> CellConfig:
    """The cell with a 16-bit sensor, no vignetting and no black level: for truth comparisons."""
    cell = load_cell(name)
    return dataclasses.replace(
        cell,
        camera=dataclasses.replace(cell.camera, bit_depth=16),
        imaging=dataclasses.replace(cell.imaging, vignetting=0.0, black_level_dn=0.0),
    )


def back_project(cam: CameraModel, cam_from_target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Target-plane coordinates ``(H, W)`` x and y of every pixel centre."""
    u, v = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    rays = cam.rays(np.column_stack([u.ravel(), v.ravel()]))
    rot, t = cam_from_target[:3, :3], cam_from_target[:3, 3]
    n = rot[:, 2]
    s = (n @ t) / (rays @ n)
    p = rays * s[:, None] - t
    xy = p @ rot[:, :2]
    return xy[:, 0].reshape(u.shape), xy[:, 1].reshape(u.shape)


@pytest.fixture(scope="session")
def paper_exact() -> CellConfig:
    return exact_cell("paper")


@pytest.fixture(scope="session")
def modern_exact() -> CellConfig:
    return exact_cell("modern")
