"""The stage layer: each stage of the job run on files, once, for every caller.

The command line, the demo, the PLC jobs and the batch runner call these functions and never
chain the libraries themselves. A stage

- takes paths (sessions, calibration, cloud, plan) and the paths it is to write,
- reads and checks its inputs once, refusing bad input with a one-line :class:`InputError`
  before any expensive work, and refusing an output that would replace an input,
- writes all its artefacts together or none (:func:`commit_together`): a failed run leaves
  what was there before,
- records its provenance (program version, time, inputs with their digests) in what it
  writes, and
- returns a typed result holding the library's result and the paths written.

The names of a job folder's artefacts are declared in :class:`scanner.formats.layout.JobLayout`.

The stages, in the pipeline's order: :mod:`~scanner.app.stages.capture` (simulate),
:mod:`~scanner.app.stages.calibration` (calibrate, check), :mod:`~scanner.app.stages.scanning`
(plan_scan, scan) and :mod:`~scanner.app.stages.judging` (measure, acceptance, inspect); what
they share (provenance, :class:`StageClock`) is in :mod:`~scanner.app.stages.common`. Callers
use the names here (``stages.scan``), which is also where a test replaces a whole stage.
"""

from __future__ import annotations

from scanner.app.stages.calibration import CalibrateRun, CheckRun, calibrate, check
from scanner.app.stages.capture import simulate
from scanner.app.stages.common import StageClock, provenance
from scanner.app.stages.judging import InspectRun, Judged, ReportFiles, acceptance, inspect, measure
from scanner.app.stages.scanning import PlanRun, ScanRun, plan_scan, scan

__all__ = [
    "CalibrateRun",
    "CheckRun",
    "InspectRun",
    "Judged",
    "PlanRun",
    "ReportFiles",
    "ScanRun",
    "StageClock",
    "acceptance",
    "calibrate",
    "check",
    "inspect",
    "measure",
    "plan_scan",
    "provenance",
    "scan",
    "simulate",
]
