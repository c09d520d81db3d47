"""The allocator keeps freed image-sized blocks: a new full-image array faults no pages."""

from __future__ import annotations

import resource

import numpy as np
import pytest

from scanner.core.memory import keep_freed_memory


def _faults_per_array(rounds: int = 10, alive: int = 6) -> float:
    """Minor page faults per fresh 1280x1024 float64 map, ``alive`` of them at a time (as a
    detection's temporaries are), each written through, all freed at the end of a round."""
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(rounds):
        maps = [np.empty((1024, 1280)) for _ in range(alive)]
        for a in maps:
            a[:] = 1.0  # every page touched
        del maps, a
    return (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / (rounds * alive)


def test_a_freed_image_sized_block_is_used_again() -> None:
    if not keep_freed_memory():
        pytest.skip("the C library is not glibc: its allocator is left as it is")
    assert keep_freed_memory()  # idempotent
    _faults_per_array(2)  # (the heap grown once)
    # Without it, glibc gives back the freed top of its heap over twice the largest block
    # freed so far: here about 500 faults per map (of 2560 pages), on the detector about 10 000 a view.
    assert _faults_per_array() < 1.0
