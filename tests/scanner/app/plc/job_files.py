"""What a running job leaves in the service's work folder, as the PLC tests wait for it."""

from __future__ import annotations

import time
from pathlib import Path


def wait_for_job_pid(work_dir: Path, timeout_s: float, job: int = 1) -> int:
    """The process id a job writes to ``job-NNNNNN/pid`` once it runs, waiting up to ``timeout_s``.

    Parameters
    ----------
    work_dir : Path
        The service's ``storage.work_dir``.
    timeout_s : float
        How long to wait for the file; reading it then fails if it is still absent.
    job : int
        The job's number in the service's history.

    Returns
    -------
    int
    """
    pid_file = work_dir / f"job-{job:06d}" / "pid"
    deadline = time.monotonic() + timeout_s
    while not pid_file.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    return int(pid_file.read_text())
