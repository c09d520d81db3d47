"""What every stage shares: the provenance it records, the check of an output's file name, and
the clock that times stages for a job's summary."""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from scanner import __version__
from scanner.core.fileio import InputError

# --------------------------------------------------------------------------------------------
# provenance


def _digest(*paths: Path) -> str | None:
    """SHA-256 of the files' bytes in turn (``None`` when one is missing)."""
    h = hashlib.sha256()
    for path in paths:
        if not path.is_file():
            return None
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def provenance(stage: str, inputs: dict[str, Path | None]) -> dict[str, Any]:
    """What produced an artefact: the stage, the program's version, when, and from what.

    Files are recorded with their SHA-256; a session folder with that of its ``session.json``
    and ``frames.csv`` (its images are named there, with their poses).
    """
    record: dict[str, Any] = {}
    for name, path in inputs.items():
        if path is None:
            continue
        p = Path(path).resolve()
        files = (p / "session.json", p / "frames.csv") if p.is_dir() else (p,)
        record[name] = {"path": str(p), "sha256": _digest(*files)}
    return {
        "stage": stage,
        "scanner_version": __version__,
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "inputs": record,
    }


def _require_suffix(path: Path, suffixes: Sequence[str], what: str) -> None:
    if path.suffix.lower() not in suffixes:
        raise InputError(
            path,
            f"{what}: expected a {', '.join(suffixes)} file name, got {path.suffix or 'none'!r}",
        )


# --------------------------------------------------------------------------------------------
# timing, for the callers that report time per stage


@dataclass
class StageClock:
    """Seconds per stage name, for a job's summary."""

    seconds: dict[str, float] = field(default_factory=dict)

    def run(self, name: str, fn: Callable[[], Any]) -> Any:
        t0 = time.perf_counter()
        try:
            return fn()
        finally:
            self.seconds[name] = time.perf_counter() - t0
