"""The C allocator told to keep freed image-sized blocks for the next array.

The stages work on whole images: the ring detector alone makes dozens of full-image
temporaries per view (a 1280x1024 float64 map is 10 MiB). glibc's ``malloc`` serves blocks
of that size from its heap once one has been freed (its mmap threshold rises), but it gives
the freed top of the heap back to the kernel whenever that passes twice the largest block
freed so far, and the next maps are then paid again in page faults: the kernel zeroes and
maps each 4 KiB page on its first touch (about 1.5 us a page here; 7000-11000 faults per
detection, so 3-5 % of its time, ``benchmarks/RESULTS.md``, fortieth session). Told to serve
blocks up to 32 MiB from its heap and to keep up to 256 MiB of freed heap for reuse,
``malloc`` hands the same pages out again and a detection makes no page fault at all; what
is computed does not change.

The price is memory: a process keeps up to :data:`KEEP_FREED_BYTES` of freed heap instead
of returning it (its resident size stays near its peak, plus that much at most). The setting
is process-wide (the allocator is the process's), so the application makes it where one of
its processes starts: the ``scanner`` command (every command, the PLC service included) and
the worker processes of :mod:`scanner.core.parallel`, and the detection benchmark; a library
call of the stages leaves its caller's allocator as it is, and so do the Dask workers of the
batch runner (started by Dask's nanny). Where the C library is not glibc it does nothing.
"""

from __future__ import annotations

import ctypes
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
    try:
        libc = ctypes.CDLL(None)  # (the process's own symbols: its C library's among them)
    except OSError:
        return _done
    mallopt = getattr(libc, "mallopt", None)
    gnu = getattr(libc, "gnu_get_libc_version", None)
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
