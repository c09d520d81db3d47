"""Atomic outputs, outputs committed together, inputs protected, JSON read safely."""

from __future__ import annotations

import json
import os
import pickle
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from scanner.core import fileio
from scanner.core.config import ConfigError
from scanner.core.fileio import (
    InputError,
    check_outputs_apart,
    commit_together,
    current_umask,
    read_json_object,
    write_json_atomic,
    write_text_atomic,
)


def test_outputs_appear_together_or_not_at_all(tmp_path: Path):
    a, b = tmp_path / "a.json", tmp_path / "sub" / "b.txt"
    write_text_atomic(a, "old a")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OSError), commit_together() as staged:
        write_text_atomic(staged(a), "new a")
        write_text_atomic(staged(blocker / "c.txt"), "cannot: its folder is a file")
    assert a.read_text() == "old a"
    assert not list(tmp_path.glob(".a.json.*")), "staging left behind"
    with commit_together() as staged:
        staged_a = staged(a)
        write_text_atomic(staged_a, "new a")
        write_text_atomic(staged(b), "new b")
        write_text_atomic(staged_a.with_suffix(".csv"), "a twin named by its writer")
    assert a.read_text() == "new a" and b.read_text() == "new b"
    assert (tmp_path / "a.csv").read_text() == "a twin named by its writer"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "a.json", "file", "sub"]


def test_a_folder_in_the_way_stops_the_commit_before_anything_is_replaced(tmp_path: Path):
    (tmp_path / "r.json").write_text("old")
    (tmp_path / "r.html").mkdir()
    with pytest.raises(InputError, match="is a folder"), commit_together() as staged:
        write_text_atomic(staged(tmp_path / "r.json"), "new")
        write_text_atomic(staged(tmp_path / "r.html"), "new")
    assert (tmp_path / "r.json").read_text() == "old"


def test_an_output_that_would_replace_an_input_is_refused(tmp_path: Path):
    session = tmp_path / "S"
    session.mkdir()
    (session / "session.json").write_text("{}")
    calib = tmp_path / "c.json"
    calib.write_text("{}")
    link = tmp_path / "link.json"
    link.symlink_to(calib)
    for out in (calib, link, session / "session.json", session / "new.json", session):
        with pytest.raises(InputError, match="would overwrite the input"):
            check_outputs_apart([session, calib], [out])
    check_outputs_apart([session, calib], [tmp_path / "out.json", tmp_path / "S2" / "x"])


def test_json_reading_names_the_file_and_the_fault(tmp_path: Path):
    p = tmp_path / "x.json"
    with pytest.raises(InputError, match=r"x\.json: gone"):
        read_json_object(p, "gone")
    p.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(InputError, match="nested too deep"):
        read_json_object(p)
    p.write_text("[1, 2]")
    with pytest.raises(InputError, match="expected a JSON object, got list"):
        read_json_object(p)
    p.write_text('{"a": 1,}')
    with pytest.raises(InputError, match="not valid JSON \\(line 1"):
        read_json_object(p)
    write_json_atomic(p, {"a": float("nan"), "b": [1.5]})
    assert json.loads(p.read_text()) == {"a": None, "b": [1.5]}


@pytest.mark.parametrize("error", [InputError(Path("a.png"), "bad"), ConfigError("p.toml", "x")])
def test_input_errors_cross_process_boundaries_whole(error: InputError):
    back = pickle.loads(pickle.dumps(error))
    assert type(back) is type(error)
    assert str(back) == str(error) and back.path == error.path and back.reason == error.reason


def test_one_name_for_two_outputs_is_refused(tmp_path: Path):
    out = tmp_path / "cal.json"
    with pytest.raises(InputError, match="named for two outputs"):
        check_outputs_apart([], [out, tmp_path / "." / "cal.json"])
    with pytest.raises(InputError, match="named for two outputs"), commit_together() as staged:
        staged(out)
        staged(out)


@pytest.mark.parametrize("proc", [True, False])
def test_the_umask_read_by_many_threads_at_once_stays_the_process_umask(
    proc, monkeypatch, tmp_path
):
    """Read from /proc where Linux gives it; otherwise by setting it to 0 and back, which
    unlocked lets two threads (the scan's workers writing chunks) read each other's 0 and
    leave the process at 0 for good."""
    if not proc:
        monkeypatch.setattr(fileio, "_PROC_STATUS", str(tmp_path / "no-such-file"))
    elif not os.path.exists(fileio._PROC_STATUS):
        pytest.skip("no /proc/self/status on this platform")
    before = os.umask(0o027)
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # threads switch between any two calls, as under load
    try:
        with ThreadPoolExecutor(4) as pool:
            reads = list(pool.map(lambda _: {current_umask() for _ in range(5000)}, range(8)))
        assert set().union(*reads) == {0o027}
        assert current_umask() == 0o027
    finally:
        sys.setswitchinterval(interval)
        os.umask(before)
