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


@pytest.fixture
def real_data() -> Path:
    path = real_data_dir()
    if not path.is_dir():
        pytest.skip(f"real captures not available here ({path} is absent)")
    return path
