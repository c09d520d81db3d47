"""A non-editable install finds the shipped configs (cells, plans, targets, plc.toml) by name."""

from __future__ import annotations

import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT

pytestmark = pytest.mark.slow


def test_an_installed_copy_finds_the_shipped_configs(tmp_path: Path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    # Our package only (no dependencies), built from a copy of the checkout, into the new prefix.
    source = tmp_path / "src"
    shutil.copytree(
        REPO_ROOT, source, ignore=shutil.ignore_patterns(".venv", ".git", "reports", "tests")
    )
    # --ignore-installed: never touch the environment running this test (pip would otherwise
    # uninstall its editable install of the same name first).
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--ignore-installed",
         "--prefix", str(venv), str(source)],
        check=True, cwd=tmp_path, capture_output=True, text=True,
    )  # fmt: skip
    site = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
        check=True, capture_output=True, text=True,
    ).stdout.strip()  # fmt: skip
    deps = sysconfig.get_path("purelib")  # numpy and the rest, from the test's environment
    probe = (
        "import scanner.core.config as c; "
        "print(c.CONFIG_DIR); "
        "print(c.resolve_config('paper_sweep', 'plans')); "
        "print(c.resolve_config('plc'))"
    )
    out = subprocess.run(
        [str(python), "-c", probe],
        check=True, capture_output=True, text=True, cwd=tmp_path,
        env={"PYTHONPATH": f"{site}:{deps}", "PATH": "/usr/bin:/bin"},
    ).stdout.split("\n")  # fmt: skip
    config_dir = Path(out[0])
    assert REPO_ROOT not in config_dir.parents, "found the checkout, not the installed copy"
    assert config_dir == venv / "share" / "robot-line-scanner" / "configs"
    assert Path(out[1]).is_file() and Path(out[2]).name == "plc.toml"
    # This environment still has its own install.
    check = [sys.executable, "-c", "import scanner.app.cli"]
    assert subprocess.run(check, cwd=tmp_path, check=False).returncode == 0
