from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from scanner.app.plc.history import JobHistory


def test_job_is_recorded_and_survives_reopening(tmp_path: Path):
    db = tmp_path / "sub" / "history.sqlite"
    with JobHistory(db) as history:
        job_id = history.start(1, "check", sequence=7, parameter=0)
        history.finish(
            job_id,
            "done",
            passed=True,
            results_um=(1.5, None, 3.0),
            report_path=tmp_path / "r.json",
            artefacts=[tmp_path / "a.ply"],
        )
    with JobHistory(db) as history:
        (rec,) = history.latest(5)
    assert (rec.id, rec.command_name, rec.sequence, rec.state, rec.passed) == (
        job_id,
        "check",
        7,
        "done",
        True,
    )
    assert (rec.result1_um, rec.result2_um, rec.result3_um) == (1.5, None, 3.0)
    assert rec.artefacts == (str(tmp_path / "a.ply"),)
    assert rec.finished_at is not None
    mode = sqlite3.connect(db).execute("PRAGMA journal_mode").fetchone()[0]
    assert mode == "wal"


def test_running_jobs_become_interrupted(tmp_path: Path):
    db = tmp_path / "h.sqlite"
    with JobHistory(db) as history:
        done = history.start(1, "check", 1, 0)
        history.finish(done, "done", passed=True)
        running = history.start(2, "scan", 2, 1)
    with JobHistory(db) as history:
        assert history.mark_interrupted(7, "stopped") == [running]
        rec = history.get(running)
        assert rec is not None
        assert (rec.state, rec.error_code, rec.error_text) == ("interrupted", 7, "stopped")
        assert history.get(done).state == "done"  # type: ignore[union-attr]
        assert history.mark_interrupted(7, "again") == []


def test_finish_checks_its_input(tmp_path: Path):
    with JobHistory(tmp_path / "h.sqlite") as history:
        job_id = history.start(1, "check", 1, 0)
        with pytest.raises(ValueError, match="expected a final state"):
            history.finish(job_id, "running")
        with pytest.raises(ValueError, match="expected 3 results"):
            history.finish(job_id, "done", results_um=(1.0,))
        with pytest.raises(ValueError, match="expected limit >= 1"):
            history.latest(0)


def test_a_history_written_before_not_proven_is_read_and_extended(tmp_path: Path):
    db = tmp_path / "old.sqlite"
    with JobHistory(db) as history:
        old = history.start(1, "check", 1, 0)
        history.finish(old, "done", passed=False)
    con = sqlite3.connect(db)  # the first release's table: no not_proven column
    con.execute("ALTER TABLE jobs DROP COLUMN not_proven")
    con.commit()
    con.close()
    with JobHistory(db, read_only=True) as history:  # read as it is, nothing written
        assert history.get(old).not_proven is False  # type: ignore[union-attr]
    assert "not_proven" not in {
        r[1] for r in sqlite3.connect(db).execute("PRAGMA table_info(jobs)")
    }
    with JobHistory(db) as history:  # opened for writing: the column is added
        job = history.start(2, "scan", 2, 0)
        history.finish(job, "done", passed=False, not_proven=True)
        assert [r.not_proven for r in history.latest(5)] == [True, False]
