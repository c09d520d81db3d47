"""`scanner history` reads a job history without touching it, refuses other files, and speaks
JSON (issue #17, items 6 and 16)."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import pytest

from scanner.app.cli import main
from scanner.app.plc.history import JobHistory
from scanner.core.fileio import InputError

pytestmark = pytest.mark.timeout(60)


def _history(path: Path) -> list[int]:
    """A closed history with a finished job and a running one; their ids, oldest first."""
    with JobHistory(path) as h:
        first = h.start(1, "check", 7, 0)
        h.finish(first, "done", passed=True, results_um=(1.5, None, 3.0), artefacts=["a.ply"])
        second = h.start(2, "scan", 8, 3)
    return [first, second]


def _unrelated(path: Path) -> None:
    db = sqlite3.connect(path)
    db.execute("CREATE TABLE parts (id INTEGER PRIMARY KEY, name TEXT)")
    db.execute("INSERT INTO parts (name) VALUES ('bracket')")
    db.commit()
    db.close()


def _files_beside(path: Path) -> list[str]:
    return sorted(p.name for p in path.parent.iterdir())


@pytest.mark.parametrize("kind", ["sqlite-without-jobs", "not-sqlite", "empty"])
def test_history_refuses_a_file_that_is_not_a_job_history_and_leaves_it_alone(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str
):
    path = tmp_path / "unrelated.sqlite"
    if kind == "sqlite-without-jobs":
        _unrelated(path)
    elif kind == "not-sqlite":
        path.write_bytes(b"PK\x03\x04 this is a zip file, not a database\n" * 40)
    else:
        path.write_bytes(b"")
    before, files = path.read_bytes(), _files_beside(path)
    assert main(["history", "--db", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert str(path) in err and "not a job history" in err
    assert path.read_bytes() == before  # no table added, not switched to WAL
    assert _files_beside(path) == files  # no -wal or -shm beside it either
    if kind == "sqlite-without-jobs":
        db = sqlite3.connect(path)
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "delete"
        tables = [r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")]
        db.close()
        assert tables == ["parts"]


def test_history_json_lists_the_records_newest_first(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    db = tmp_path / "history.sqlite"
    first, second = _history(db)
    before = db.read_bytes()
    assert main(["history", "--db", str(db), "--json"]) == 0
    records = json.loads(capsys.readouterr().out)
    assert [r["id"] for r in records] == [second, first]
    newest, oldest = records
    assert (newest["command_name"], newest["sequence"], newest["parameter"]) == ("scan", 8, 3)
    assert (newest["state"], newest["passed"], newest["finished_at"]) == ("running", None, None)
    assert (oldest["state"], oldest["passed"]) == ("done", True)
    assert (oldest["result1_um"], oldest["result2_um"], oldest["result3_um"]) == (1.5, None, 3.0)
    assert oldest["artefacts"] == ["a.ply"]
    assert set(oldest) >= {"started_at", "error_code", "error_text", "report_path"}
    assert main(["history", "--db", str(db), "--json", "--limit", "1"]) == 0
    assert [r["id"] for r in json.loads(capsys.readouterr().out)] == [second]
    assert db.read_bytes() == before


def test_history_json_of_an_empty_history_is_an_empty_list(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    db = tmp_path / "history.sqlite"
    JobHistory(db).close()
    assert main(["history", "--db", str(db), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == []


def test_history_opens_read_only(tmp_path: Path):
    db = tmp_path / "history.sqlite"
    ids = _history(db)
    before = db.read_bytes()
    with JobHistory(db, read_only=True) as h:
        assert [r.id for r in h.latest(5)] == ids[::-1]
        with pytest.raises(sqlite3.OperationalError, match="readonly"):
            h.start(1, "check", 9, 0)
        with pytest.raises(sqlite3.OperationalError, match="readonly"):
            h.mark_interrupted(7, "a reader must not mark the service's job interrupted")
    assert db.read_bytes() == before
    with JobHistory(db) as h:  # nothing was changed: the running job is still running
        assert h.get(ids[1]).state == "running"  # type: ignore[union-attr]


def test_read_only_history_refuses_a_missing_file(tmp_path: Path):
    with pytest.raises(InputError, match="job history not found"):
        JobHistory(tmp_path / "absent.sqlite", read_only=True)
    assert not (tmp_path / "absent.sqlite").exists()


def test_a_writable_history_refuses_a_foreign_database(tmp_path: Path):
    path = tmp_path / "unrelated.sqlite"
    _unrelated(path)
    before = path.read_bytes()
    with pytest.raises(InputError, match=r"not a job history .*its tables: parts"):
        JobHistory(path)
    assert path.read_bytes() == before
