"""`scanner target` and `scanner simulate` on the command line."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import pytest

from scanner.app.cli import main
from scanner.core.targets import parse_target
from scanner.virtual_cell import load_cell


def test_target_svg_is_one_to_one_with_the_spec_beside_it(tmp_path, capsys):
    out = tmp_path / "target.svg"
    assert main(["target", "--cell", "paper", "--out", str(out)]) == 0
    root = ET.parse(out).getroot()
    assert root.get("width") == "216.000mm"  # card: marker extent 96 mm + 12 mm margin, twice
    circles = [
        c for c in root.iter("{http://www.w3.org/2000/svg}circle") if c.get("fill") == "none"
    ]
    assert len(circles) == 14
    assert float(circles[-1].get("r")) == pytest.approx(80.0)
    spec = parse_target(json.loads((tmp_path / "target.json").read_text()))
    assert spec == load_cell("paper").target_spec()
    assert "print at 100 %" in capsys.readouterr().out


def test_target_pdf_from_a_spec_file(tmp_path):
    out = tmp_path / "cb.pdf"
    spec_file = load_cell.__globals__["CONFIG_DIR"] / "targets" / "chessboard_11x8.toml"
    assert main(["target", "--spec", str(spec_file), "--out", str(out)]) == 0
    assert out.read_bytes()[:4] == b"%PDF"


def test_target_bad_input_is_one_line(tmp_path, capsys):
    assert (
        main(["target", "--spec", str(tmp_path / "none.toml"), "--out", str(tmp_path / "x.svg")])
        == 2
    )
    assert "not found" in capsys.readouterr().err
    assert main(["target", "--out", str(tmp_path / "x.txt")]) == 2


def test_simulate_refuses_bad_arguments(tmp_path, capsys):
    assert main(["simulate", "--out", str(tmp_path), "--sessions", "nope"]) == 2
    assert "--sessions" in capsys.readouterr().err
    assert main(["simulate", "--cell", "nocell", "--out", str(tmp_path)]) == 2


@pytest.mark.slow
def test_simulate_writes_a_check_session(tmp_path):
    assert main(["simulate", "--cell", "paper", "--out", str(tmp_path), "--sessions", "check"]) == 0
    assert (tmp_path / "check" / "session.json").is_file()
    assert (tmp_path / "truth.json").is_file()
