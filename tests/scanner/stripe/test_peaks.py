"""Several peaks per scan line: the segments that link them."""

from __future__ import annotations

import numpy as np
import pytest

from scanner.stripe import peaks
from scanner.stripe.kernels import HAVE_NUMBA
from scanner.stripe.profile import _Peaks


def _random_peaks(rng: np.random.Generator, n_lines: int = 300) -> _Peaks:
    """Three wandering segments with dropouts, stray peaks and two that cross."""
    lines, pos = [], []
    for start, slope in ((40.0, 0.3), (200.0, -0.25), (120.0, 0.0)):
        line = np.flatnonzero(rng.random(n_lines) > 0.15)  # dropouts, some two lines long
        lines.append(line)
        pos.append(start + slope * line + rng.normal(0.0, 0.4, line.size))
    stray = rng.integers(0, n_lines, 60)
    lines.append(stray)
    pos.append(rng.uniform(0.0, 300.0, stray.size))
    line = np.concatenate(lines).astype(np.int64)
    order = rng.permutation(line.size)  # the labels must not depend on the input order
    n = line.size
    z = np.zeros(n, np.float32)
    return _Peaks(line[order], np.concatenate(pos)[order], z, z, z, np.zeros(n, np.uint8), z)


@pytest.mark.skipif(not HAVE_NUMBA, reason="numba is not installed")
@pytest.mark.parametrize("max_gap", [1, 2])
def test_compiled_segments_label_as_the_sparse_graph_does(max_gap, monkeypatch):
    rng = np.random.default_rng(5)
    for _ in range(20):
        p = _random_peaks(rng)
        got = peaks._segments(p, link_px=2.0, max_gap=max_gap)
        with monkeypatch.context() as m:
            m.setattr(peaks, "HAVE_NUMBA", False)
            want = peaks._segments(p, link_px=2.0, max_gap=max_gap)
        np.testing.assert_array_equal(got, want)
        assert 3 < got.max() + 1 < p.line.size  # segments formed, strays left alone


def test_segments_follow_a_stripe_across_a_dropout_only_with_a_gap_of_two():
    line = np.array([0, 1, 2, 4, 5, 6])
    pos = np.array([10.0, 10.5, 11.0, 12.0, 12.5, 13.0])
    z = np.zeros(line.size, np.float32)
    p = _Peaks(line, pos, z, z, z, np.zeros(line.size, np.uint8), z)
    np.testing.assert_array_equal(peaks._segments(p, 1.0, max_gap=1), [0, 0, 0, 1, 1, 1])
    np.testing.assert_array_equal(peaks._segments(p, 1.0, max_gap=2), [0, 0, 0, 0, 0, 0])


def _partition(labels: np.ndarray) -> list[frozenset[int]]:
    groups: dict[int, set[int]] = {}
    for i, lab in enumerate(labels.tolist()):
        groups.setdefault(lab, set()).add(i)
    return sorted(frozenset(g) for g in groups.values())


@pytest.mark.parametrize("numba", [True, False])
def test_a_nan_position_links_to_nothing_and_leaves_the_others_linked(numba, monkeypatch):
    """The peaks with a position link as they would without the NaN ones, which stay alone
    (a NaN in the sort key would unsort it and lose links)."""
    if numba and not HAVE_NUMBA:
        pytest.skip("numba is not installed")
    monkeypatch.setattr(peaks, "HAVE_NUMBA", numba)
    rng = np.random.default_rng(8)
    for _ in range(30):
        p = _random_peaks(rng)
        nan = rng.random(p.line.size) < 0.1
        pos = np.where(nan, np.nan, p.pos)
        z = np.zeros(p.line.size, np.float32)
        with_nan = _Peaks(p.line, pos, z, z, z, np.zeros(p.line.size, np.uint8), z)
        got = peaks._segments(with_nan, link_px=2.0, max_gap=2)
        kept = np.flatnonzero(~nan)
        alone = _Peaks(p.line[kept], pos[kept], *([z[kept]] * 3), z[kept].astype(np.uint8), z[kept])
        want = peaks._segments(alone, link_px=2.0, max_gap=2)
        assert _partition(got[kept]) == _partition(want)
        assert all(np.count_nonzero(got == got[i]) == 1 for i in np.flatnonzero(nan))
