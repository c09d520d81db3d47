from __future__ import annotations

import datetime as dt
import json
import os
import threading
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import open3d as o3d
import pytest

from metrology.ef_check import EFCheckResult, EFMeasurement
from scanner.app import stages
from scanner.app.plc.config import (
    CalibrationGate,
    CheckTolerances,
    PlcConfig,
    Recipe,
    StorageConfig,
)
from scanner.app.plc.jobs import (
    FolderSource,
    JobCancelled,
    JobContext,
    JobError,
    PipelineJobs,
    VirtualCellSource,
    calibration_gate,
    ef_tolerances,
    install_calibration,
)
from scanner.app.plc.registers import ErrorCode
from scanner.formats.calibration_file import CalibrationQuality, write_calibration
from scanner.formats.clouds import write_cloud
from scanner.formats.layout import JobLayout
from scanner.formats.meshes import write_mesh
from scanner.scanning.planning import PlanConfig
from scanner.virtual_cell.parts import SAMPLE_PARTS, boss_part, scan_part
from tests.scanner.formats.test_calibration_file import paper_calibration


def _session(root: Path, name: str, kind: str, mtime: float | None) -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    if mtime is not None:
        marker = folder / "session.json"
        marker.write_text(json.dumps({"format": "scan-session/1", "kind": kind}), "utf-8")
        os.utime(marker, (mtime, mtime))
    return folder


def _ctx(tmp: Path, config: PlcConfig, parameter: int = 0) -> JobContext:
    return JobContext(1, 1, parameter, tmp / "job", config)


def test_folder_source_takes_the_newest_complete_session_of_the_kind(tmp_path: Path):
    root = tmp_path / "drop"
    _session(root, "a", "check", 1000.0)
    newest = _session(root, "b", "check", 2000.0)
    _session(root, "c", "check", None)  # being written: no session.json yet
    _session(root, "d", "sweep", 3000.0)
    source = FolderSource(root)
    assert source.newest("check") == newest
    ctx = _ctx(tmp_path, PlcConfig())
    with pytest.raises(JobError) as err:
        source.acquire("calibration", ctx)
    assert err.value.code == ErrorCode.NO_SESSION
    assert FolderSource(tmp_path / "absent").newest("check") is None


def test_install_calibration_keeps_the_old_one(tmp_path: Path):
    current = tmp_path / "cal" / "calibration.json"
    first = tmp_path / "first.json"
    first.write_text("1", "utf-8")
    assert install_calibration(first, current) is None
    second = tmp_path / "second.json"
    second.write_text("2", "utf-8")
    now = dt.datetime(2026, 1, 2, 3, 4, 5, tzinfo=dt.timezone.utc)
    kept = install_calibration(second, current, now=now)
    assert kept == current.with_name("calibration-20260102T030405.json")
    assert kept.read_text("utf-8") == "1"
    assert current.read_text("utf-8") == "2"
    third = tmp_path / "third.json"
    third.write_text("3", "utf-8")
    assert install_calibration(third, current, now=now).name == "calibration-20260102T030405-1.json"


def test_check_passes_only_within_every_tolerance():
    tol = ef_tolerances(CheckTolerances(max_mean_abs_um=10, max_abs_um=20, max_o_spread_um=30))

    def result(errors_mm: list[float], o_spread_mm: float) -> EFCheckResult:
        measurements = [
            EFMeasurement(i, True, length_mm=100.0 + e, error_mm=e) for i, e in enumerate(errors_mm)
        ]
        o = np.array([[0.0, 0.0, 0.0], [o_spread_mm * 2, 0.0, 0.0]])
        return EFCheckResult(100.0, measurements, o_positions_base=o, tolerances=tol)

    assert result([0.0, -0.020], 0.030).passed  # mean 0.010, largest 0.020, spread 0.030
    assert not result([0.0, -0.0202], 0.030).passed
    assert not result([0.0, 0.0], 0.031).passed
    assert not EFCheckResult(100.0, [], tolerances=tol).passed  # nothing measured: not proven


def test_pipeline_jobs_say_why_they_cannot_start(tmp_path: Path):
    config = PlcConfig(
        storage=StorageConfig(calibration=str(tmp_path / "none.json")),
        recipes=[Recipe(number=1, name="a", plan="p")],
    )
    jobs = PipelineJobs(config, source=FolderSource(tmp_path))
    with pytest.raises(JobError) as err:
        jobs.scan(_ctx(tmp_path, config, parameter=5))
    assert err.value.code == ErrorCode.UNKNOWN_RECIPE
    with pytest.raises(JobError) as err:
        jobs.recalibration_check(_ctx(tmp_path, config))
    assert err.value.code == ErrorCode.NO_CALIBRATION
    with pytest.raises(JobError) as err:
        jobs.full_calibration(_ctx(tmp_path, config))
    assert err.value.code == ErrorCode.NO_SESSION


def test_cancellation_is_raised_at_the_next_check(tmp_path: Path):
    ctx = JobContext(1, 1, 0, tmp_path, PlcConfig(), cancel=threading.Event())
    ctx.check_cancelled()
    ctx.cancel.set()
    with pytest.raises(JobCancelled):
        ctx.check_cancelled()


def test_calibration_gate_judges_the_quality_record():
    gate = CalibrationGate(
        max_intrinsics_rms_px=0.5, max_light_plane_rms_um=50, max_hand_eye_rms_px=1
    )
    good = {
        "intrinsics": {"rms_px": 0.2},
        "light_plane": {"rms_mm": 0.012},
        "hand_eye": {"rms_px": 0.4},
    }
    assert calibration_gate(CalibrationQuality.from_json(good), gate) == (
        True,
        "",
        pytest.approx(12.0),
    )
    bad = CalibrationQuality.from_json({**good, "light_plane": {"rms_mm": 0.08}})
    passed, reason, plane_um = calibration_gate(bad, gate)
    assert not passed and "light-plane RMS 80 um over the limit 50 um" in reason
    assert plane_um == pytest.approx(80.0)
    partial = CalibrationQuality.from_json({"intrinsics": {"rms_px": 0.2}})
    passed, reason, _ = calibration_gate(partial, gate)
    assert not passed and "missing" in reason


def _fake_pipeline(monkeypatch: pytest.MonkeyPatch, quality: dict, rows: list) -> None:
    """Stand-in stages: the jobs' own logic (gate, install, figures) is what is tested here."""

    def calibrate(session: Path, out: Path, **_: object) -> SimpleNamespace:
        Path(out).write_text("new", "utf-8")
        return SimpleNamespace(
            quality=CalibrationQuality.from_json(quality),
            calibration_path=out,
            report_path=None,
            result=SimpleNamespace(calibration=SimpleNamespace(light_plane=object())),
        )

    def scan(sessions: list[Path], calibration: Path, out: Path, **_: object) -> None:
        Path(out).write_text("ply", "utf-8")

    report = SimpleNamespace(rows=rows, passed=True, verdict="pass", summary=lambda: "PASS")

    def measure(cloud: Path, plan: Path, out: Path, **_: object) -> SimpleNamespace:
        for path in (out, out.with_suffix(".html")):
            path.write_text("{}", "utf-8")
        return SimpleNamespace(result=report, files=stages.ReportFiles.beside(out))

    monkeypatch.setattr(stages, "calibrate", calibrate)
    monkeypatch.setattr(stages, "scan", scan)
    monkeypatch.setattr(stages, "measure", measure)


GOOD = {"intrinsics": {"rms_px": 0.2}, "light_plane": {"rms_mm": 0.01}, "hand_eye": {"rms_px": 0.3}}


@pytest.mark.parametrize("light_plane_mm", [0.01, 0.5])
def test_full_calibration_replaces_the_current_one_only_when_it_passes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, light_plane_mm: float
):
    quality = {**GOOD, "light_plane": {"rms_mm": light_plane_mm}}
    _fake_pipeline(monkeypatch, quality, [])
    current = tmp_path / "cal" / "calibration.json"
    current.parent.mkdir()
    current.write_text("old", "utf-8")
    _session(tmp_path / "drop", "s1", "calibration", 1000.0)
    config = PlcConfig(storage=StorageConfig(calibration=str(current)))
    jobs = PipelineJobs(config, source=FolderSource(tmp_path / "drop"))
    ctx = _ctx(tmp_path, config)
    ctx.work_dir.mkdir()
    outcome = jobs.full_calibration(ctx)
    assert outcome.results_um[0] == pytest.approx(light_plane_mm * 1000)
    kept = sorted(current.parent.glob("calibration-*.json"))
    if light_plane_mm < 0.1:
        assert outcome.passed and outcome.error == ErrorCode.NONE
        assert current.read_text("utf-8") == "new"
        assert [k.read_text("utf-8") for k in kept] == ["old"]
    else:
        assert not outcome.passed and outcome.error == ErrorCode.QUALITY_GATE
        assert "light-plane RMS" in outcome.message
        assert current.read_text("utf-8") == "old" and kept == []


def _scan_recipe_config(tmp_path: Path) -> PlcConfig:
    """A current calibration, one sweep session dropped, recipe 3 measuring the modern plan."""
    current = tmp_path / "calibration.json"
    current.write_text("{}", "utf-8")
    _session(tmp_path / "drop", "s1", "sweep", 1000.0)
    return PlcConfig(
        storage=StorageConfig(calibration=str(current)),
        recipes=[Recipe(number=3, name="r", plan="modern_sweep")],
    )


def test_scan_job_reports_the_plans_first_figures_in_micrometres(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    rows = [SimpleNamespace(actual=25.0123), SimpleNamespace(actual=None)]
    _fake_pipeline(monkeypatch, GOOD, rows)
    config = _scan_recipe_config(tmp_path)
    jobs = PipelineJobs(config, source=FolderSource(tmp_path / "drop"))
    ctx = _ctx(tmp_path, config, parameter=3)
    ctx.work_dir.mkdir()
    outcome = jobs.scan(ctx)
    assert outcome.passed
    assert outcome.results_um == (pytest.approx(25012.3), None, None)
    assert ctx.session_path == tmp_path / "drop" / "s1"
    assert outcome.report_path is not None and outcome.report_path.is_file()


def _cancelling_stage(ctx: JobContext, cancel_at: int, done: list[int]):
    """A stand-in stage that runs 10 steps (chunks, images, frames), records each in
    ``done``, has the service cancel the job at step ``cancel_at`` and calls the check the
    job gave it after every step."""

    def stage(*_: object, **kwargs: object) -> None:
        check = kwargs["check_cancelled"]
        for step in range(10):
            done.append(step)
            if step == cancel_at:
                ctx.cancel.set()  # the service cancels while the stage runs
            check()  # type: ignore[operator]

    return stage


def test_a_scan_job_is_cancelled_inside_the_scan_stage(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """The scan stage gets the job's check: a thread-worker service's shutdown stops the
    extraction at its next chunk, not after the whole sweep."""
    _fake_pipeline(monkeypatch, GOOD, [SimpleNamespace(actual=1.0)])
    config = _scan_recipe_config(tmp_path)
    ctx = _ctx(tmp_path, config, parameter=3)
    ctx.work_dir.mkdir()
    chunks_done: list[int] = []
    monkeypatch.setattr(stages, "scan", _cancelling_stage(ctx, 3, chunks_done))
    with pytest.raises(JobCancelled):
        PipelineJobs(config, source=FolderSource(tmp_path / "drop")).scan(ctx)
    assert chunks_done == [0, 1, 2, 3]


def test_a_calibration_job_is_cancelled_inside_the_calibration(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """The calibrate stage gets the job's check: a cancelled calibration stops at its next
    image and installs nothing."""
    current = tmp_path / "cal" / "calibration.json"
    current.parent.mkdir()
    current.write_text("old", "utf-8")
    _session(tmp_path / "drop", "s1", "calibration", 1000.0)
    config = PlcConfig(storage=StorageConfig(calibration=str(current)))
    ctx = _ctx(tmp_path, config)
    ctx.work_dir.mkdir()
    images_done: list[int] = []
    monkeypatch.setattr(stages, "calibrate", _cancelling_stage(ctx, 4, images_done))
    with pytest.raises(JobCancelled):
        PipelineJobs(config, source=FolderSource(tmp_path / "drop")).full_calibration(ctx)
    assert images_done == [0, 1, 2, 3, 4]
    assert current.read_text("utf-8") == "old"


def test_a_check_job_is_cancelled_inside_the_ef_check(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """The check stage gets the job's check: a thread-worker service's shutdown stops the EF
    check at its next laser frame."""
    current = tmp_path / "calibration.json"
    current.write_text("{}", "utf-8")
    _session(tmp_path / "drop", "s1", "check", 1000.0)
    config = PlcConfig(storage=StorageConfig(calibration=str(current)))
    ctx = _ctx(tmp_path, config)
    ctx.work_dir.mkdir()
    frames_done: list[int] = []
    monkeypatch.setattr(stages, "check", _cancelling_stage(ctx, 1, frames_done))
    with pytest.raises(JobCancelled):
        PipelineJobs(config, source=FolderSource(tmp_path / "drop")).recalibration_check(ctx)
    assert frames_done == [0, 1]


def test_a_virtual_cell_capture_is_cancelled_inside_the_rendering(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """The virtual cell's capture gets the job's check: a thread-worker service's shutdown
    stops the rendering at its next frame, not after the whole session."""
    config = PlcConfig()
    ctx = _ctx(tmp_path, config)
    ctx.work_dir.mkdir()
    frames_done: list[int] = []
    monkeypatch.setattr(stages, "simulate", _cancelling_stage(ctx, 2, frames_done))
    with pytest.raises(JobCancelled):
        VirtualCellSource().acquire("check", ctx)
    assert frames_done == [0, 1, 2]


def test_scan_job_with_a_nominal_inspects_the_cloud_against_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """A recipe naming a nominal mesh: the scan job inspects its cloud (the real stage) and
    returns the largest deviation, the deviation RMS and the alignment RMS in µm."""
    rng = np.random.default_rng(7)
    bump = (np.array([30.0, 30.0, 30.0]), 0.25, 6.0)
    scan_truth = scan_part(boss_part(), rng, count=60_000, bumps=[bump])
    nominal = write_mesh(tmp_path / "part.stl", boss_part())

    def scan(sessions: list[Path], calibration: Path, out: Path, **_: object) -> None:
        cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(scan_truth.points_cloud))
        write_cloud(out, cloud)

    monkeypatch.setattr(stages, "scan", scan)
    current = tmp_path / "calibration.json"
    current.write_text("{}", "utf-8")
    _session(tmp_path / "drop", "s1", "sweep", 1000.0)
    config = PlcConfig(
        storage=StorageConfig(calibration=str(current)),
        recipes=[Recipe(number=4, name="part", nominal=str(nominal))],
    )
    jobs = PipelineJobs(config, source=FolderSource(tmp_path / "drop"))
    ctx = _ctx(tmp_path, config, parameter=4)
    ctx.work_dir.mkdir()
    outcome = jobs.scan(ctx)
    largest_um, rms_um, alignment_um = outcome.results_um
    assert not outcome.passed  # over 1 % of the points in the bump lie outside +-0.1 mm
    assert largest_um is not None and 240.0 < largest_um < 340.0  # bump peak + noise tail
    assert rms_um is not None and 20.0 < rms_um < 40.0
    assert alignment_um is not None and 18.0 < alignment_um < 35.0  # noise 20 µm + bump
    job = JobLayout.of(ctx.work_dir)
    assert job.inspection.is_file() and job.deviations.is_file()
    assert json.loads(job.inspection.read_text("utf-8"))["verdict"] == "fail"
    assert "inspection fail" in outcome.message


def test_a_recipe_needs_a_plan_or_a_nominal():
    with pytest.raises(ValueError, match="neither"):
        Recipe(number=1, name="empty")


def test_a_recalibration_keeps_the_installed_laser_origin(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """A laser origin given from the sensor's drawing is not in a calibration session: the
    PLC's recalibration carries the installed one over, for the new plane to be checked on."""
    given: list[object] = []
    _fake_pipeline(monkeypatch, GOOD, [])
    fake = stages.calibrate

    def calibrate(session: Path, out: Path, **kwargs: object) -> SimpleNamespace:
        given.append(kwargs.get("laser_origin_cam_mm"))
        return fake(session, out)

    monkeypatch.setattr(stages, "calibrate", calibrate)
    current = tmp_path / "calibration.json"
    installed = replace(paper_calibration(), laser_origin_cam=np.array([150.0, 2.0, -5.0]))
    write_calibration(current, installed)
    _session(tmp_path / "drop", "s1", "calibration", 1000.0)
    config = PlcConfig(storage=StorageConfig(calibration=str(current)))
    jobs = PipelineJobs(config, source=FolderSource(tmp_path / "drop"))
    ctx = _ctx(tmp_path, config)
    ctx.work_dir.mkdir()
    assert jobs.full_calibration(ctx).passed
    assert given == [(150.0, 2.0, -5.0)]
    # One the installed calibration estimated itself is not carried: the new session's wins.
    record = {**installed.quality.record, "laser_origin_source": "estimated from shadow edges"}
    write_calibration(
        current, replace(installed, quality=replace(installed.quality, record=record))
    )
    ctx = _ctx(tmp_path, config)
    ctx.work_dir.mkdir(exist_ok=True)
    assert jobs.full_calibration(ctx).passed
    assert given == [(150.0, 2.0, -5.0), None]


def test_a_recipe_with_planned_sweeps_runs_the_full_object_job(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """A recipe naming a part and its plan: the virtual cell captures the planned sweeps with
    the part where the plan put it, the scan merges them without the table (ICP on), and the
    cloud is inspected against the part."""
    part = write_mesh(tmp_path / "stepped.stl", SAMPLE_PARTS["stepped"]())
    plan_dir = tmp_path / "plan"
    config_plan = PlanConfig(step_mm=4.0, samples=4000)
    planned = stages.plan_scan(
        part, plan_dir, cell="modern", part_at_mm=(590.0, 110.0, 0.0), config=config_plan
    )
    seen: dict[str, object] = {}

    def simulate(cell, out: Path, **kwargs: object):
        seen["cell"], seen["sweep_paths"] = cell, kwargs["sweep_paths"]
        (out / "sweep").mkdir(parents=True)
        (out / "sweep" / "session.json").write_text("{}", "utf-8")

    rng = np.random.default_rng(11)
    truth = scan_part(SAMPLE_PARTS["stepped"](), rng, count=40_000)

    def scan(sessions: list[Path], calibration: Path, out: Path, **kwargs: object) -> None:
        seen["options"] = kwargs["options"]
        write_cloud(out, o3d.t.geometry.PointCloud(o3d.core.Tensor(truth.points_cloud)))

    monkeypatch.setattr(stages, "simulate", simulate)
    monkeypatch.setattr(stages, "scan", scan)
    current = tmp_path / "calibration.json"
    current.write_text("{}", "utf-8")
    recipe = Recipe(number=5, name="full", nominal=str(part), sweeps=str(plan_dir))
    config = PlcConfig(storage=StorageConfig(calibration=str(current)), recipes=[recipe])
    jobs = PipelineJobs(config, source=VirtualCellSource("modern"))
    ctx = _ctx(tmp_path, config, parameter=5)
    ctx.work_dir.mkdir()
    outcome = jobs.scan(ctx)
    (placed,) = seen["cell"].sweep.objects
    assert placed.type == "mesh" and Path(placed.path) == part.resolve()
    np.testing.assert_allclose(placed.center_mm, planned.base_from_part[:3, 3], atol=1e-9)
    paths = seen["sweep_paths"]
    assert len(paths) == len(planned.plan.sweeps)
    assert sum(len(p) for p in paths) == planned.plan.frames
    options = seen["options"]
    assert options.icp and options.table_z_mm == pytest.approx(0.0, abs=1e-9)
    assert options.isolated_radius_mm is not None
    lo, hi = planned.plan.points_base.min(axis=0), planned.plan.points_base.max(axis=0)
    assert np.all(np.asarray(options.region_mm[0]) < lo) and np.all(
        np.asarray(options.region_mm[1]) > hi
    )
    assert JobLayout.of(ctx.work_dir).inspection.is_file()
    assert outcome.results_um[1] is not None and outcome.results_um[1] < 40.0  # rms, 20 µm noise


def test_planned_sweeps_need_the_part_as_nominal(tmp_path: Path):
    with pytest.raises(ValueError, match="needs the part as nominal"):
        Recipe(number=1, name="x", plan="modern_sweep", sweeps=str(tmp_path))
