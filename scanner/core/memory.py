"""The C allocator told to keep freed image-sized blocks for the next array.

The stages work on whole images: the ring detector alone makes dozens of full-image
temporaries per view (a 1280x1024 float64 map is 10 MiB). glibc's ``malloc`` hands blocks of
that size out as fresh ``mmap`` pages and gives them back to the kernel when they are freed,
so every such array is paid again in page faults: the kernel zeroes and maps each 4 KiB page
on its first touch (about 1.5 us a page here, 4 ms for each 10 MiB map; 7000-11000 faults, so
3-5 % of a detection's time, ``benchmarks/RESULTS.md``, fortieth session). Told to serve
blocks up to 32 MiB from its heap and to keep up to 256 MiB of freed heap for reuse,
``malloc`` hands the same pages out again and a detection makes no page fault at all; what
is computed does not change.

:func:`keep_freed_memory` is process-wide (the allocator is the process's), so the
application calls it where a process starts: the ``scanner`` command, the worker processes
(:mod:`scanner.core.parallel`) and the benchmarks; a library call of the stages leaves the
caller's allocator as it is. Where the C library is not glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

__all__ = ["KEEP_FREED_BYTES", "MMAP_FROM_BYTES", "keep_freed_memory"]

log = logging.getLogger(__name__)

#: Blocks at least this large still come from ``mmap`` (glibc's largest threshold on a 64-bit
#: system): a 12 Mpx float64 image and larger are rare and outlive their stage.
MMAP_FROM_BYTES = 32 * 1024 * 1024
#: Freed heap kept for reuse before ``malloc`` gives it back to the kernel.
KEEP_FREED_BYTES = 256 * 1024 * 1024

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

_done: bool | None = None


def keep_freed_memory() -> bool:
    """Have glibc's ``malloc`` serve image-sized blocks from its heap and keep freed ones.

    Idempotent; returns whether the allocator was set (``False`` where the C library is not
    glibc or refused the settings).
    """
    global _done
    if _done is not None:
        return _done
    _done = False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        mallopt = None if libc is None else getattr(libc, "mallopt", None)
        gnu = None if libc is None else getattr(libc, "gnu_get_libc_version", None)
    except OSError:
        return _done
    if mallopt is None or gnu is None:  # not glibc (musl, macOS): left as it is
        return _done
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    _done = bool(
        mallopt(_M_MMAP_THRESHOLD, MMAP_FROM_BYTES) and mallopt(_M_TRIM_THRESHOLD, KEEP_FREED_BYTES)
    )
    if not _done:
        log.info("malloc kept its own settings (mallopt refused)")
    return _done
