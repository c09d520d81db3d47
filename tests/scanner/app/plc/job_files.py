"""What a running job leaves in the service's work folder, as the PLC tests wait for it."""

from __future__ import annotations

import os
import time
from pathlib import Path


def write_whole(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` whole: a reader polling for the file sees none or all of it.

    A plain ``write_text`` creates the file before it writes, so a test polling for the file
    could read it empty; the text goes to a temporary name and is renamed into place.
    """
    partial = path.with_name(path.name + ".partial")
    partial.write_text(text, encoding="utf-8")
    os.replace(partial, path)


def write_job_pid(job_dir: Path) -> None:
    """Write this process's id to ``job_dir/pid`` (:func:`write_whole`).

    Parameters
    ----------
    job_dir : Path
        The job's own work folder (``job-NNNNNN``); created if missing.
    """
    job_dir.mkdir(parents=True, exist_ok=True)
    write_whole(job_dir / "pid", str(os.getpid()))


def wait_for_job_pid(work_dir: Path, timeout_s: float, job: int = 1) -> int:
    """The process id a job writes to ``job-NNNNNN/pid`` once it runs, waiting up to ``timeout_s``.

    Parameters
    ----------
    work_dir : Path
        The service's ``storage.work_dir``.
    timeout_s : float
        How long to wait for the file to hold a number; reading it then fails if it does not.
    job : int
        The job's number in the service's history.

    Returns
    -------
    int
    """
    pid_file = work_dir / f"job-{job:06d}" / "pid"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        text = pid_file.read_text() if pid_file.exists() else ""
        if text.strip().isdigit():
            return int(text)
        time.sleep(0.05)
    return int(pid_file.read_text())
