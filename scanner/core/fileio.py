"""File helpers shared by every stage: the input error type and atomic writes."""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "InputError",
    "atomic_output",
    "check_outputs_apart",
    "commit_together",
    "current_umask",
    "json_int",
    "read_json_object",
    "write_json_atomic",
    "write_text_atomic",
]


class InputError(ValueError):
    """Bad input: a file that is missing, unreadable or wrong, with the reason.

    ``str(err)`` is the one line the command line prints: ``"<path>: <reason>"``.
    """

    def __init__(self, path: str | os.PathLike[str] | None, reason: str) -> None:
        self.path = None if path is None else Path(path)
        self.reason = reason
        super().__init__(reason if path is None else f"{path}: {reason}")

    def __reduce__(self) -> tuple[Any, ...]:
        # Crosses process boundaries whole (a worker pool's error stays an input error).
        return (type(self), (self.path, self.reason))


_UMASK_LOCK = threading.Lock()
_PROC_STATUS = "/proc/self/status"


def current_umask() -> int:
    """The process's umask, for giving an output the mode a plain ``open`` would.

    Read from ``/proc/self/status`` where Linux gives it (4.7 and later). Elsewhere it can only
    be read by setting it and setting it back: under a lock, so that two threads writing
    outputs at once (the scan's workers) do not read each other's 0 and leave the process at
    0 for good (a file another thread creates in that instant still gets mode 0666).
    """
    try:
        with open(_PROC_STATUS, encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _UMASK_LOCK:
        umask = os.umask(0)
        os.umask(umask)
    return umask


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str], suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success.

    A failure leaves ``path`` as it was (never half-written) and removes the temporary file.
    ``suffix`` defaults to the target's suffix so format-sniffing writers (Open3D) still work.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(
        prefix=f".{target.name}.",
        suffix=suffix if suffix is not None else target.suffix,
        dir=target.parent,
    )
    os.close(fd)
    tmp = Path(tmp_name)
    # mkstemp makes the file private (0600); an output should get the usual umask permissions.
    umask = current_umask()
    try:
        yield tmp
        if tmp.exists():
            os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    with atomic_output(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _without_nan(obj: Any) -> Any:
    """``obj`` with NaN and infinite floats as ``None`` (JSON has no NaN; readers choke on it)."""
    if isinstance(obj, float | np.floating):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.ndarray):
        return _without_nan(obj.tolist())
    if isinstance(obj, dict):
        return {k: _without_nan(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_without_nan(v) for v in obj]
    return obj


def write_json_atomic(path: str | os.PathLike[str], obj: Any) -> None:
    """Write ``obj`` as indented JSON, atomically.

    NumPy arrays and scalars are allowed; a NaN or infinite number (an undetermined figure)
    is written as ``null``, since strict JSON readers refuse NaN.
    """
    text = json.dumps(_without_nan(obj), indent=2, default=_json_default, allow_nan=False)
    write_text_atomic(path, text + "\n")


@contextlib.contextmanager
def commit_together() -> Iterator[Callable[[Path], Path]]:
    """Write several outputs of one run so that they appear together or not at all.

    Yields ``staged(final_path) -> Path``: where to write ``final_path`` for now (the same
    name, in a hidden folder made beside it, so that a folder that cannot be written to fails
    here, before anything is replaced). Writers that derive sibling names from their path
    (``x.json`` -> ``x.csv``, ``x.html``) can be handed the staged path: every file written
    into a staged folder is committed. On success the staged files are renamed onto their
    final paths (same file system: each rename is atomic); on any failure nothing final is
    touched and the staged files are removed, so a failed run never replaces earlier outputs
    with half of a new set.
    """
    staging: list[Path] = []

    finals: set[Path] = set()

    def staged(final: Path) -> Path:
        final = Path(final)
        key = final.resolve()
        if key in finals:
            raise InputError(final, "named for two outputs of one run; give each its own name")
        if final.is_dir():
            raise InputError(final, "is a folder; expected a file name to write")
        finals.add(key)
        final.parent.mkdir(parents=True, exist_ok=True)
        folder = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=final.parent))
        staging.append(folder)
        return folder / final.name

    umask = current_umask()
    try:
        yield staged
        produced = [(f, folder.parent / f.name) for folder in staging for f in folder.iterdir()]
        for _, final in produced:
            if final.is_dir():
                raise InputError(final, "is a folder; expected a file name to write")
        for tmp, _ in produced:
            os.chmod(tmp, 0o666 & ~umask)
        for tmp, final in produced:
            os.replace(tmp, final)
    finally:
        for folder in staging:
            shutil.rmtree(folder, ignore_errors=True)


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_outputs_apart(inputs: Iterable[str | os.PathLike[str]], outputs: Iterable[Path]) -> None:
    """Refuse an output that is, or would replace, an input (same path, same file, or a file
    inside an input folder such as a session), two outputs with one name, and an output
    where a folder stands.

    Raises
    ------
    InputError
        Naming the output and the input it would overwrite.
    """
    ins = [Path(p).resolve() for p in inputs]
    for out in outputs:
        o = Path(out).resolve()
        for i in ins:
            inside = i.is_dir() and (o == i or i in o.parents)
            if o == i or inside or _same_file(o, i):
                raise InputError(out, f"would overwrite the input {i}; write it elsewhere")
    # Outputs among themselves, and outputs a folder stands in for: refused before the work.
    seen: set[Path] = set()
    for out in outputs:
        o = Path(out).resolve()
        if o in seen:
            raise InputError(out, "named for two outputs of one run; give each its own name")
        if o.is_dir():
            raise InputError(out, "is a folder; expected a file name to write")
        seen.add(o)


def read_json_object(
    path: str | os.PathLike[str], missing: str = "file not found"
) -> dict[str, Any]:
    """Read a JSON file that must hold one object; every failure is an :class:`InputError`.

    ``missing`` is the reason given when the file does not exist. Invalid JSON names its
    line; a document nested too deep to parse (a hostile or broken file) is refused too.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, missing)
    try:
        obj = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(p, f"cannot read: {exc}") from None
    except json.JSONDecodeError as exc:
        raise InputError(p, f"not valid JSON (line {exc.lineno}: {exc.msg})") from None
    except RecursionError:
        raise InputError(p, "not valid JSON (nested too deep)") from None
    if not isinstance(obj, dict):
        raise InputError(p, f"expected a JSON object, got {type(obj).__name__}")
    return obj


def json_int(value: Any, where: str) -> int:
    """A whole number as JSON gives it (``1280``, or ``1280.0``), never a bool, a string or a
    fraction; ``ValueError`` naming ``where`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{where}: expected a whole number, got {value!r}")
    if isinstance(value, float) and not (math.isfinite(value) and value.is_integer()):
        raise ValueError(f"{where}: expected a whole number, got {value!r}")
    return int(value)
