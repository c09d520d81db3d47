"""The job history: every job the PLC service accepts, in one SQLite file (WAL mode).

A job is inserted as ``running`` before the PLC sees its acknowledgement, and updated once
when it ends (``done``, ``error``) with its figures, error code and text and the paths of its
report and artefacts. Commits are synchronous (``synchronous=FULL``), so a record survives a
killed process or a power cut. On start, :meth:`JobHistory.mark_interrupted` turns any record
still ``running`` (the service died under it) into ``interrupted``: none is left running.

``JobHistory(path, read_only=True)`` (what ``scanner history`` uses) opens the file with the
SQLite URI ``mode=ro``: it never creates, converts or writes anything, and it refuses a file
that is not a job history. Either way a file that is not a job history, or one that cannot be
created or opened, raises :class:`~scanner.core.fileio.InputError` naming the file.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import sqlite3
import threading
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from scanner.core.fileio import InputError

__all__ = ["JOB_STATES", "JobHistory", "JobRecord"]

log = logging.getLogger(__name__)

#: The states a record can be in.
JOB_STATES = ("running", "done", "error", "interrupted")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    command INTEGER NOT NULL,
    command_name TEXT NOT NULL,
    sequence INTEGER NOT NULL,
    parameter INTEGER NOT NULL DEFAULT 0,
    state TEXT NOT NULL CHECK (state IN ('running', 'done', 'error', 'interrupted')),
    started_at TEXT NOT NULL,
    finished_at TEXT,
    passed INTEGER,
    result1_um REAL,
    result2_um REAL,
    result3_um REAL,
    error_code INTEGER NOT NULL DEFAULT 0,
    error_text TEXT NOT NULL DEFAULT '',
    session_path TEXT,
    report_path TEXT,
    artefacts TEXT NOT NULL DEFAULT '[]',
    not_proven INTEGER NOT NULL DEFAULT 0
);
"""

#: Columns added after the first release, with their type and default: a history written
#: before them gains them when opened for writing, and reads as their default when opened
#: read-only.
_LATER_COLUMNS = {"not_proven": ("INTEGER", "0")}

_COLUMNS = (
    "id, command, command_name, sequence, parameter, state, started_at, finished_at, passed, "
    "result1_um, result2_um, result3_um, error_code, error_text, session_path, report_path, "
    "artefacts"
)
_COLUMN_NAMES = frozenset(c.strip() for c in _COLUMNS.split(","))


def _now() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds")


@dataclass(frozen=True)
class JobRecord:
    """One row of the history."""

    id: int
    command: int
    command_name: str
    sequence: int
    parameter: int
    state: str
    started_at: str
    finished_at: str | None
    passed: bool | None
    result1_um: float | None
    result2_um: float | None
    result3_um: float | None
    error_code: int
    error_text: str
    session_path: str | None
    report_path: str | None
    artefacts: tuple[str, ...]
    not_proven: bool = False
    """Guarded acceptance could not prove conformity (status bit 7); ``passed`` is false."""

    @classmethod
    def _from_row(cls, row: Sequence) -> JobRecord:
        values = list(row)
        values[8] = None if values[8] is None else bool(values[8])
        values[16] = tuple(json.loads(values[16] or "[]"))
        values[17] = bool(values[17])
        return cls(*values)

    def to_dict(self) -> dict[str, Any]:
        """The record as a JSON-ready dictionary (``artefacts`` a list)."""
        data = asdict(self)
        data["artefacts"] = list(self.artefacts)
        return data


class JobHistory:
    """The SQLite job history (one file, WAL mode, safe to use from several threads).

    Parameters
    ----------
    path : path-like
        The database file; its folder is created. ``":memory:"`` for a throw-away history.
    read_only : bool
        Open an existing history for reading only (SQLite ``mode=ro``): nothing is created,
        converted (WAL) or written, and the write methods fail.

    Raises
    ------
    InputError
        The file is not a job history (not an SQLite database, or a database without the
        ``jobs`` table), or it cannot be created or opened (``read_only``: it does not exist).
    """

    def __init__(self, path: str | os.PathLike[str], *, read_only: bool = False) -> None:
        self.path = str(path)
        self.read_only = read_only
        self._lock = threading.Lock()
        self._db = self._open_read_only() if read_only else self._open_read_write()
        present = {r[1] for r in self._db.execute("PRAGMA table_info(jobs)")}
        # what a SELECT reads: every column, a later one as its default where the file lacks it
        self._select = ", ".join(
            [_COLUMNS]
            + [
                name if name in present else f"{default} AS {name}"
                for name, (_, default) in _LATER_COLUMNS.items()
            ]
        )

    def _open_read_only(self) -> sqlite3.Connection:
        path = Path(self.path)
        if not path.is_file():
            raise InputError(path, "job history not found")
        uri = f"{path.absolute().as_uri()}?mode=ro"
        try:
            db = sqlite3.connect(uri, uri=True, check_same_thread=False, isolation_level=None)
        except sqlite3.Error as exc:
            raise InputError(path, f"cannot open the job history ({exc})") from None
        try:
            db.execute("PRAGMA busy_timeout=5000")
            self._check_schema(db, require_jobs=True)
        except BaseException:
            db.close()
            raise
        return db

    def _open_read_write(self) -> sqlite3.Connection:
        memory = self.path == ":memory:"
        path = Path(self.path)
        try:
            if not memory:
                path.parent.mkdir(parents=True, exist_ok=True)
            db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        except OSError as exc:
            blocker = next((a for a in path.parents if a.exists() and not a.is_dir()), None)
            if blocker is not None:
                reason = f"its folder cannot be created: {blocker} is a file, not a folder"
            else:
                where = f": {exc.filename}" if exc.filename else ""
                reason = f"{exc.strerror or type(exc).__name__}{where}"
            raise InputError(path, f"cannot create the job history ({reason})") from None
        except sqlite3.Error as exc:
            raise InputError(path, f"cannot open the job history for writing ({exc})") from None
        try:
            self._check_schema(db, require_jobs=False)
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=FULL")
            db.execute("PRAGMA busy_timeout=5000")
            db.executescript(_SCHEMA)
            present = {r[1] for r in db.execute("PRAGMA table_info(jobs)")}
            for name, (kind, default) in _LATER_COLUMNS.items():
                if name not in present:
                    db.execute(
                        f"ALTER TABLE jobs ADD COLUMN {name} {kind} NOT NULL DEFAULT {default}"
                    )
        except sqlite3.Error as exc:
            db.close()
            raise InputError(path, f"cannot open the job history for writing ({exc})") from None
        except BaseException:
            db.close()
            raise
        return db

    def _check_schema(self, db: sqlite3.Connection, *, require_jobs: bool) -> None:
        """Refuse a file that is not a job history.

        A database without any table is accepted when ``require_jobs`` is false (a new history
        gets its table); one with tables but no ``jobs`` table of the right columns never is.
        """
        try:
            tables = sorted(
                r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")
            )
        except sqlite3.DatabaseError as exc:
            if isinstance(exc, sqlite3.OperationalError):  # locked, unreadable, ...
                raise InputError(self.path, f"cannot read the job history ({exc})") from None
            raise InputError(
                self.path, f"not a job history (not an SQLite database: {exc})"
            ) from None
        tables = [t for t in tables if not t.startswith("sqlite_")]
        if "jobs" not in tables:
            if not tables and not require_jobs:
                return
            has = f"its tables: {', '.join(tables)}" if tables else "it has no tables"
            raise InputError(
                self.path, f"not a job history (an SQLite database without a 'jobs' table; {has})"
            )
        columns = {r[1] for r in db.execute("PRAGMA table_info(jobs)")}
        missing = sorted(_COLUMN_NAMES - columns)
        if missing:
            raise InputError(
                self.path,
                f"not a job history (its 'jobs' table lacks the columns {', '.join(missing)})",
            )

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def __enter__(self) -> JobHistory:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self, command: int, command_name: str, sequence: int, parameter: int) -> int:
        """Insert a ``running`` job and return its id (committed when this returns)."""
        with self._lock:
            cur = self._db.execute(
                "INSERT INTO jobs (command, command_name, sequence, parameter, state, started_at)"
                " VALUES (?, ?, ?, ?, 'running', ?)",
                (command, command_name, sequence, parameter, _now()),
            )
            return int(cur.lastrowid or 0)

    def finish(
        self,
        job_id: int,
        state: str,
        *,
        passed: bool | None = None,
        not_proven: bool = False,
        results_um: Sequence[float | None] = (None, None, None),
        error_code: int = 0,
        error_text: str = "",
        session_path: str | os.PathLike[str] | None = None,
        report_path: str | os.PathLike[str] | None = None,
        artefacts: Sequence[str | os.PathLike[str]] = (),
    ) -> None:
        """Record how job ``job_id`` ended.

        Raises
        ------
        ValueError
            ``state`` is not a final state or ``results_um`` does not hold three values.
        """
        if state not in JOB_STATES[1:]:
            raise ValueError(f"expected a final state {JOB_STATES[1:]}, got {state!r}")
        if len(results_um) != 3:
            raise ValueError(f"expected 3 results, got {len(results_um)}")
        r1, r2, r3 = (None if r is None else float(r) for r in results_um)
        with self._lock:
            self._db.execute(
                "UPDATE jobs SET state=?, finished_at=?, passed=?, result1_um=?, result2_um=?,"
                " result3_um=?, error_code=?, error_text=?, session_path=?, report_path=?,"
                " artefacts=?, not_proven=? WHERE id=?",
                (
                    state,
                    _now(),
                    None if passed is None else int(passed),
                    r1,
                    r2,
                    r3,
                    int(error_code),
                    error_text,
                    None if session_path is None else str(session_path),
                    None if report_path is None else str(report_path),
                    json.dumps([str(a) for a in artefacts]),
                    int(bool(not_proven)),
                    job_id,
                ),
            )

    def mark_interrupted(self, error_code: int, error_text: str) -> list[int]:
        """Turn every ``running`` record into ``interrupted``; return their ids."""
        with self._lock:
            ids = [r[0] for r in self._db.execute("SELECT id FROM jobs WHERE state='running'")]
            if ids:
                self._db.execute(
                    "UPDATE jobs SET state='interrupted', finished_at=?, error_code=?,"
                    " error_text=? WHERE state='running'",
                    (_now(), int(error_code), error_text),
                )
        for job_id in ids:
            log.warning("job %d was running when the service stopped: marked interrupted", job_id)
        return ids

    def get(self, job_id: int) -> JobRecord | None:
        """The record with this id, or ``None``."""
        with self._lock:
            row = self._db.execute(
                f"SELECT {self._select} FROM jobs WHERE id=?", (job_id,)
            ).fetchone()
        return None if row is None else JobRecord._from_row(row)

    def latest(self, limit: int = 20) -> list[JobRecord]:
        """The newest ``limit`` records, newest first."""
        if limit < 1:
            raise ValueError(f"expected limit >= 1, got {limit}")
        with self._lock:
            rows = self._db.execute(
                f"SELECT {self._select} FROM jobs ORDER BY id DESC LIMIT ?", (limit,)
            ).fetchall()
        return [JobRecord._from_row(r) for r in rows]
