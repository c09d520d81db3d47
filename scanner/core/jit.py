"""numba's ``njit`` where numba imports, and a stand-in that leaves the function as Python.

numba is a dependency (the stripe's and the ring detector's compiled kernels); the stand-in
keeps the package importable on a platform without it, where the same code runs slowly.
:data:`HAVE_NUMBA` tells which one is in use.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

__all__ = ["HAVE_NUMBA", "njit"]

try:
    from numba import njit
except ImportError:  # pragma: no cover - numba is a dependency; kept for odd platforms
    HAVE_NUMBA = False

    def njit(*args: Any, **kwargs: Any) -> Callable[[Callable[..., Any]], Callable[..., Any]]:  # type: ignore[no-redef]
        return lambda fn: fn

else:
    HAVE_NUMBA = True
