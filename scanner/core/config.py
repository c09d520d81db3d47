"""Configs are dataclasses loaded from ``configs/*.toml`` and validated once, at the edge.

:func:`load_config` reads a TOML file into a (frozen) dataclass, converting and checking every
field by its type annotation. Errors name the file, the key and, where it can be found, the
line: ``configs/plan.toml, line 12, features[1].radius_mm: expected a number, got 'x'``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import sys
import sysconfig
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from scanner.core.fileio import InputError

__all__ = [
    "CONFIG_DIR",
    "ConfigError",
    "config_dirs",
    "from_dict",
    "load_config",
    "load_toml",
    "resolve_config",
]

T = TypeVar("T")

#: Where the shipped configs are installed by a (non-editable) install: ``pyproject.toml``'s
#: ``data-files`` put ``configs/`` under ``<prefix>/share/robot-line-scanner/configs``.
INSTALLED_CONFIG_DIR = Path(sysconfig.get_path("data")) / "share" / "robot-line-scanner" / "configs"
#: ``configs/`` of a checkout (beside the packages), for an editable install or a source tree.
CHECKOUT_CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"


def config_dirs() -> list[Path]:
    """The folders searched for a config given by name, in order.

    ``$SCANNER_CONFIG_PATH`` (folders separated by ``os.pathsep``) first, then the checkout's
    ``configs/``, then the installed copy. Only folders that exist are listed.
    """
    env = [Path(p) for p in os.environ.get("SCANNER_CONFIG_PATH", "").split(os.pathsep) if p]
    found = [p for p in (*env, CHECKOUT_CONFIG_DIR, INSTALLED_CONFIG_DIR) if p.is_dir()]
    return found or [CHECKOUT_CONFIG_DIR]


#: The shipped configs: the first folder of :func:`config_dirs` at import time.
CONFIG_DIR = config_dirs()[0]


class ConfigError(InputError):
    """A config value that is missing or wrong; the message names file, line and key."""


def resolve_config(name_or_path: str | os.PathLike[str], subdir: str = "") -> Path:
    """A path as given if it exists; a bare name (no folder) is looked up as
    ``<subdir>/<name>.toml`` in :func:`config_dirs`."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    if len(p.parts) > 1:
        # A path with a folder is meant as a path: never replaced by a shipped namesake.
        raise InputError(p, "config not found (no such file)")
    name = p.name if p.suffix == ".toml" else f"{p.name}.toml"
    candidates = [folder / subdir / name for folder in config_dirs()]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    looked = ", ".join(str(c) for c in candidates)
    raise InputError(p, f"config not found (looked for it as given and as {looked})")


def load_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(p, f"cannot read config ({exc.strerror or exc})") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(p, f"not valid TOML ({exc})") from None


def _line_of(text: str, key_path: str) -> int | None:
    """Line of ``key_path`` (``measurements[2].features``) in TOML ``text``: the n-th
    ``[[array]]`` table, then the last key's ``key =`` inside it (inline tables included)."""
    parts = re.findall(r"([A-Za-z_][\w-]*)(?:\[(\d+)\])?", key_path)
    start, end = 0, len(text)
    keys: list[str] = []
    for name, index in parts:
        if index:
            header = re.compile(rf"^[ \t]*\[\[[ \t]*{re.escape(name)}[ \t]*\]\]", re.M)
            found = [m.start() for m in header.finditer(text)]
            if int(index) < len(found):
                start = found[int(index)]
                after = text.find("\n", start)
                nxt = re.compile(r"^[ \t]*\[", re.M).search(text, after + 1) if after >= 0 else None
                end = nxt.start() if nxt else len(text)
                keys = []
                continue
        keys.append(name)
    for key in reversed(keys):
        m = re.compile(rf"(?<![\w.-]){re.escape(key)}[ \t]*=").search(text, start, end)
        if m:
            return text.count("\n", 0, m.start()) + 1
    if start:
        return text.count("\n", 0, start) + 1
    return None


def _join_key_path(msg: str) -> str:
    """``"features[1].region: box_max_mm: reason"`` -> ``"features[1].region.box_max_mm: reason"``."""
    pattern = re.compile(r"^([\w.\[\]]+): ([A-Za-z_][\w]*(?:\[\d+\])?(?:\.[\w\[\]]+)*): ")
    while m := pattern.match(msg):
        msg = f"{m.group(1)}.{m.group(2)}: " + msg[m.end() :]
    return msg


def _is_optional(tp: Any) -> tuple[bool, Any]:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return True, args[0]
    return False, tp


def _convert(value: Any, tp: Any, where: str) -> Any:
    optional, inner = _is_optional(tp)
    if value is None:
        if optional:
            return None
        raise ValueError(f"{where}: expected a value, got nothing")
    tp = inner
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ValueError(f"{where}: expected a table, got {type(value).__name__}")
        return from_dict(tp, value, where)
    if tp is typing.Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(value):
            # TOML allows nan and inf; no setting of ours means either (a nan timeout would
            # disable a watchdog, an inf tolerance accept anything).
            raise ValueError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ValueError(f"{where}: expected a string, got {value!r}")
        return value
    if origin is typing.Literal:
        allowed = typing.get_args(tp)
        if value not in allowed:
            raise ValueError(
                f"{where}: expected one of {', '.join(map(repr, allowed))}, got {value!r}"
            )
        return value
    if origin in (tuple, list):
        if not isinstance(value, list | tuple):
            raise ValueError(f"{where}: expected a list, got {type(value).__name__}")
        args = typing.get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ValueError(f"{where}: expected {len(args)} values, got {len(value)}")
            return tuple(
                _convert(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args))
            )
        elem = args[0] if args else typing.Any
        items = [_convert(v, elem, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise ValueError(f"{where}: expected a table, got {type(value).__name__}")
        _, vt = typing.get_args(tp) or (str, typing.Any)
        return {str(k): _convert(v, vt, f"{where}.{k}") for k, v in value.items()}
    return value


def from_dict(cls: type[T], data: dict[str, Any], where: str = "") -> T:
    """Build dataclass ``cls`` from ``data``, converting and checking each field by type.

    Unknown keys are refused (a typo should not be silently ignored); fields with defaults may
    be omitted. ``__post_init__`` validation of the dataclass runs as usual.
    """
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    prefix = f"{where}." if where else ""
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ValueError(f"{prefix}{unknown[0]}: unknown key (expected one of {', '.join(fields)})")
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ValueError(f"{prefix}{name}: missing required key")
            continue
        kwargs[name] = _convert(data[name], hints[name], f"{prefix}{name}")
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        msg = str(exc)
        raise ValueError(
            msg if msg.startswith(prefix) or not where else f"{where}: {msg}"
        ) from None


def load_config(cls: type[T], path: str | os.PathLike[str]) -> T:
    """Load TOML ``path`` into dataclass ``cls``; errors name the file, the line (found inside
    the right ``[[array]]`` table) and the full key path."""
    p = Path(path)
    data = load_toml(p)
    try:
        return from_dict(cls, data)
    except ValueError as exc:
        msg = _join_key_path(str(exc))
        key = msg.split(":", 1)[0]
        line = _line_of(p.read_text(encoding="utf-8"), key)
        raise ConfigError(f"{p}, line {line}" if line else p, msg) from None
