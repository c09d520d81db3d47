"""The standard Hough transform of a binary mask: OpenCV's lines, computed cache-friendly.

The ring detector's coarse stage looks for the target's diameters among every Hough line of
its line mask (:func:`calibration.detection.concentric_rays._hough_lines`), at 0.25 deg
steps. ``cv2.HoughLines`` votes pixel by pixel: each mask pixel adds one vote to each of the
720 rows of a 13 MB accumulator (1280x1024 image), and most of its time (about 15 % of such
a view's detection) went to cache misses. :func:`hough_lines` gives the same lines, to the
bit and in the same order, angle by angle instead: one accumulator row at a time (4 partial
rows, interleaved, so that runs of votes into one cell do not wait on each other), each
row's local maxima taken as soon as its neighbours are complete, the lines then ordered by
votes (a counting sort; within equal votes, by accumulator index, as OpenCV orders them).
About 1.6 times faster than OpenCV's on the detector's masks (``benchmarks/RESULTS.md``,
thirty-first session).

OpenCV's arithmetic is kept exactly: the angle table accumulated in float32, each vote's
``rho = x cos + y sin`` in float32 (two products and a sum, not fused: numba fuses nothing
without ``fastmath``, and neither does OpenCV's x86-64 build; a build that fuses them, as
compilers may on aarch64, would differ in the last bit, and the test comparing the two
would say so) and rounded half to even, the peak test (strictly above the threshold and the
lower neighbours, at least the upper ones), the lines' float32 ``(rho, theta)``. Without
numba (:data:`HAVE_NUMBA`) OpenCV's function is called instead.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from scanner.core.jit import HAVE_NUMBA, njit

__all__ = ["HAVE_NUMBA", "hough_lines"]


@njit(cache=True, nogil=True)
def _angle_table(numangle, theta_step):  # pragma: no cover - compiled
    """cos and sin of the angles ``0, step, 2 step ...``, the angle summed in float32 (1 px
    rho steps)."""
    tab_cos = np.empty(numangle, np.float32)
    tab_sin = np.empty(numangle, np.float32)
    angle = np.float32(0.0)
    for n in range(numangle):
        tab_cos[n] = np.float32(np.cos(np.float64(angle)))
        tab_sin[n] = np.float32(np.sin(np.float64(angle)))
        angle = np.float32(angle + theta_step)
    return tab_cos, tab_sin


@njit(cache=True, nogil=True)
def _votes_and_peaks(us, vs, tab_cos, tab_sin, numrho, threshold):  # pragma: no cover - compiled
    """The peaks of the accumulator over ``threshold``, ordered: ``(angle index, rho
    index)``, each shape (N,), int32."""
    numangle = tab_cos.shape[0]
    shift = (numrho - 1) // 2 + 1  # (+1: the accumulator's guard column)
    n_pts = us.shape[0]
    width = numrho + 2
    rows = np.zeros((3, width), np.int32)  # accumulator rows i-2, i-1, i in turn
    partial = np.zeros((4, width), np.int32)
    rho = np.empty(n_pts, np.int32)
    n4 = n_pts - n_pts % 4
    cap = numangle * (numrho // 2 + 1)  # (peaks are never side by side along rho)
    peak_n = np.empty(cap, np.int32)
    peak_r = np.empty(cap, np.int32)
    peak_votes = np.empty(cap, np.int32)
    m = 0
    top = 0  # the most votes of a peak
    # Row i of the accumulator holds angle i - 1; rows 0 and numangle + 1 are its zero guard.
    for i in range(1, numangle + 2):
        cur = rows[i % 3]
        if i <= numangle:
            c = tab_cos[i - 1]
            s = tab_sin[i - 1]
            for k in range(n_pts):
                rho[k] = np.int32(np.rint(us[k] * c + vs[k] * s)) + shift
            for k in range(0, n4, 4):
                partial[0, rho[k]] += 1
                partial[1, rho[k + 1]] += 1
                partial[2, rho[k + 2]] += 1
                partial[3, rho[k + 3]] += 1
            for k in range(n4, n_pts):
                partial[0, rho[k]] += 1
            for j in range(width):
                cur[j] = partial[0, j] + partial[1, j] + partial[2, j] + partial[3, j]
                partial[0, j] = 0
                partial[1, j] = 0
                partial[2, j] = 0
                partial[3, j] = 0
        else:
            cur[:] = 0
        if i >= 2:  # row i - 1 has both neighbours now
            below = rows[(i - 2) % 3]
            mid = rows[(i - 1) % 3]
            for r in range(1, numrho + 1):
                a = mid[r]
                if (
                    a > threshold
                    and a > mid[r - 1]
                    and a >= mid[r + 1]
                    and a > below[r]
                    and a >= cur[r]
                ):
                    peak_n[m] = i - 2
                    peak_r[m] = r - 1
                    peak_votes[m] = a
                    m += 1
                    top = max(top, a)
    # Most votes first; equal votes in the order found (OpenCV's: by accumulator index).
    start = np.zeros(top + 1, np.int64)
    for q in range(m):
        start[peak_votes[q]] += 1
    total = 0
    for a in range(top, -1, -1):
        count = start[a]
        start[a] = total
        total += count
    out_n = np.empty(m, np.int32)
    out_r = np.empty(m, np.int32)
    for q in range(m):
        pos = start[peak_votes[q]]
        start[peak_votes[q]] += 1
        out_n[pos] = peak_n[q]
        out_r[pos] = peak_r[q]
    return out_n, out_r


def _numangle(theta_step: np.float32) -> int:
    """Angles from 0 below pi (the last one dropped where it is pi itself, to half a step)."""
    step = float(theta_step)
    n = int(np.floor(np.pi / step)) + 1
    if n > 1 and abs(np.pi - (n - 1) * step) < step / 2:
        n -= 1
    return n


def hough_lines(mask: NDArray, theta_step_rad: float, threshold: int) -> NDArray:
    """Every line of the standard Hough transform of ``mask`` with more than ``threshold``
    votes, most votes first: ``cv2.HoughLines(mask, 1.0, theta_step_rad, threshold)``.

    Parameters
    ----------
    mask : ndarray, shape (H, W), uint8
        Non-zero pixels vote.
    theta_step_rad : float
        The angle step (> 0); angles run from 0 below pi. The rho step is 1 px.
    threshold : int
        A line needs more votes than this (an integer).

    Returns
    -------
    ndarray, shape (N, 2), float32
        ``(rho px, theta rad)`` of each line, as OpenCV gives them; N may be 0.
    """
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype != np.uint8:
        raise ValueError(f"mask: expected a 2-D uint8 array, got {mask.dtype} {mask.shape}")
    step = np.float32(theta_step_rad)
    if not (np.isfinite(step) and step > 0):
        raise ValueError(
            f"theta_step_rad: expected a finite step > 0 (in float32), got {theta_step_rad}"
        )
    if int(threshold) != threshold:
        raise ValueError(f"threshold: expected an integer, got {threshold}")
    if not HAVE_NUMBA:  # pragma: no cover - numba is a dependency
        lines = cv2.HoughLines(mask, 1.0, float(theta_step_rad), int(threshold))
        return np.zeros((0, 2), np.float32) if lines is None else lines[:, 0, :]
    h, w = mask.shape
    numrho = 2 * (w + h) + 1
    tab_cos, tab_sin = _angle_table(_numangle(step), step)
    rows, cols = np.nonzero(mask)
    us, vs = cols.astype(np.float32), rows.astype(np.float32)
    del rows, cols  # (int64: twice the float32 copies, not kept through the votes)
    n, r = _votes_and_peaks(us, vs, tab_cos, tab_sin, numrho, int(threshold))
    rho = r.astype(np.float32) - np.float32((numrho - 1) * 0.5)
    theta = n.astype(np.float32) * step
    return np.column_stack([rho, theta])
