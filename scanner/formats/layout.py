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
    """Where each artefact of a job folder ``root`` lives."""

    root: Path

    @property
    def sessions(self) -> Path:
        return self.root / "sessions"

    def session(self, kind: str) -> Path:
        """The session folder of ``kind`` (``calibration``, ``check`` or ``sweep``)."""
        return self.sessions / kind

    @property
    def truth(self) -> Path:
        return self.sessions / "truth.json"

    @property
    def calibration(self) -> Path:
        return self.root / "calibration.json"

    @property
    def calibration_report(self) -> Path:
        return report_beside(self.calibration)

    @property
    def check(self) -> Path:
        return self.root / "check.json"

    @property
    def check_report(self) -> Path:
        return report_beside(self.check)

    @property
    def cloud(self) -> Path:
        return self.root / "cloud.ply"

    @property
    def measure(self) -> Path:
        return self.root / "measure.json"

    @property
    def acceptance(self) -> Path:
        return self.root / "acceptance.json"

    @property
    def summary(self) -> Path:
        return self.root / "summary.json"

    @property
    def index(self) -> Path:
        return self.root / "index.html"
