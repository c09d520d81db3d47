"""Configuration of the PLC service: ``configs/plc.toml`` as validated dataclasses.

Load with :func:`load_plc_config` (which uses :func:`scanner.core.config.load_config`, so errors
name the file, line and key). Relative paths in the file are resolved against the current
working directory when the service starts (a systemd unit sets ``WorkingDirectory``).
"""

from __future__ import annotations

import ipaddress
import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Literal

from scanner.core.config import load_config, resolve_config

__all__ = [
    "CalibrationGate",
    "CheckTolerances",
    "JobsConfig",
    "PlcConfig",
    "Recipe",
    "ServerConfig",
    "SourceConfig",
    "StorageConfig",
    "WatchdogConfig",
    "check_host",
    "load_plc_config",
]

#: A host name as RFC 1123 allows it: dot-separated labels of letters, digits and hyphens.
_HOST_NAME = re.compile(r"^(?!-)[A-Za-z0-9-]{1,63}(?<!-)(\.(?!-)[A-Za-z0-9-]{1,63}(?<!-))*\.?$")


def check_host(host: str, option: str = "host") -> str:
    """``host`` if it is an IP address or a well-formed host name, else ``ValueError``.

    Only the spelling is checked (no name lookup): a name made of digits and dots only
    (``999.1.1.1``) must be an IP address, as RFC 1123 rules out all-numeric top-level labels.

    Raises
    ------
    ValueError
        ``"<option>: expected an IP address or a host name, got '<host>'"``.
    """
    try:
        ipaddress.ip_address(host)
        return host
    except ValueError:
        pass
    labels = host.rstrip(".").split(".")
    if _HOST_NAME.match(host) and len(host) <= 253 and not labels[-1].isdigit():
        return host
    raise ValueError(
        f"{option}: expected an IP address or a host name, got {host!r}"
        + (" (not an IP address)" if re.fullmatch(r"[0-9.]+", host) else "")
    )


@dataclass(frozen=True)
class ServerConfig:
    """Where and to whom the Modbus TCP server listens.

    ``allowed_clients`` holds addresses or networks (``"192.168.10.5"``, ``"10.0.0.0/24"``);
    an empty list allows every address (only sensible on an isolated PLC network).
    """

    host: str = "127.0.0.1"
    port: int = 5020
    allowed_clients: list[str] = field(default_factory=lambda: ["127.0.0.1"])
    max_connections: int = 8
    idle_timeout_s: float = 60.0

    def __post_init__(self) -> None:
        check_host(self.host)
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port: expected 0..65535, got {self.port}")
        if self.max_connections < 1:
            raise ValueError(f"max_connections: expected >= 1, got {self.max_connections}")
        if self.idle_timeout_s <= 0:
            raise ValueError(f"idle_timeout_s: expected > 0, got {self.idle_timeout_s}")
        for i, entry in enumerate(self.allowed_clients):
            try:
                ipaddress.ip_network(entry, strict=False)
            except ValueError:
                raise ValueError(
                    f"allowed_clients[{i}]: expected an IP address or network, got {entry!r}"
                ) from None

    def networks(self) -> list[ipaddress.IPv4Network | ipaddress.IPv6Network]:
        """The allowed clients as networks (a single address is a /32 or /128)."""
        return [ipaddress.ip_network(e, strict=False) for e in self.allowed_clients]


def _refuse_fields(config: Any, bad: Callable[[float], bool], expected: str) -> None:
    """Raise on the first field of the dataclass ``config`` that ``rule`` refuses.

    Parameters
    ----------
    config : dataclass instance
        A section whose fields are all numbers under the same rule.
    bad : callable
        True for a refused value.
    expected : str
        What is expected instead, for the message.

    Raises
    ------
    ValueError
        ``"<field>: expected <expected>, got <value>"``.
    """
    for f in fields(config):
        value = getattr(config, f.name)
        if bad(value):
            raise ValueError(f"{f.name}: expected {expected}, got {value}")


@dataclass(frozen=True)
class WatchdogConfig:
    """Limits on a running job; 0 disables a limit."""

    #: Abort the job when register 2 has not changed for this long (s).
    heartbeat_timeout_s: float = 5.0
    #: Abort a job running longer than this (s).
    job_timeout_s: float = 900.0
    #: On SIGTERM, how long to wait for a running job to stop before recording it interrupted.
    shutdown_grace_s: float = 5.0

    def __post_init__(self) -> None:
        _refuse_fields(self, lambda v: v < 0, ">= 0")


@dataclass(frozen=True)
class StorageConfig:
    """Files of the service: job history, job outputs, the current calibration."""

    history_db: str = "var/plc/history.sqlite"
    work_dir: str = "var/plc/jobs"
    calibration: str = "var/plc/calibration.json"


@dataclass(frozen=True)
class SourceConfig:
    """Where sessions come from.

    ``virtual``: each job captures a fresh session from the virtual cell ``cell`` (seeded by
    ``seed`` plus the job id). ``folder``: capture software drops session folders into
    ``folder`` (one sub-folder each, ``session.json`` written last); a job takes the newest
    complete one of the kind it needs.
    """

    kind: Literal["virtual", "folder"] = "virtual"
    cell: str = "modern"
    folder: str = ""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.kind == "folder" and not self.folder:
            raise ValueError("folder: expected a folder path when kind = 'folder', got ''")


@dataclass(frozen=True)
class CheckTolerances:
    """Pass/fail limits of the recalibration check, micrometres."""

    max_mean_abs_um: float = 100.0
    max_abs_um: float = 250.0
    max_o_spread_um: float = 500.0

    def __post_init__(self) -> None:
        _refuse_fields(self, lambda v: not v > 0, "a positive limit")


@dataclass(frozen=True)
class CalibrationGate:
    """Quality gate a new calibration must pass before it replaces the current one."""

    max_intrinsics_rms_px: float = 1.0
    max_light_plane_rms_um: float = 100.0
    max_hand_eye_rms_px: float = 2.0


@dataclass(frozen=True)
class Recipe:
    """A scan job selected by register 3: which inspection plan and/or nominal mesh,
    optionally which cell."""

    number: int
    name: str
    #: Inspection plan: a ``configs/plans`` name or a path; empty for none.
    plan: str = ""
    #: Virtual cell to scan in (virtual source only); empty means ``[source] cell``.
    cell: str = ""
    #: Nominal mesh (STL, PLY, OBJ) to inspect the scan against (``scanner inspect``); empty
    #: for none. Relative paths are resolved against the service's working directory.
    nominal: str = ""
    #: Inspection spec with the nominal: a ``configs/inspect`` name or a path.
    inspect_spec: str = "default"
    #: Planned sweeps of a full-object job: a ``scanner plan-scan`` folder (plan.json,
    #: sweeps.csv) for the part given as ``nominal``. The virtual cell captures them with the
    #: part where the plan put it; every sweep goes into one cloud (ICP between sweeps, the
    #: table under the part left out) that is inspected against the nominal.
    sweeps: str = ""

    def __post_init__(self) -> None:
        if not 1 <= self.number <= 65535:
            raise ValueError(f"number: expected 1..65535, got {self.number}")
        if self.sweeps and not self.nominal:
            raise ValueError("sweeps: a planned full-object scan needs the part as nominal")
        if not self.plan and not self.nominal:
            raise ValueError(
                "plan: expected an inspection plan, a nominal mesh or both, got neither"
            )


#: The name of the job runner that runs the real stages (:class:`scanner.app.plc.jobs.PipelineJobs`).
BUILTIN_RUNNER = "pipeline"


@dataclass(frozen=True)
class JobsConfig:
    """Which job runner the service uses.

    ``"pipeline"`` (the default) runs the real stages; tests and integrators may name their
    own as ``"package.module:factory"``, called with the config.
    """

    runner: str = BUILTIN_RUNNER
    #: "process": each job in a worker process of its own (killable, no GIL contention with
    #: the server); "thread": on a thread of the service (cooperative cancellation only).
    worker: Literal["process", "thread"] = "process"
    #: After a cancellation, how long a job process may take to stop before it is killed (s).
    kill_after_s: float = 2.0

    def __post_init__(self) -> None:
        if self.kill_after_s < 0:
            raise ValueError(f"kill_after_s: expected >= 0, got {self.kill_after_s}")
        module, sep, attr = self.runner.partition(":")
        if self.runner != BUILTIN_RUNNER and (not sep or not module or not attr):
            raise ValueError(
                f"runner: expected {BUILTIN_RUNNER!r} or 'package.module:factory', "
                f"got {self.runner!r}"
            )


@dataclass(frozen=True)
class PlcConfig:
    """The whole of ``configs/plc.toml``."""

    server: ServerConfig = field(default_factory=ServerConfig)
    watchdog: WatchdogConfig = field(default_factory=WatchdogConfig)
    storage: StorageConfig = field(default_factory=StorageConfig)
    source: SourceConfig = field(default_factory=SourceConfig)
    check: CheckTolerances = field(default_factory=CheckTolerances)
    calibration_gate: CalibrationGate = field(default_factory=CalibrationGate)
    jobs: JobsConfig = field(default_factory=JobsConfig)
    recipes: list[Recipe] = field(default_factory=list)

    def __post_init__(self) -> None:
        seen: set[int] = set()
        for i, recipe in enumerate(self.recipes):
            if recipe.number in seen:
                raise ValueError(
                    f"recipes[{i}].number: expected a unique number, got {recipe.number} twice"
                )
            seen.add(recipe.number)

    def recipe(self, number: int) -> Recipe | None:
        """The recipe with this number, or ``None``."""
        return next((r for r in self.recipes if r.number == number), None)


def load_plc_config(path: str | os.PathLike[str] | None = None) -> PlcConfig:
    """Load ``path`` (default ``configs/plc.toml``) into a :class:`PlcConfig`."""
    return load_config(PlcConfig, resolve_config(Path(path) if path else "plc"))
