"""`scanner batch` on Dask: the same numbers as scan + measure alone, failures recorded while the
others go on, restarts that skip finished sessions, and a run on a real scheduler and worker.

The sessions are small renders of :class:`scanner.virtual_cell.analytic.TableStepScene` (a
table with a 20 mm block), 40 frames each so that ``scanner scan``'s default two extraction
processes really split them (two chunks), with a plan fitted to that scene.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import socket
import subprocess
import sys
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
from distributed import Client, LocalCluster

from scanner.app import stages
from scanner.app.batch import (
    RESULT_COLUMNS,
    BatchRequest,
    BatchState,
    ResultRow,
    _run_on_cluster,
    dask_client,
    expand_sessions,
    prepare,
)
from scanner.app.cli import build_parser, main
from scanner.app.commands import scan_options
from scanner.app.commands.batch import ProgressLine, compare_results
from scanner.core.fileio import InputError
from scanner.formats.calibration_file import write_calibration
from scanner.formats.clouds import read_cloud
from scanner.formats.layout import JobLayout
from scanner.scanning.pipeline import ScanOptions
from scanner.virtual_cell.analytic import (
    TableStepScene,
    table_step_plan,
    write_table_step_sweep,
)
from tests.conftest import REPO_ROOT

FRAMES = np.linspace(-30.0, 30.0, 40)


def write_plan(path: Path, tolerance: float = 0.2) -> Path:
    path.write_text(table_step_plan(tolerance, flatness_tolerance_mm=0.5), encoding="utf-8")
    return path


@dataclass(frozen=True)
class Scene:
    sessions: tuple[Path, ...]
    calibration: Path
    plan: Path


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Scene:
    root = tmp_path_factory.mktemp("batch")
    sessions = []
    for i in range(2):
        session, cal, _ = write_table_step_sweep(
            root / "sessions" / f"part{i}", x_mm=FRAMES, seed=i
        )
        sessions.append(session)
    calibration = root / "calibration.json"
    write_calibration(calibration, cal)
    return Scene(tuple(sessions), calibration, write_plan(root / "plan.toml"))


def batch(scene: Scene, sessions, out: Path, *extra: str) -> int:
    """``scanner batch`` in this process, on a local cluster of two workers."""
    argv = ["batch", *map(str, sessions), "--calibration", str(scene.calibration)]
    argv += ["--plan", str(scene.plan), "--out", str(out), "--quiet", "--dashboard", "127.0.0.1:0"]
    has_scheduler = "--scheduler" in extra
    return main([*argv, *([] if has_scheduler else ["--workers", "2"]), *extra])


def summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text(encoding="utf-8"))


def results(out: Path) -> list[dict[str, str]]:
    with open(out / "results.csv", encoding="utf-8", newline="") as fh:
        return list(csv.DictReader(fh))


def scan_then_measure_alone(scene: Scene, session: Path, folder: Path) -> tuple[Path, Path]:
    """``scanner scan SESSION --calibration C --out x.ply``, ``scanner measure x.ply --plan P
    --out m.json``, with the commands' defaults."""
    folder.mkdir(parents=True)
    cloud, report = folder / "x.ply", folder / "m.json"
    argv = ["scan", str(session), "--calibration", str(scene.calibration), "--out", str(cloud)]
    assert main([*argv, "--quiet"]) == 0
    assert main(["measure", str(cloud), "--plan", str(scene.plan), "--out", str(report)]) == 0
    return cloud, report


def broken_copy(session: Path, dest: Path) -> Path:
    """The session with one laser image gone."""
    shutil.copytree(session, dest)
    (dest / "images" / "laser_0005.png").unlink()
    return dest


# --------------------------------------------------------------------------------------------
# quick checks (no cluster)


def test_batch_scans_with_the_scan_commands_defaults_on_one_process():
    args = build_parser().parse_args(["scan", "s", "--calibration", "c.json", "--out", "x.ply"])
    cli = scan_options(args)
    batch_args = build_parser().parse_args(
        ["batch", "s", "--calibration", "c.json", "--plan", "p", "--out", "o"]
    )
    assert batch_args.mode == args.mode
    assert replace(cli, workers=1) == ScanOptions(mode=batch_args.mode, workers=1)
    flagged = build_parser().parse_args(
        ["scan", "s", "--calibration", "c.json", "--out", "x.ply", "--stretch-end-lines", "3"]
    )
    assert scan_options(flagged).stripe.end_lines == 3


def test_stripe_results_do_not_depend_on_the_number_of_workers(scene, tmp_path):
    one = stages.scan(
        [scene.sessions[0]],
        scene.calibration,
        tmp_path / "one.ply",
        options=ScanOptions(workers=1, chunk_frames=8),
    )
    two = stages.scan(
        [scene.sessions[0]],
        scene.calibration,
        tmp_path / "two.ply",
        options=ScanOptions(workers=2, chunk_frames=8),
    )
    a, b = one.result.cloud.point, two.result.cloud.point
    np.testing.assert_array_equal(a.positions.numpy(), b.positions.numpy())
    np.testing.assert_array_equal(a.intensity.numpy(), b.intensity.numpy())


def test_duplicate_session_names_are_refused_with_one_line(scene, tmp_path, capsys):
    other = tmp_path / "elsewhere" / scene.sessions[0].name
    shutil.copytree(scene.sessions[0], other)
    assert batch(scene, [scene.sessions[0], other], tmp_path / "out") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "part0" in err[0] and str(other) in err[0]
    assert not (tmp_path / "out").exists()


def test_bad_input_is_refused_before_any_work(scene, tmp_path, capsys):
    missing = tmp_path / "missing.json"
    argv = ["batch", str(scene.sessions[0]), "--calibration", str(missing)]
    assert main([*argv, "--plan", str(scene.plan), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.json" in err[0]
    camera_only = tmp_path / "camera_only.json"
    write_calibration(camera_only, replace(TableStepScene().calibration(), light_plane=None))
    argv = ["batch", str(scene.sessions[0]), "--calibration", str(camera_only)]
    assert main([*argv, "--plan", str(scene.plan), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "camera_only.json" in err[0] and "light plane" in err[0]
    with pytest.raises(InputError, match="no session folder matches"):
        expand_sessions([str(tmp_path / "nothing-*")])
    # Outputs inside a session would replace it.
    assert batch(scene, [scene.sessions[0]], scene.sessions[0].parent) == 2
    assert "would overwrite the input" in capsys.readouterr().err


def test_globs_are_expanded_in_order(scene):
    pattern = str(scene.sessions[0].parent / "part*")
    assert expand_sessions([pattern]) == sorted(scene.sessions)


def test_unreachable_scheduler_is_an_os_error_naming_it():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"  # nothing listens there
    with pytest.raises(OSError, match=address), dask_client(address, connect_timeout_s=1.0):
        pass


def test_progress_line_says_done_failed_running_and_time_left():
    line = ProgressLine.text(BatchState(10, 2, 5, 1, 2, 30.0))
    assert "5/10 done (2 reused)" in line and "1 failed" in line and "2 running" in line
    assert "left" in line
    assert "finished" in ProgressLine.text(BatchState(3, 0, 3, 0, 0, 5.0))
    # Before the first processed session nothing can be estimated.
    assert BatchState(4, 2, 2, 0, 2, 1.0).seconds_left is None


def test_compare_lists_the_sessions_whose_verdict_changed():
    def row(name: str, actual: str, status: str) -> ResultRow:
        return ResultRow(name, "mm", "20.0", actual, "", "-0.1", "0.1", status)

    before = {"a": (row("h", "20.05", "pass"),), "b": (row("h", "20.0", "pass"),)}
    now = {"a": (row("h", "20.25", "fail"),), "b": (row("h", "20.01", "pass"),), "c": ()}
    cmp = compare_results(before, now, Path("prev"))
    assert cmp.changed_sessions == ("a",)
    (change,) = cmp.changes
    assert (change.previous_verdict, change.verdict) == ("pass", "fail")
    assert change.moved == pytest.approx(0.2)
    assert cmp.only_now == ("c",)


def test_sessions_are_failed_not_waited_for_when_the_cluster_has_no_worker(scene, tmp_path):
    request = BatchRequest(scene.sessions, scene.calibration, scene.plan, tmp_path / "out")
    jobs = prepare(request).jobs
    settled: dict = {}
    with (
        LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        _run_on_cluster(client, jobs, settled, len(jobs), None, 0.05, no_worker_timeout_s=0.3)
    assert sorted(settled) == sorted(s.name for s in scene.sessions)
    assert all(not o.ok and "no Dask worker" in o.reason for o in settled.values())


# --------------------------------------------------------------------------------------------
# batches on a local cluster


@pytest.mark.slow
def test_results_are_those_of_scan_then_measure_on_each_session_alone(scene, tmp_path):
    out = tmp_path / "out"
    assert batch(scene, scene.sessions, out) == 0
    rows = results(out)
    assert list(rows[0]) == list(RESULT_COLUMNS)
    s = summary(out)
    assert s["sessions"] == 2 and s["ok"] == 2 and s["failed"] == []
    assert s["cluster"]["workers"] == 2 and s["cluster"]["local"]
    for session in scene.sessions:
        layout = JobLayout.of(out / session.name)
        cloud, report = scan_then_measure_alone(scene, session, tmp_path / "alone" / session.name)
        alone, batched = read_cloud(cloud).point, read_cloud(layout.cloud).point
        np.testing.assert_array_equal(alone.positions.numpy(), batched.positions.numpy())
        np.testing.assert_array_equal(alone.intensity.numpy(), batched.intensity.numpy())
        # The report's table, number for number (the CSV holds every digit).
        csv_alone = report.with_suffix(".csv").read_text(encoding="utf-8")
        assert layout.measure.with_suffix(".csv").read_text(encoding="utf-8") == csv_alone
        assert layout.measure.with_suffix(".html").is_file()
        m_alone = json.loads(report.read_text(encoding="utf-8"))["measurements"]
        m_batch = json.loads(layout.measure.read_text(encoding="utf-8"))["measurements"]
        assert m_batch == m_alone
        with open(report.with_suffix(".csv"), encoding="utf-8", newline="") as fh:
            expected = [
                {"session": session.name, **{k: r[k] for k in RESULT_COLUMNS[1:]}}
                for r in csv.DictReader(fh)
            ]
        assert [r for r in rows if r["session"] == session.name] == expected


@pytest.mark.slow
def test_a_failing_session_is_recorded_and_the_others_go_on(scene, tmp_path, capsys):
    broken = broken_copy(scene.sessions[0], tmp_path / "in" / "no_image")
    # A sweep that stops before the block: the plan's "top" region holds no point.
    short, _, _ = write_table_step_sweep(
        tmp_path / "in" / "short", x_mm=np.linspace(-30.0, -16.0, 8), seed=7
    )
    sessions = [scene.sessions[0], broken, short, scene.sessions[1]]
    out = tmp_path / "out"
    assert batch(scene, sessions, out) == 1
    s = summary(out)
    assert s["sessions"] == 4 and s["ok"] == 2
    reasons = {f["session"]: f["reason"] for f in s["failed"]}
    assert set(reasons) == {"no_image", "short"}
    assert "laser_0005.png" in reasons["no_image"] and "frames.csv" in reasons["no_image"]
    assert "'top'" in reasons["short"] and "too few points" in reasons["short"]
    assert all("\n" not in r for r in reasons.values())
    rows = results(out)
    by_session = {name: [r for r in rows if r["session"] == name] for name in reasons}
    assert [r["status"] for r in by_session["no_image"]] == ["error", "error"]
    assert [r["status"] for r in by_session["short"]] == ["error", "pass"]  # table flatness
    for good in (scene.sessions[0], scene.sessions[1]):
        assert [r["status"] for r in rows if r["session"] == good.name] == ["pass", "pass"]
    assert not JobLayout.of(out / "no_image").measure.exists()
    assert "FAILED no_image" in capsys.readouterr().err


@pytest.mark.slow
def test_restart_skips_complete_sessions_unless_redo(scene, tmp_path, capsys):
    out = tmp_path / "out"
    assert batch(scene, scene.sessions, out) == 0
    first, second = (JobLayout.of(out / s.name) for s in scene.sessions)
    stamp = first.cloud.stat().st_mtime_ns
    # Stopped while the second session was being measured: its cloud is there, not its report.
    second.measure.with_suffix(".html").unlink()
    second.measure.unlink()
    assert batch(scene, scene.sessions, out) == 0
    s = summary(out)
    assert (s["processed"], s["reused"], s["ok"]) == (1, 1, 2)
    assert first.cloud.stat().st_mtime_ns == stamp
    assert second.measure.with_suffix(".html").is_file()
    assert len(results(out)) == 4
    # Every session again with --redo.
    assert batch(scene, scene.sessions, out, "--redo") == 0
    assert summary(out)["processed"] == 2
    assert first.cloud.stat().st_mtime_ns != stamp
    # Another plan in the same folder is refused: old and new results would mix.
    tighter = write_plan(tmp_path / "tighter.toml", tolerance=0.01)
    argv = ["batch", *map(str, scene.sessions), "--calibration", str(scene.calibration)]
    capsys.readouterr()
    assert main([*argv, "--plan", str(tighter), "--out", str(out), "--quiet"]) == 2
    assert "batch.json" in capsys.readouterr().err


@pytest.mark.slow
def test_compare_reports_verdicts_that_changed_and_how_far_values_moved(scene, tmp_path):
    before = tmp_path / "before"
    assert batch(scene, scene.sessions, before) == 0
    tighter = write_plan(tmp_path / "tighter.toml", tolerance=0.01)
    after = tmp_path / "after"
    tight_scene = replace(scene, plan=tighter)
    assert batch(tight_scene, scene.sessions, after, "--compare", str(before)) == 0
    with open(after / "compare.csv", encoding="utf-8", newline="") as fh:
        changes = list(csv.DictReader(fh))
    assert {c["session"] for c in changes} == {s.name for s in scene.sessions}
    height = [c for c in changes if c["name"] == "step height"]
    assert all((c["previous_verdict"], c["verdict"]) == ("pass", "fail") for c in height)
    assert all(float(c["moved"]) == 0.0 for c in changes)  # same clouds, other tolerance


# --------------------------------------------------------------------------------------------
# a real scheduler and worker


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=20)


@pytest.mark.slow
def test_batch_runs_on_a_dask_scheduler_and_worker(scene, tmp_path):
    dask = Path(sys.executable).parent / "dask"
    if not dask.is_file():
        pytest.skip(f"{dask} not installed (pip install -e .)")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    logs = tmp_path / "logs"
    logs.mkdir()
    scheduler_args = [str(dask), "scheduler", "--host", "127.0.0.1", "--port", str(port)]
    scheduler_args += ["--dashboard-address", f"127.0.0.1:{_free_port()}"]
    worker_args = [str(dask), "worker", address, "--nworkers", "1", "--nthreads", "1"]
    worker_args += ["--host", "127.0.0.1", "--no-dashboard", "--death-timeout", "60"]
    worker_args += ["--local-directory", str(tmp_path / "dask-worker")]
    procs: list[subprocess.Popen] = []
    with ExitStack() as stack:
        stack.callback(lambda: [_stop(p) for p in reversed(procs)])
        scheduler_log = stack.enter_context(open(logs / "scheduler.log", "w"))
        worker_log = stack.enter_context(open(logs / "worker.log", "w"))
        for args, log in ((scheduler_args, scheduler_log), (worker_args, worker_log)):
            procs.append(
                subprocess.Popen(
                    args, stdout=subprocess.DEVNULL, stderr=log, cwd=REPO_ROOT, env=env
                )
            )
        out = tmp_path / "out"
        code = batch(scene, scene.sessions, out, "--scheduler", address)
        assert code == 0, (logs / "worker.log").read_text()[-2000:]
        s = summary(out)
        assert s["ok"] == 2 and s["cluster"]["scheduler"] == address
        assert (s["cluster"]["workers"], s["cluster"]["threads"]) == (1, 1)
        assert not s["cluster"]["local"]
        assert len(results(out)) == 4
        for session in scene.sessions:
            assert JobLayout.of(out / session.name).measure.with_suffix(".html").is_file()
