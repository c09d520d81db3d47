"""The stage layer protects what is there: no output replaces an input, and a failed run
replaces none of the earlier outputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from scanner.app import stages
from scanner.app.cli import main
from tests.metrology.test_measure import paper_scene


@pytest.fixture
def files(tmp_path: Path) -> dict[str, Path]:
    session = tmp_path / "S"
    session.mkdir()
    (session / "session.json").write_text('{"format": "scan-session/1"}')
    (session / "frames.csv").write_text("id\n")
    calibration = tmp_path / "c.json"
    calibration.write_text('{"format": "scan-calibration/1"}')
    cloud = tmp_path / "cloud.npy"
    np.save(cloud, paper_scene(np.random.default_rng(0), n=4000))
    return {"session": session, "calibration": calibration, "cloud": cloud}


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}


@pytest.mark.parametrize(
    "argv",
    [
        "check {session} --calibration {calibration} --out {calibration}",
        "check {session} --calibration {calibration} --out {tmp}/r.json --report {session}/frames.csv",
        "calibrate {session} --out {session}/session.json",
        "calibrate {session} --out {tmp}/new.json --report {session}/frames.csv",
        "scan {session} --calibration {calibration} --out {session}/cloud.ply",
        "measure {cloud} --plan paper_sweep --calibration {calibration} --out {calibration}",
        "acceptance {cloud} --spec acceptance_paper --out {tmp}/cloud.json --calibration {tmp}/cloud.csv",
        "acceptance {cloud} {tmp}/cloud.csv --spec acceptance_paper --out {tmp}/cloud.json",
    ],
)
def test_an_output_that_would_replace_an_input_is_refused(files, tmp_path, capsys, argv):
    (tmp_path / "cloud.csv").write_text("a calibration by another name")
    before = _snapshot(tmp_path)
    args = argv.format(tmp=tmp_path, **files).split()
    assert main(args) == 2
    assert "would overwrite the input" in capsys.readouterr().err
    assert _snapshot(tmp_path) == before


def test_a_failed_measure_keeps_the_earlier_report_whole(files, tmp_path, capsys):
    out = tmp_path / "m.json"
    assert main(["measure", str(files["cloud"]), "--plan", "paper_sweep", "--out", str(out)]) == 0
    before = _snapshot(tmp_path)
    assert set(before) >= {"m.json", "m.csv", "m.html"}
    (tmp_path / "m.html").unlink()
    (tmp_path / "m.html").mkdir()  # the report cannot be written now
    before = _snapshot(tmp_path)
    assert main(["measure", str(files["cloud"]), "--plan", "paper_sweep", "--out", str(out)]) == 2
    assert "m.html: is a folder" in capsys.readouterr().err
    assert _snapshot(tmp_path) == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "staging left behind"


def test_stages_record_their_provenance(files, tmp_path):
    judged = stages.measure(files["cloud"], "paper_sweep", tmp_path / "m.json")
    record = json.loads((tmp_path / "m.json").read_text())["cloud"]["provenance"]["stage"]
    assert record["stage"] == "measure" and record["scanner_version"]
    assert record["inputs"]["cloud"]["path"] == str(files["cloud"].resolve())
    assert len(record["inputs"]["cloud"]["sha256"]) == 64
    assert judged.files.html_path.is_file() and judged.result.passed


def test_a_report_named_like_the_result_is_refused(files, tmp_path, capsys):
    argv = ["calibrate", str(files["session"]), "--out", str(tmp_path / "cal.json"),
            "--report", str(tmp_path / "cal.json")]  # fmt: skip
    assert main(argv) == 2
    assert "named for two outputs of one run" in capsys.readouterr().err
