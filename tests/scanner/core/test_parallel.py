"""Worker pools: processes for Python-heavy stages, threads for GIL-releasing ones."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from scanner.core.parallel import process_map, thread_map, thread_pool
from scanner.stripe.extract import extract_stripe
from scanner.virtual_cell.analytic import StripeSegment, render_stripes
from tests.cancelling import CancelAt, Cancelled


def _frame(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    seg = StripeSegment(
        (0, 240), (rng.uniform(100, 200), rng.uniform(-0.2, 0.2), 0.0), amplitude=150.0
    )
    img, _ = render_stripes((240, 320), [seg], noise=2.0, background=8.0, seed=seed)
    return img


def test_a_thread_pool_runs_tasks_in_threads_of_this_process():
    with thread_pool(2) as pool:
        names = set(pool.map(lambda _: threading.current_thread().name, range(8)))
    assert names and all(n.startswith("scanner-worker") for n in names)


def test_a_thread_pool_refuses_no_workers():
    with pytest.raises(ValueError, match="expected >= 1, got 0"):
        thread_pool(0)


def test_stripes_extracted_on_threads_equal_those_of_one_thread():
    frames = [_frame(seed) for seed in range(6)]
    alone = [extract_stripe(f, "fast", "rows") for f in frames]
    with thread_pool(2) as pool:
        pooled = list(pool.map(lambda f: extract_stripe(f, "fast", "rows"), frames))
    for a, b in zip(alone, pooled, strict=True):
        np.testing.assert_array_equal(a.u, b.u)
        np.testing.assert_array_equal(a.flags, b.flags)


def _touch_and_square(item: tuple[Path, int]) -> int:
    """(module level: a pool's processes import it) Leaves a file saying it ran."""
    folder, x = item
    (folder / f"{x}.done").touch()
    time.sleep(0.01)
    return x * x


@pytest.mark.parametrize(("workers", "count"), [(1, 10), (2, 3), (2, 10)])
def test_process_map_gives_the_results_in_order(tmp_path: Path, workers: int, count: int):
    items = [(tmp_path, x) for x in range(count)]
    assert list(process_map(_touch_and_square, items, workers, chunksize=2)) == [
        x * x for x in range(count)
    ]


@pytest.mark.parametrize("workers", [1, 2])
def test_a_cancelled_process_map_stops_and_drops_what_has_not_started(tmp_path: Path, workers: int):
    check = CancelAt(3)  # before the first item, after the first, after the second

    items = [(tmp_path, x) for x in range(300)]
    results = []
    with pytest.raises(Cancelled):
        for r in process_map(_touch_and_square, items, workers, chunksize=2, check_cancelled=check):
            results.append(r)
    assert results == [0, 1] and check.calls == 3
    started = len(list(tmp_path.glob("*.done")))
    # (the items the pool's processes hold finish, a few on a quiet machine; the rest are
    # dropped)
    assert 2 <= started <= (2 if workers == 1 else 299)


def test_process_map_refuses_no_workers(tmp_path: Path):
    with pytest.raises(ValueError, match="workers: expected >= 1, got 0"):
        list(process_map(_touch_and_square, [(tmp_path, 1)], 0))


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_thread_map_gives_the_results_in_order_and_checks_with_a_free_worker(workers: int):
    # Each check comes when a worker is free for the next item (at most workers - 1 running),
    # as a loop's check comes between its items; the pool alone would bound only how many run.
    lock = threading.Lock()
    running, at_check = [0], []

    def slow_square(x: int) -> int:
        with lock:
            running[0] += 1
        time.sleep(0.01 * (x % 3))  # later items may end first
        with lock:
            running[0] -= 1
        return x * x

    def check() -> None:
        time.sleep(0.002)  # the items just handed over have started
        with lock:
            at_check.append(running[0])

    squares = thread_map(slow_square, range(12), workers, check_cancelled=check)
    assert squares == [x * x for x in range(12)]
    assert len(at_check) == 12 and max(at_check) <= workers - 1


@pytest.mark.parametrize("workers", [1, 2])
def test_a_cancelled_thread_map_starts_nothing_after_the_check_and_ends_what_runs(workers: int):
    # As a loop that checks before each item: the check that raises is the fourth, so three
    # items were started, and all three end before the cancellation comes out.
    started, ended = [], []

    def record(x: int) -> int:
        started.append(x)
        time.sleep(0.02)
        ended.append(x)
        return x

    check = CancelAt(4)
    with pytest.raises(Cancelled):
        thread_map(record, range(20), workers, check_cancelled=check)
    assert check.calls == 4
    assert sorted(started) == [0, 1, 2] and sorted(ended) == [0, 1, 2]
    # A cancellation that comes while the items run (here: once one has ended) stops the
    # items after those already started; none waits queued past a check.
    started.clear()
    ended.clear()

    def cancelled_once_one_ended() -> None:
        if ended:
            raise Cancelled

    with pytest.raises(Cancelled):
        thread_map(record, range(20), workers, check_cancelled=cancelled_once_one_ended)
    assert sorted(started) == list(range(workers))


def test_thread_map_passes_an_items_error_on_and_refuses_no_workers():
    def fail_on_two(x: int) -> int:
        if x == 2:
            raise RuntimeError("item 2")
        return x

    with pytest.raises(RuntimeError, match="item 2"):
        thread_map(fail_on_two, range(6), 2)
    with pytest.raises(ValueError, match="workers: expected >= 1, got 0"):
        thread_map(fail_on_two, [1], 0)
