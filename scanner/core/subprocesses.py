"""Our own modules run in a fresh interpreter: the service, the command line, from a checkout.

A process started this way imports the checkout at ``root`` (``PYTHONPATH``), not whatever
copy an installed environment would find, and runs with ``root`` as its working folder.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Sequence
from typing import Any

__all__ = ["start_module"]


def start_module(
    module: str, args: Sequence[str], root: str | os.PathLike[str], **popen: Any
) -> subprocess.Popen[str]:
    """Start ``python -m module args`` with this interpreter, importing the checkout at ``root``.

    Parameters
    ----------
    module : str
        Dotted module name, run as ``__main__``.
    args : sequence of str
        Its command-line arguments.
    root : path
        The checkout: put on ``PYTHONPATH`` and made the working folder.
    **popen
        Passed to :class:`subprocess.Popen` (``stdout=subprocess.PIPE``, ...); the process is
        always in text mode.

    Returns
    -------
    subprocess.Popen
    """
    env = {**os.environ, "PYTHONPATH": str(root)}
    return subprocess.Popen(
        [sys.executable, "-m", module, *args], cwd=root, env=env, text=True, **popen
    )
