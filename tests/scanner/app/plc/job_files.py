"""What a running job leaves in the service's work folder, as the PLC tests wait for it."""

from __future__ import annotations

import os
import time
from pathlib import Path


def write_job_pid(job_dir: Path) -> None:
    """Write this process's id to ``job_dir/pid`` whole: a reader sees no file or the full number.

    A plain ``write_text`` creates the file before it writes the digits, so a test polling for
    the file could read it empty; the id goes to a temporary name and is renamed into place.

    Parameters
    ----------
    job_dir : Path
        The job's own work folder (``job-NNNNNN``); created if missing.
    """
    job_dir.mkdir(parents=True, exist_ok=True)
    partial = job_dir / "pid.partial"
    partial.write_text(str(os.getpid()), encoding="utf-8")
    os.replace(partial, job_dir / "pid")


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
