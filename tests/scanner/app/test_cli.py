import subprocess
import sys

import pytest

from scanner.app.cli import build_parser, main


def test_help_lists_the_contract_commands(capsys):
    assert main([]) == 2
    out = capsys.readouterr().out
    for command in ("calibrate", "check", "scan", "demo", "serve"):
        assert command in out


def test_bad_input_gives_one_line_on_stderr_and_non_zero_exit(tmp_path):
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "scanner.app.cli",
            "calibrate",
            str(tmp_path / "missing"),
            "--out",
            str(tmp_path / "c.json"),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "missing" in lines[0]
    assert not (tmp_path / "c.json").exists()


@pytest.mark.parametrize("argv", [["-v", "serve", "--print-map"], ["serve", "--print-map", "-v"]])
def test_verbose_goes_before_or_after_the_command(argv):
    assert build_parser().parse_args(argv).verbose is True
    assert build_parser().parse_args(["serve", "--print-map"]).verbose is False
