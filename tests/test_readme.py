"""Every ``scanner`` command the README shows is run here, so the README cannot rot.

The tour block runs as written, in order, in a scratch folder (it simulates the paper's cell,
then calibrates, checks, scans, measures and runs the acceptance test on it). The command
reference's lines are checked to name real commands and options; ``scanner demo`` itself is
run by ``tests/scanner/app/test_demo.py`` and ``scanner history`` by ``tests/scanner/app/plc``.
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys

import pytest

from tests.conftest import REPO_ROOT

README = REPO_ROOT / "README.md"


def code_blocks(text: str) -> list[str]:
    return re.findall(r"```(?:bash|sh)?\n(.*?)```", text, flags=re.S)


def scanner_lines(block: str) -> list[str]:
    lines = []
    for line in block.splitlines():
        line = line.split("  #")[0].strip()
        if line.startswith("scanner "):
            lines.append(line)
    return lines


def tour_commands() -> list[str]:
    blocks = [scanner_lines(b) for b in code_blocks(README.read_text(encoding="utf-8"))]
    tours = [b for b in blocks if b and b[0].startswith("scanner simulate")]
    assert tours, "README: expected a code block starting with `scanner simulate` (the tour)"
    return tours[0]


def run_scanner(line: str, cwd) -> subprocess.CompletedProcess:
    args = shlex.split(line)[1:]
    return subprocess.run(
        [sys.executable, "-m", "scanner", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        check=False,
        timeout=1200,
    )


def test_readme_set_up_commands_are_the_ci_commands():
    text = README.read_text(encoding="utf-8")
    assert "bash bootstrap.sh demo" in text
    assert "bash bootstrap.sh test" in text
    assert "bash bootstrap.sh test" in (REPO_ROOT / ".ci" / "run").read_text()


def test_reference_commands_exist_with_their_options():
    from scanner.app.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    text = README.read_text(encoding="utf-8")
    for cmd, options in re.findall(r"^\| `scanner ([\w-]+)([^`]*)`", text, flags=re.M):
        assert cmd in sub.choices, f"README names `scanner {cmd}`, which does not exist"
        known = {o for a in sub.choices[cmd]._actions for o in a.option_strings}
        for option in re.findall(r"--[a-z][a-z-]*", options):
            assert option in known, f"README: `scanner {cmd}` has no option {option}"


@pytest.mark.slow
def test_readme_tour_runs_as_written(tmp_path):
    # In a folder of its own (no configs/ beside it): shipped plans are found by name.
    printed = {}
    for line in tour_commands():
        proc = run_scanner(line, tmp_path)
        assert proc.returncode == 0, f"README command failed: {line}\n{proc.stderr[-2000:]}"
        printed[shlex.split(line)[1]] = proc.stdout
    # The tour ends in PASS, as the README says: the spheres and the plate are in the cloud.
    assert "measure: PASS" in printed["measure"], printed["measure"]
    assert "acceptance: PASS" in printed["acceptance"], printed["acceptance"]
    assert (tmp_path / "tour" / "calibration.html").is_file()  # the report beside --out
    assert (tmp_path / "tour" / "calibration.json").is_file()
    assert (tmp_path / "tour" / "cloud.ply").is_file()
    assert (tmp_path / "tour" / "measure.html").is_file()


@pytest.mark.parametrize(
    "line",
    ["scanner target --out target.svg", "scanner serve --print-map"],
)
def test_readme_small_commands_run(line, tmp_path):
    assert line in README.read_text(encoding="utf-8")
    proc = run_scanner(line, tmp_path)
    assert proc.returncode == 0, proc.stderr
