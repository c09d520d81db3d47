"""Capture: sessions from the virtual cell (``scanner simulate``), with their truth."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from numpy.typing import NDArray

from scanner.virtual_cell.cell import CellConfig
from scanner.virtual_cell.simulate import simulate_cell
from scanner.virtual_cell.truth import CellTruth

# --------------------------------------------------------------------------------------------
# simulate


def simulate(
    cell: str | CellConfig,
    out_dir: Path,
    *,
    seed: int = 0,
    target: str | None = None,
    sweep_frames: int | None = None,
    sessions: tuple[str, ...] = ("calibration", "check", "sweep"),
    workers: int = 2,
    progress: bool = False,
    sweep_paths: Sequence[NDArray] | None = None,
    check_cancelled: Callable[[], None] | None = None,
) -> CellTruth:
    """Capture sessions from the virtual cell into ``out_dir/<kind>/``, with their truth.

    ``sweep_paths`` (flange poses of each planned sweep) replaces the cell's own sweep;
    ``check_cancelled`` is called before the first frame and after each (``simulate_cell``).
    """
    if seed < 0:
        raise ValueError(f"--seed: expected >= 0, got {seed}")
    return simulate_cell(
        cell,
        out_dir,
        seed=seed,
        target=target,
        sweep_frames=sweep_frames,
        sessions=sessions,
        workers=workers,
        progress=progress,
        sweep_paths=sweep_paths,
        check_cancelled=check_cancelled,
    )
