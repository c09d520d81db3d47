"""Shared test fixtures: where the real captures live, and small helpers."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def real_data_dir() -> Path:
    """``../shared/data/real`` beside the repository, or ``$SCANNER_REAL_DATA``."""
    env = os.environ.get("SCANNER_REAL_DATA")
    return Path(env) if env else (REPO_ROOT.parent / "shared" / "data" / "real").resolve()


def real_data_subdir(sub: str) -> Path:
    """``sub`` of :func:`real_data_dir`; skips the calling test when that folder is absent.

    Parameters
    ----------
    sub : str
        Folder of one capture below the real-data root, e.g. ``"kuka_1"``.

    Returns
    -------
    Path
        The capture's folder.
    """
    root = real_data_dir() / sub
    if not root.is_dir():
        pytest.skip(f"real data not found at {root} (set SCANNER_REAL_DATA)")
    return root


@pytest.fixture
def real_data() -> Path:
    path = real_data_dir()
    if not path.is_dir():
        pytest.skip(f"real captures not available here ({path} is absent)")
    return path


@pytest.fixture(scope="session")
def simulated_cells(tmp_path_factory):
    """Render virtual-cell sessions once per test run and share them between test modules.

    ``simulated_cells(cell, sessions=("check",))`` returns the folder holding the requested
    sessions and ``truth.json``; repeated requests reuse what was rendered.
    """
    from scanner.virtual_cell.simulate import simulate_cell

    cache: dict[tuple, Path] = {}

    def get(
        cell: str,
        sessions: tuple[str, ...] = ("calibration", "check", "sweep"),
        seed: int = 0,
        **kwargs,
    ) -> Path:
        key = (cell, tuple(sorted(sessions)), seed, tuple(sorted(kwargs.items())))
        # A full simulation serves any subset of its sessions.
        for (c, s, sd, kw), path in cache.items():
            if c == cell and sd == seed and kw == key[3] and set(sessions) <= set(s):
                return path
        path = tmp_path_factory.mktemp(f"cell-{cell}-{seed}")
        simulate_cell(cell, path, seed=seed, sessions=tuple(sessions), **kwargs)
        cache[key] = path
        return path

    return get
