"""Worker pools: processes for Python-heavy stages, threads for GIL-releasing ones."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from scanner.core.parallel import thread_pool
from scanner.stripe.extract import extract_stripe
from scanner.virtual_cell.analytic import StripeSegment, render_stripes


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
