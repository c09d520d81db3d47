"""Worker pools for the stages that use both cores.

Processes (:func:`process_pool`) for the stages whose work is mostly Python (target detection,
rendering). They are started with ``spawn``, never ``fork``: OpenCV, OpenBLAS and Open3D keep
thread pools whose locks a forked child inherits in whatever state the parent left them, and a
child that then touches them (``cv2.setNumThreads``, a BLAS call) can wait forever. Spawned
workers cost an interpreter start and the imports (about a second) once per pool, not per task.
:func:`process_map` runs a function over items on such a pool, in order, and stops at a
caller's cancellation (a PLC job's) with the pool's unstarted items dropped.

Threads (:func:`thread_pool`) for the stages whose heavy steps release the GIL: the scan's
stripe extraction decodes frames in OpenCV and measures them in compiled kernels that run
without the GIL, so two threads keep both cores busy without that second's start (on a
300-frame sweep the scan took 1.8-1.9 s with threads against 4.1 s with processes).
:func:`thread_map` runs independent fits on such threads, at most N at a time, each started
after the cancellation check a plain loop would make: the distortion model's fold fits
(their projections and derivatives are compiled kernels that release the GIL: 6.4 s on one
thread -> 5.2-5.4 s on two for the intrinsics of a 20-view session, thirty-ninth session; the
uncertainty's re-solves, which hold the GIL longer, were slower on threads and stay in turn).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from typing import TypeVar

import cv2

from scanner.core.memory import keep_freed_memory

__all__ = ["process_map", "process_pool", "thread_map", "thread_pool"]

T = TypeVar("T")
R = TypeVar("R")

log = logging.getLogger(__name__)


def _exit_with(parent: int) -> None:
    """End this worker once ``parent`` is gone (a killed parent runs no clean-up of its own)."""
    while True:
        time.sleep(0.5)
        if os.getppid() != parent:
            os._exit(3)


def _init_worker(parent: int) -> None:
    # Each worker is one of N parallel processes: nested thread pools only oversubscribe.
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    cv2.setNumThreads(1)
    keep_freed_memory()  # (as the command does: scanner.core.memory)
    # The parent's pid is passed in: a worker still starting when the parent dies would
    # already read its new parent (pid 1) from os.getppid().
    threading.Thread(target=_exit_with, args=(parent,), name="parent-watch", daemon=True).start()


def process_pool(workers: int) -> Executor:
    """A process pool of ``workers`` spawned processes, each limited to one thread, each
    ending by itself when this process dies (even by SIGKILL).

    In a daemonic process (a Dask worker, a host's own daemon pool), which may not start
    children, it is a thread pool of ``workers`` threads instead: the stages' heavy steps
    (OpenCV, NumPy) release the GIL, and the stage still runs rather than failing.
    """
    if workers < 1:
        raise ValueError(f"workers: expected >= 1, got {workers}")
    if multiprocessing.current_process().daemon:
        log.info("daemonic process: %d worker threads instead of processes", workers)
        return ThreadPoolExecutor(max_workers=workers)
    return ProcessPoolExecutor(
        max_workers=workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_init_worker,
        initargs=(os.getpid(),),
    )


def thread_pool(workers: int) -> Executor:
    """A pool of ``workers`` threads of this process, for tasks whose heavy steps release the
    GIL (OpenCV's decoding and filters, NumPy's array operations, numba kernels compiled with
    ``nogil``).

    The tasks share this process's OpenCV settings: a task must not change them (no
    ``cv2.setNumThreads``), or the rest of the process runs with its change. (So an OpenCV
    call of a task may start OpenCV's own threads beside the pool's: on the scan's decoding
    and stripe steps that costs nothing measurable.)
    """
    if workers < 1:
        raise ValueError(f"workers: expected >= 1, got {workers}")
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="scanner-worker")


def process_map(
    func: Callable[[T], R],
    items: Iterable[T],
    workers: int,
    chunksize: int = 1,
    check_cancelled: Callable[[], None] | None = None,
) -> Iterator[R]:
    """``func`` of each item, in order: on a :func:`process_pool` of ``workers``, or in this
    process where ``workers`` is 1 or the items are fewer than 4 (a pool's start would cost
    more than it saves).

    ``check_cancelled`` is called before the first item and after each result: what it
    raises comes out of the iteration. Then, as when the caller stops iterating (close the
    iterator, e.g. with :func:`contextlib.closing`, rather than leave it to the garbage
    collector) or an item raises, the pool drops the items not yet started and waits for
    those its processes hold: with ``check_cancelled`` they are sent one at a time (not in
    chunks), so that is at most a few items.

    Parameters
    ----------
    func : callable
        A module-level function (a pool's processes import it by name).
    items : iterable
        Its arguments, one per call.
    workers : int
        At least 1.
    chunksize : int
        Items sent to a pool's process at a time, without ``check_cancelled``.
    check_cancelled : callable, optional
        Raises to stop (a PLC job's cancellation).

    Yields
    ------
    The results, in the order of ``items``.
    """
    if workers < 1:
        raise ValueError(f"workers: expected >= 1, got {workers}")
    check = check_cancelled or (lambda: None)
    jobs = list(items)
    check()
    if workers == 1 or len(jobs) < 4:
        for job in jobs:
            yield func(job)
            check()
        return
    pool = process_pool(workers)
    try:
        size = chunksize if check_cancelled is None else 1
        for result in pool.map(func, jobs, chunksize=size):
            yield result
            check()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def thread_map(
    func: Callable[[T], R],
    items: Iterable[T],
    workers: int,
    check_cancelled: Callable[[], None] | None = None,
) -> list[R]:
    """``func`` of each item, in order, at most ``workers`` at a time on threads of this
    process: for independent fits whose array steps release the GIL (NumPy, LAPACK).

    ``check_cancelled`` is called before each item is started, as a loop over the items
    would call it: what it raises comes out once the items already running (at most
    ``workers - 1``) have ended, and the others are never started. An item that raises does
    the same. ``workers`` 1 runs the items in this thread.

    Parameters
    ----------
    func : callable
        Any callable; the items may share read-only state through it.
    items : iterable
        Its arguments, one per call.
    workers : int
        At least 1.
    check_cancelled : callable, optional
        Raises to stop (a PLC job's cancellation).

    Returns
    -------
    list
        The results, in the order of ``items``.
    """
    if workers < 1:
        raise ValueError(f"workers: expected >= 1, got {workers}")
    check = check_cancelled or (lambda: None)
    if workers == 1:
        out = []
        for item in items:
            check()
            out.append(func(item))
        return out
    done: list[R] = []
    with thread_pool(workers) as pool:
        running: deque[Future[R]] = deque()
        for item in items:
            if len(running) >= workers:
                done.append(running.popleft().result())
            check()
            running.append(pool.submit(func, item))
        done += [fut.result() for fut in running]
    return done
