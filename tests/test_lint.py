"""Ruff lint and format are part of the suite, so CI refuses code that drifts from the style."""

import shutil
import subprocess
import sys

import pytest

from tests.conftest import REPO_ROOT


def ruff() -> list[str]:
    exe = shutil.which("ruff", path=str(REPO_ROOT / ".venv" / "bin")) or shutil.which("ruff")
    if exe is None:
        pytest.skip("ruff is not installed (pip install -e '.[dev]')")
    return [exe]


@pytest.mark.parametrize(
    "args", [["check", "."], ["format", "--check", "."]], ids=["lint", "format"]
)
def test_ruff(args):
    proc = subprocess.run(
        [*ruff(), *args], cwd=REPO_ROOT, capture_output=True, text=True, check=False
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-1000:]


def test_no_sys_path_tricks():
    offenders = [
        str(p.relative_to(REPO_ROOT))
        for folder in ("scanner", "calibration", "metrology", "tests", "benchmarks")
        for p in (REPO_ROOT / folder).rglob("*.py")
        if "sys.path." in p.read_text(encoding="utf-8") and p.name != "test_lint.py"
    ]
    assert not offenders, f"sys.path manipulation in {offenders}"
    assert sys.version_info >= (3, 10)
