"""The candidate image of O: where the rays from a crossing of two long lines find rings.

Step 2 of :mod:`calibration.detection.concentric`: the long straight dark lines (Hough) are
candidates for the two diameters and each crossing of two of them a candidate image of O,
judged by how many rays from it cross the rings in the spec's order
(:func:`~calibration.detection.ray_kernels.label_rays`). On a steep target the chosen
crossing may be off O: a later pass moves it to where the rays find the most rings.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from calibration.detection.concentric_rays import _line_from_hough, _ray_support
from calibration.detection.concentric_votes import axes_through
from calibration.detection.conics import intersect_lines, line_through

#: The coarse stage's maps hold the darkness over its local noise threshold: a printed line
#: may be where it is over this (the Hough mask and the rays' crossings alike).
Z_LINE = 1.0

#: The strongest Hough lines whose crossings every pass tries. Clutter's long lines can
#: outvote a small target's diameters: a generous number is tried (a crossing without rings
#: around it costs little).
HOUGH_LINES = 16

#: The last pass also tries the crossings of the lines after those, up to this many: a small
#: target among long clutter edges (randomised view 5:1) has its diameters ranked 22nd-43rd.
#: Only views every other pass refused pay for it.
WIDE_HOUGH_LINES = 48

#: A candidate image of O ``(2,)`` px, the two Hough lines through it (homogeneous ``(3,)``)
#: and the diameters' four directions from it, rad.
_Centre = tuple[NDArray, tuple[NDArray, NDArray], list[float]]


def _best_centre(
    z_rays: NDArray,
    lines: list[tuple[float, float]],
    radii: NDArray,
    size: tuple[int, int],
    ring0_hidden: bool,
    first_new: int = 0,
    z_line: float = Z_LINE,
    bundle_step_px: float = 0.0,
) -> _Centre | None:
    """The crossing of two long lines with the most ring crossings in order around it.

    Parameters
    ----------
    z_rays : ndarray, shape (H, W)
        Darkness over its local threshold, -1 where the print is hidden.
    lines : list of (rho, theta)
        The strongest long lines (Hough).
    radii : ndarray, shape (K,)
        The spec's ring radii, mm.
    size : (int, int)
        The image's width and height, px.
    ring0_hidden : bool
        See :func:`~calibration.detection.ray_kernels.label_rays`.
    first_new : int
        Only pairs with a line at this index or later: the earlier lines' crossings were
        tried already (the last pass, :data:`WIDE_HOUGH_LINES`).

    Returns
    -------
    tuple or None
        The candidate image of O, its two lines and the diameters' directions
        (:data:`_Centre`); None where no crossing has rings around it (a support of at
        least 12 crossings beyond the two any fit takes, over 96 rays).
    """
    w, h = size
    best = None
    for i in range(len(lines)):
        for j in range(max(i + 1, first_new), len(lines)):
            (r1, t1), (r2, t2) = lines[i], lines[j]
            ang = abs((t1 - t2 + np.pi / 2) % np.pi - np.pi / 2)
            if ang < np.radians(12):
                continue
            l1, l2 = _line_from_hough(r1, t1), _line_from_hough(r2, t2)
            x = intersect_lines(l1, l2)
            if abs(x[2]) < 1e-12:
                continue
            c = x[:2] / x[2]
            if not (0 <= c[0] < w and 0 <= c[1] < h):
                continue
            axis_angles = [t1 + np.pi / 2, t1 - np.pi / 2, t2 + np.pi / 2, t2 - np.pi / 2]
            # a quarter of the rays first: most crossings of clutter lines stop here
            quick = _ray_support(
                z_rays, c, radii, z_line, axis_angles, 24, ring0_hidden, bundle_step_px
            )
            if quick < 2 or (best is not None and 4 * quick < 0.5 * best[0]):
                continue
            good = _ray_support(
                z_rays,
                c,
                radii,
                z_line,
                axis_angles,
                ring0_hidden=ring0_hidden,
                bundle_step_px=bundle_step_px,
            )
            if best is None or good > best[0]:
                best = (good, c, (l1, l2), axis_angles)
    if best is None or best[0] < 12:
        return None
    return best[1], best[2], best[3]


def _climbed_centre(
    z_rays: NDArray, centre: _Centre, radii: NDArray, step_px: float, ring0_hidden: bool
) -> _Centre:
    """A candidate centre moved to where its rays find the most ring crossings in order.

    A pattern search on the rays' support (:func:`_ray_support`): the eight neighbours
    ``step_px`` away are tried, the best one taken while it beats the centre, the step halved
    when none does,
    while the step is at least 1 px. The lines and the diameters' directions stay the Hough
    lines'. Along a diameter a shift is nearly a projectivity of the radii, so the centre
    lands on the diameter within a ring or so of O (the ring conics' pencil pins O after).
    Among clutter the centre moves too, to wherever lines cross more often in order: what
    refuses such a candidate is the pencil's radius ratios, the fine stage and the marker,
    as in every pass (no false detection on the benchmark's 300 target-free views).

    Parameters
    ----------
    z_rays : ndarray, shape (H, W)
        Darkness over its local threshold, -1 where the print is hidden.
    centre : tuple
        The chosen candidate (:data:`_Centre`).
    radii : ndarray, shape (K,)
        The spec's ring radii, mm.
    step_px : float
        The first step: the coarse stage's closing kernel, the scale it looks at.
    ring0_hidden : bool
        See :func:`~calibration.detection.ray_kernels.label_rays`.
    """
    c, pair, axis_angles = centre
    h, w = z_rays.shape

    def support(p: NDArray) -> int:
        if not (0 <= p[0] < w and 0 <= p[1] < h):
            return -1
        return _ray_support(z_rays, p, radii, Z_LINE, axis_angles, ring0_hidden=ring0_hidden)

    best = support(c)
    moves = [np.array([dx, dy], float) for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy]
    step = float(step_px)
    while step >= 1.0:
        scored = [(support(c + step * m), i) for i, m in enumerate(moves)]
        top, i = max(scored)
        if top > best:
            best, c = top, c + step * moves[i]
        else:
            step /= 2.0
    return c, pair, axis_angles


def _voted_centre(
    z_rays: NDArray, peaks: NDArray, radii: NDArray, ring0_hidden: bool
) -> _Centre | None:
    """The candidate image of O among the peaks ``(M, 2)`` of the edges' votes
    (:func:`~calibration.detection.concentric_votes.voted_centres`) whose rays find the most
    rings in order; None where none has rings around it (a support of at least 12, as
    :func:`_best_centre` asks).

    Its diameters' directions are the darkest lines through it out to the smallest target's
    radius the detector is specified for (7.5 % of the shorter side), its lines the lines
    through it along them.
    """
    h, w = z_rays.shape
    reach = max(8.0, 0.075 * min(h, w))
    best = None
    for c in peaks:
        axis_angles = axes_through(z_rays, c, reach)
        quick = _ray_support(z_rays, c, radii, Z_LINE, axis_angles, 24, ring0_hidden)
        if quick < 2 or (best is not None and 4 * quick < 0.5 * best[0]):
            continue
        good = _ray_support(z_rays, c, radii, Z_LINE, axis_angles, ring0_hidden=ring0_hidden)
        if best is None or good > best[0]:
            best = (good, c, axis_angles)
    if best is None or best[0] < 12:
        return None
    _, c, axis_angles = best
    return c, (line_through(c, axis_angles[0]), line_through(c, axis_angles[2])), axis_angles
