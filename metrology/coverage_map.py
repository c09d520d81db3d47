"""The coverage map: which parts of a part's surface a scan plan (or a scan) measures.

Surface samples are drawn from the report's named views (:data:`metrology.inspect.viewer.VIEWS`)
with the same shading: measured in the colour of the sweep that measures them first, visible
from above but not measured in red, not visible from above (underside, deep bores) in light
grey. Nearer samples are drawn over farther ones.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from metrology.inspect.viewer import VIEWS, project, rasterise, shade
from scanner.formats.meshes import TriangleMesh

__all__ = ["write_coverage_map"]

_UNSEEN = (220, 30, 30)
_HIDDEN = (205, 205, 205)
_DISPLAY_POINTS = 300_000
_VIEW_PX = (520, 420)


def _sweep_colours(count: int) -> NDArray[np.uint8]:
    """Distinct colours for the sweeps, red left out (it marks what stays unseen)."""
    cmap = matplotlib.colormaps["tab10"]
    hues = [k for k in range(10) if k != 3]
    return (np.array([cmap(hues[k % 9])[:3] for k in range(max(count, 1))]) * 255).astype(np.uint8)


def write_coverage_map(
    path: Path,
    mesh: TriangleMesh,
    points: NDArray[np.float64],
    visible: NDArray[np.bool_],
    measured_by: NDArray[np.int64],
    title: str,
    views: tuple[str, ...] = ("iso", "rear iso", "top"),
) -> Path:
    """Write the map as a PNG.

    Parameters
    ----------
    path : Path
    mesh : TriangleMesh
        The part, in the frame of ``points`` (z up).
    points : ndarray, shape (M, 3)
        Surface samples the coverage was counted on.
    visible : ndarray, shape (M,), bool
        Visible from above the table.
    measured_by : ndarray, shape (M,), int
        Index of the sweep measuring each sample, -1 for none.
    title : str
    views : tuple of str
        Names in :data:`VIEWS`.

    The surface is drawn densely (each drawn point takes the state of its nearest sample)
    and z-buffered, so that nothing behind the surface shows through.
    """
    colours = np.empty((len(points), 3), dtype=np.uint8)
    colours[:] = _HIDDEN
    colours[visible & (measured_by < 0)] = _UNSEEN
    sweeps = int(measured_by.max()) + 1 if len(measured_by) else 0
    palette = _sweep_colours(sweeps)
    done = measured_by >= 0
    colours[done] = palette[measured_by[done]]
    rng = np.random.default_rng(0)
    shown, normals = mesh.sample_surface(_DISPLAY_POINTS, rng)
    _, nearest = cKDTree(points).query(shown)
    shown_colours = colours[nearest]
    fig = Figure(figsize=(5.2 * len(views), 5.2), dpi=110)
    axes = fig.subplots(1, len(views), squeeze=False)[0]
    for ax, name in zip(axes, views):
        yaw, pitch = VIEWS[name]
        view = project(shown, yaw, pitch)
        lo, hi = view.min(axis=0), view.max(axis=0)
        pad = 0.03 * float(max(hi[0] - lo[0], hi[1] - lo[1], 1e-6))
        box = (lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad)
        image, extent = rasterise(view, shade(shown_colours, normals, yaw, pitch), box, _VIEW_PX)
        ax.imshow(image, extent=extent, interpolation="nearest")
        ax.set_title(name)
        ax.set_axis_off()
    entries = [(palette[k], f"sweep {k + 1}") for k in range(sweeps)]
    entries += [(_UNSEEN, "visible, not measured"), (_HIDDEN, "not visible from above")]
    handles = [
        Line2D([], [], ls="", marker="s", markersize=9, color=np.asarray(c) / 255.0, label=text)
        for c, text in entries
    ]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 7), frameon=False)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.08, 1, 0.95))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
