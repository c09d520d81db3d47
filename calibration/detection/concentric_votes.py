"""Candidate images of O where the printed lines' edges point: the last sweep's centres.

Every other pass takes its candidate centres from the crossings of long straight lines
(:mod:`calibration.detection.concentric_centre`). A small target among long clutter edges may
have no such crossing at O: its diameters rank far down the Hough lines (randomised view
1:104, 86 px across in a 640x480 view, ranks 78 and up) or one of them gives no line at all
(2:54, 18:66). But each ring's edges face O: along the darkness's gradient from every edge
pixel, votes cast on both sides meet there, from every ring at once (a Hough transform of
the centres of concentric circles). A tilt ``t`` spreads an ellipse's votes over its
evolute, about ``r sin^2 t`` either way along its major axis and ``r sin^2 t / cos t`` along
its minor one, so the votes are smoothed before their peaks are taken, and the peaks are
only near O on a moderate tilt (at 40 deg within about 6 px for rings of 90 px); the rays
from each peak then judge it as they judge a crossing of lines
(:func:`~calibration.detection.concentric_centre._voted_centre`).

Clutter's circles collect votes too: a peak is only a candidate, refused or kept by the
pencil's radius ratios, the fine stage and, in the last sweep, the orientation marker.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from scanner.core.jit import njit

__all__ = ["VOTED_PEAKS", "axes_through", "full_image_px", "voted_centres"]

#: Vote peaks each scale's rays judge, strongest first. On the randomised benchmark's views
#: that only these candidates reach (1:104, 2:54, 18:66, 22:81) O was among the first five,
#: within 6 px.
VOTED_PEAKS = 8

#: Share of the pixels with any gradient that vote: those whose gradient is in the top fifth
#: (the printed lines' edges; paper grain and noise below).
VOTING_SHARE = 0.2

#: The votes are cast on a map whose shorter side is reduced to about this many pixels (a
#: 1600x1200 view's 370,000 voters over 600 px each take 2 s; halved, a quarter of them
#: over half the reach, 0.1 s), the peaks scaled back.
VOTING_SIDE_PX = 480


@njit(cache=True, nogil=True)
def _cast_votes(gx, gy, mag, threshold, reach, votes):  # pragma: no cover - compiled
    h, w = gx.shape
    for y in range(h):
        for x in range(w):
            m = mag[y, x]
            if m < threshold or m <= 0.0:
                continue
            dx = gx[y, x] / m
            dy = gy[y, x] / m
            for side in (-1.0, 1.0):
                for r in range(2, reach):
                    u = int(np.floor(x + side * r * dx + 0.5))
                    v = int(np.floor(y + side * r * dy + 0.5))
                    if u < 0 or v < 0 or u >= w or v >= h:
                        break
                    votes[v, u] += 1.0


def voted_centres(z: NDArray, n: int = VOTED_PEAKS) -> NDArray:
    """The ``n`` strongest peaks of the votes the edges of the printed lines cast.

    Parameters
    ----------
    z : ndarray, shape (H, W)
        Darkness over its local threshold (the coarse stage's map), negative where the print
        is hidden.
    n : int
        Peaks wanted.

    Returns
    -------
    ndarray, shape (M, 2)
        Peak positions, px, strongest first; ``M <= n`` (fewer where the votes have fewer
        peaks, none on a map without edges).
    """
    h, w = z.shape
    factor = max(1, round(min(h, w) / VOTING_SIDE_PX))
    dark = np.clip(z, 0.0, 4.0).astype(np.float32)
    if factor > 1:
        dark = cv2.resize(dark, (w // factor, h // factor), interpolation=cv2.INTER_AREA)
    dark = cv2.GaussianBlur(dark, (0, 0), 1.0)
    gx = cv2.Sobel(dark, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(dark, cv2.CV_32F, 0, 1)
    mag = np.hypot(gx, gy)
    edges = mag[mag > 0]
    if edges.size == 0:
        return np.zeros((0, 2))
    threshold = float(np.quantile(edges, 1.0 - VOTING_SHARE))
    votes = np.zeros(dark.shape, np.float32)
    _cast_votes(gx, gy, mag, threshold, max(3, min(dark.shape) // 2), votes)
    smooth = cv2.GaussianBlur(votes, (0, 0), 2.0)
    local_max = smooth >= cv2.dilate(smooth, np.ones((9, 9), np.uint8))
    ys, xs = np.nonzero(local_max & (smooth > 0))
    order = np.argsort(-smooth[ys, xs], kind="stable")[:n]
    peaks = np.column_stack([xs[order], ys[order]]).astype(np.float64)
    return full_image_px(peaks, (dark.shape[1], dark.shape[0]), (w, h))


def full_image_px(
    points_px: NDArray, reduced_size: tuple[int, int], full_size: tuple[int, int]
) -> NDArray:
    """Pixel positions ``(N, 2)`` on a map resized from ``full_size`` to ``reduced_size``
    (width, height: OpenCV's resize scales each axis by its own ratio, pixel centres onto
    pixel centres) in the full map's pixels."""
    scale = np.asarray(full_size, dtype=np.float64) / np.asarray(reduced_size, dtype=np.float64)
    return (np.asarray(points_px, dtype=np.float64) + 0.5) * scale - 0.5


def axes_through(z: NDArray, c: NDArray, reach_px: float) -> list[float]:
    """The directions (rad) of the two darkest lines through ``c`` (at least 12 deg apart),
    each both ways: a voted candidate's diameters, for its rays to keep clear of.

    Mean clipped darkness along each line to ``reach_px`` either side (the print hidden
    left out, the first 3 px too), every degree.
    """
    h, w = z.shape
    theta = np.radians(np.arange(180.0))
    t = np.concatenate([-np.arange(3.0, reach_px), np.arange(3.0, reach_px)])
    u = np.rint(c[0] + np.cos(theta)[:, None] * t[None, :]).astype(np.intp)
    v = np.rint(c[1] + np.sin(theta)[:, None] * t[None, :]).astype(np.intp)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    zs = z[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)]
    seen = inside & (zs >= 0)
    strength = np.where(seen, np.clip(zs, 0.0, 4.0), 0.0).sum(axis=1) / np.maximum(
        seen.sum(axis=1), 1
    )
    first = int(np.argmax(strength))
    apart = np.abs((theta - theta[first] + np.pi / 2) % np.pi - np.pi / 2) >= np.radians(12)
    second = int(np.argmax(np.where(apart, strength, -1.0)))
    a, b = float(theta[first]), float(theta[second])
    return [a, a + np.pi, b, b + np.pi]
