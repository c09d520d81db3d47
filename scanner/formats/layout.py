"""The artefacts of a job folder, named in one place.

A job (``scanner demo``, a PLC job, one session of ``scanner batch``) writes its stages'
artefacts into one folder under these names, so that any stage can be rerun alone with the
ordinary commands and every caller finds the same files::

    JOB/sessions/{calibration,check,sweep}/   captured or simulated sessions (+ truth.json)
    JOB/calibration.json, calibration.html    scanner calibrate
    JOB/check.json, check.html                scanner check (the EF check)
    JOB/cloud.ply                             scanner scan
    JOB/measure.json, .csv, .html             scanner measure
    JOB/acceptance.json, .csv, .html          scanner acceptance
    JOB/summary.json, index.html              the job's own summary and index page
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

__all__ = ["JobLayout", "report_beside"]


def report_beside(out_path: str | os.PathLike[str], suffix: str = ".html") -> Path:
    """The report written beside a result: same folder and name, ``suffix`` in place of its own.

    Every command writes its HTML report this way unless told otherwise.
    """
    return Path(out_path).with_suffix(suffix)


@dataclass(frozen=True)
class JobLayout:
    """Where each artefact of a job folder lives: ``JobLayout.of(root)``."""

    root: Path
    sessions: Path
    truth: Path
    calibration: Path
    calibration_report: Path
    check: Path
    check_report: Path
    cloud: Path
    measure: Path
    acceptance: Path
    inspection: Path
    deviations: Path
    summary: Path
    index: Path

    @classmethod
    def of(cls, root: str | os.PathLike[str]) -> JobLayout:
        """The layout of the job folder ``root``."""
        r = Path(root)
        return cls(
            root=r,
            sessions=r / "sessions",
            truth=r / "sessions" / "truth.json",
            calibration=r / "calibration.json",
            calibration_report=report_beside(r / "calibration.json"),
            check=r / "check.json",
            check_report=report_beside(r / "check.json"),
            cloud=r / "cloud.ply",
            measure=r / "measure.json",
            acceptance=r / "acceptance.json",
            inspection=r / "inspect.json",
            deviations=r / "deviations.ply",
            summary=r / "summary.json",
            index=r / "index.html",
        )

    def session(self, kind: str) -> Path:
        """The session folder of ``kind`` (``calibration``, ``check`` or ``sweep``)."""
        return self.sessions / kind
