from __future__ import annotations

from pathlib import Path

import pytest

from scanner.app.plc.config import load_plc_config
from scanner.core.config import CONFIG_DIR as REPO_CONFIGS
from scanner.core.config import ConfigError


def test_shipped_config_loads_and_binds_loopback():
    config = load_plc_config()
    assert config.server.host == "127.0.0.1"
    assert config.server.port == 5020
    assert config.recipe(1) is not None
    assert config.recipe(99) is None
    assert config.jobs.worker == "process"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('[server]\nallowed_clients = ["plc"]\n', "allowed_clients"),
        ("[server]\nport = 70000\n", "port"),
        ("[server]\nmax_connections = 0\n", "max_connections"),
        ('[source]\nkind = "folder"\n', "folder"),
        ('[jobs]\nrunner = "nomodule"\n', "runner"),
        (
            '[[recipes]]\nnumber = 1\nname = "a"\nplan = "p"\n'
            '[[recipes]]\nnumber = 1\nname = "b"\nplan = "q"\n',
            "unique",
        ),
    ],
)
def test_bad_config_names_the_key(tmp_path: Path, text: str, message: str):
    path = tmp_path / "plc.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match=message):
        load_plc_config(path)


@pytest.mark.parametrize("key", ["heartbeat_timeout_s", "job_timeout_s"])
def test_a_nan_timeout_cannot_disable_the_watchdog(tmp_path, key):
    text = (REPO_CONFIGS / "plc.toml").read_text()
    path = tmp_path / "plc.toml"
    path.write_text(text.replace(f"{key} = ", f"{key} = nan  # was ", 1))
    with pytest.raises(ConfigError, match=f"watchdog.{key}: expected a finite number"):
        load_plc_config(path)


def test_a_check_limit_of_zero_is_refused_at_load(tmp_path):
    text = (REPO_CONFIGS / "plc.toml").read_text()
    path = tmp_path / "plc.toml"
    path.write_text(text.replace("max_abs_um = 250.0", "max_abs_um = 0.0", 1))
    with pytest.raises(ConfigError, match=r"check\.max_abs_um: expected a positive limit"):
        load_plc_config(path)
