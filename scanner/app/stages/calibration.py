"""Calibration: a ``calibration`` session to the calibration file and its report
(``scanner calibrate``), and the EF check of a calibration on a ``check`` session
(``scanner check``)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from calibration.pipeline import CalibrationResult, calibrate_session
from calibration.report import write_calibration_report
from metrology.ef_check import EFCheckResult, EFTolerances, run_ef_check
from metrology.ef_report import write_ef_report
from scanner.app.stages.common import _require_suffix, provenance
from scanner.core.fileio import check_outputs_apart, commit_together, write_json_atomic
from scanner.formats.calibration_file import CalibrationQuality, read_calibration, write_calibration
from scanner.formats.layout import report_beside
from scanner.formats.session import read_session

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# calibrate


@dataclass(frozen=True)
class CalibrateRun:
    """A calibration written: the library's result and the files."""

    result: CalibrationResult
    calibration_path: Path
    report_path: Path | None

    @property
    def quality(self) -> CalibrationQuality:
        return self.result.calibration.quality


def calibrate(
    session_dir: Path,
    out: Path,
    *,
    report: Path | Literal["beside"] | None = "beside",
    method: Literal["default", "paper"] = "default",
    refine_intrinsics: bool = False,
    laser_origin_cam_mm: tuple[float, float, float] | None = None,
    laser_origin_strict: bool = True,
    progress: bool = False,
    on_stage: Callable[[str], None] | None = None,
    check_cancelled: Callable[[], None] | None = None,
) -> CalibrateRun:
    """Calibrate from a ``calibration`` session and write the calibration file and its report.

    Parameters
    ----------
    session_dir : path
        The calibration session folder.
    out : path
        The calibration file to write (JSON).
    report : path, None or "beside"
        The HTML report: beside ``out`` (same name, ``.html``) by default, ``None`` for none.
    laser_origin_cam_mm : tuple of float, optional
        The laser fan's apex in the camera frame (mm) from the sensor's drawing: written as
        ``laser_origin_cam``; it must lie on the calibrated light plane (within 5 mm).
    laser_origin_strict : bool
        An origin off the new plane is an error (``True``, a user's input) or left out with a
        warning (``False``: the PLC carrying the installed calibration's origin over).
    check_cancelled : callable, optional
        Called between the calibration's stages and images (``calibrate_session``).
    """
    out = Path(out)
    _require_suffix(out, (".json",), "--out")
    report_path = report_beside(out) if report == "beside" else report
    outputs = [out] + ([report_path] if report_path is not None else [])
    check_outputs_apart([session_dir], outputs)
    if laser_origin_cam_mm is not None and not all(math.isfinite(v) for v in laser_origin_cam_mm):
        raise ValueError(f"--laser-origin-mm: expected finite numbers, got {laser_origin_cam_mm}")
    session = read_session(session_dir)
    result = calibrate_session(
        session,
        method=method,
        progress=progress,
        refine_intrinsics=refine_intrinsics,
        on_stage=on_stage,
        check_cancelled=check_cancelled,
    )
    record = dict(result.calibration.quality.record)
    record["provenance"] = provenance("calibrate", {"session": Path(session_dir)})
    if result.calibration.laser_origin_cam is not None:
        record["laser_origin_source"] = "estimated from the laser frames' shadow edges"
    calibration = replace(
        result.calibration, quality=replace(result.calibration.quality, record=record)
    )
    if laser_origin_cam_mm is not None:
        origin = np.asarray(laser_origin_cam_mm, dtype=np.float64)
        if calibration.light_plane is None:
            raise ValueError("--laser-origin-mm: the session gave no light plane to put it on")
        off = abs(float(calibration.light_plane.signed_distance(origin)))
        if off <= 5.0:
            record["laser_origin_source"] = "given (--laser-origin-mm, the sensor's drawing)"
            cov = calibration.covariance  # the estimate's origin covariance is not the drawing's
            calibration = replace(
                calibration,
                laser_origin_cam=origin,
                quality=replace(calibration.quality, record=record),
                covariance=cov if cov is None else replace(cov, laser_origin_mm2=None),
            )
        elif laser_origin_strict:
            raise ValueError(
                f"--laser-origin-mm: expected a point on the calibrated light plane, got one "
                f"{off:.1f} mm off it (camera frame, mm?)"
            )
        else:
            log.warning(
                "laser origin %s left out: %.1f mm off the new light plane", origin.tolist(), off
            )
    result = replace(result, calibration=calibration)
    with commit_together() as staged:
        write_calibration(staged(out), calibration)
        if report_path is not None:
            staged_report = staged(report_path)
            write_calibration_report(result, staged_report.parent, staged_report.name)
    return CalibrateRun(result, out, report_path)


# --------------------------------------------------------------------------------------------
# check


@dataclass(frozen=True)
class CheckRun:
    """An EF check written: the result and the files."""

    result: EFCheckResult
    out_path: Path
    report_path: Path | None


def check(
    session_dir: Path,
    calibration_path: Path,
    out: Path,
    *,
    report: Path | Literal["beside"] | None = "beside",
    mode: Literal["fast", "precise"] = "precise",
    tolerances: EFTolerances | None = None,
    progress: bool = False,
    check_cancelled: Callable[[], None] | None = None,
) -> CheckRun:
    """The paper's EF check on a ``check`` session; writes the result JSON and its report.

    ``check_cancelled`` is called after each laser frame's measurement (``run_ef_check``).
    """
    out = Path(out)
    _require_suffix(out, (".json",), "--out")
    report_path = report_beside(out) if report == "beside" else report
    outputs = [out] + ([report_path] if report_path is not None else [])
    check_outputs_apart([session_dir, calibration_path], outputs)
    calibration = read_calibration(calibration_path)
    calibration.require_light_plane(calibration_path, "the EF check")
    session = read_session(session_dir)
    result = run_ef_check(
        session,
        calibration,
        progress=progress,
        mode=mode,
        calibration_source=str(Path(calibration_path).resolve()),
        tolerances=tolerances,
        check_cancelled=check_cancelled,
    )
    data = result.to_json()
    data["provenance"] = provenance(
        "check", {"session": Path(session_dir), "calibration": Path(calibration_path)}
    )
    with commit_together() as staged:
        write_json_atomic(staged(out), data)
        if report_path is not None:
            write_ef_report(result, staged(report_path))
    return CheckRun(result, out, report_path)
