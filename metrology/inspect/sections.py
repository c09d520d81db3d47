"""Section cuts of an inspection: the nominal's profile in a plane and the measured points near it.

A :class:`~metrology.inspect.spec.SectionSpec` names a plane (a point and a normal, nominal
frame). The cut gives, in the plane's own 2-D coordinates ``(u, v)`` (mm, origin at the spec's
point):

- the nominal profile: where the mesh's triangles cross the plane, as 2-D segments, and the
  same segments chained into polylines with their arc length;
- the measured points within ``thickness_mm / 2`` of the plane, with their deviation and their
  position along the profile (arc length of the closest profile point), so a report can plot the
  deviation along the section.

The in-plane axes are chosen so that a drawing reads naturally: ``v`` is the world ``z`` (``y``
for a horizontal cut) projected into the plane, ``u`` completes it, pointing along ``+x`` where
it can (``+y`` otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from metrology.inspect.result import InspectionResult
from metrology.inspect.spec import SectionSpec
from scanner.formats.meshes import TriangleMesh

__all__ = [
    "SectionCut",
    "chain_segments",
    "cut_mesh",
    "cut_section",
    "section_axes",
    "sections_of",
]

#: A measured point's position along the profile is read from the profile resampled this finely
#: (a share of the profile's bounding-box diagonal).
_ARC_STEP_SHARE = 1.0 / 4000.0


@dataclass(frozen=True)
class SectionCut:
    """One section through the nominal and the measured points near it.

    Attributes
    ----------
    spec : SectionSpec
        The plane and slab thickness.
    origin : ndarray, shape (3,)
        The spec's point (nominal frame, mm): ``(u, v) = (0, 0)``.
    normal, u_axis, v_axis : ndarray, shape (3,)
        Unit normal of the plane and the in-plane axes (nominal frame).
    segments_uv : ndarray, shape (S, 2, 2)
        The nominal profile: each segment's two end points in ``(u, v)``, mm.
    polylines_uv : list of ndarray, shape (K_i, 2)
        The segments chained into polylines (a closed loop repeats its first point at its end).
    polylines_arc_mm : list of ndarray, shape (K_i,)
        Arc length of each polyline vertex, continuing from one polyline to the next.
    point_index : ndarray, shape (M,), int64
        Indices of the measured points within half the thickness of the plane.
    points_uv : ndarray, shape (M, 2)
        Their in-plane coordinates, mm.
    offset_mm : ndarray, shape (M,)
        Their signed distance from the plane along ``normal``, mm.
    deviation_mm : ndarray, shape (M,)
        Their signed deviation from the nominal, mm.
    outlier : ndarray, shape (M,), bool
    arc_mm : ndarray, shape (M,)
        Arc length of the closest profile point (NaN when the plane misses the nominal).
    """

    spec: SectionSpec
    origin: NDArray[np.float64]
    normal: NDArray[np.float64]
    u_axis: NDArray[np.float64]
    v_axis: NDArray[np.float64]
    segments_uv: NDArray[np.float64]
    polylines_uv: list[NDArray[np.float64]]
    polylines_arc_mm: list[NDArray[np.float64]]
    point_index: NDArray[np.int64]
    points_uv: NDArray[np.float64]
    offset_mm: NDArray[np.float64]
    deviation_mm: NDArray[np.float64]
    outlier: NDArray[np.bool_]
    arc_mm: NDArray[np.float64]

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def profile_length_mm(self) -> float:
        """Total length of the nominal profile, mm (0 when the plane misses the part)."""
        if self.segments_uv.size == 0:
            return 0.0
        return float(np.linalg.norm(self.segments_uv[:, 1] - self.segments_uv[:, 0], axis=1).sum())

    def axis_label(self, axis: str) -> str:
        """``"u = (+1, +0, +0)"`` style label of the in-plane axis ``"u"`` or ``"v"``."""
        vec = self.u_axis if axis == "u" else self.v_axis
        shown = np.where(np.abs(vec) < 5e-3, 0.0, vec)  # no "-0" components
        return f"{axis} along ({', '.join(f'{c:+.2g}' for c in shown)}), mm"


def section_axes(normal: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """In-plane unit axes ``(u, v)`` of the plane with ``normal`` (shape (3,), any length > 0).

    ``v`` is the world ``z`` projected into the plane (world ``y`` when the plane is nearly
    horizontal); ``u = v x n`` up to sign, pointing along ``+x`` (``+y`` when ``u`` is nearly
    perpendicular to ``x``).
    """
    n = np.asarray(normal, dtype=np.float64)
    length = float(np.linalg.norm(n))
    if n.shape != (3,) or not np.isfinite(length) or length < 1e-12:
        raise ValueError(f"normal: expected a finite non-zero 3-vector, got {normal!r}")
    n = n / length
    up = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    v = up - (up @ n) * n
    v /= np.linalg.norm(v)
    u = np.cross(v, n)
    reference = 0 if abs(u[0]) > 1e-6 else 1
    if u[reference] < 0:
        u = -u
    return u, v


def cut_mesh(mesh: TriangleMesh, point: NDArray, normal: NDArray) -> NDArray[np.float64]:
    """Where the triangles of ``mesh`` cross the plane through ``point`` with ``normal``.

    A vertex counts on the positive side when its signed distance is ``>= 0``, so every crossed
    triangle gives exactly one segment; triangles lying in the plane give none.

    Parameters
    ----------
    mesh : TriangleMesh
    point : ndarray, shape (3,)
        A point of the plane, the mesh's frame, mm.
    normal : ndarray, shape (3,)
        The plane's normal (any length > 0).

    Returns
    -------
    ndarray, shape (S, 2, 3)
        The segments' end points, the mesh's frame, mm.
    """
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    tri = mesh.vertices[mesh.triangles]  # (T, 3, 3)
    d = (tri - np.asarray(point, dtype=np.float64)) @ n  # (T, 3)
    positive = d >= 0
    a, b = np.array([0, 1, 2]), np.array([1, 2, 0])
    crossing = positive[:, a] != positive[:, b]  # (T, 3) edges crossing; 0 or 2 per triangle
    hit = crossing.any(axis=1)
    da, db = d[hit][:, a], d[hit][:, b]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(crossing[hit], da / (da - db), 0.0)
    pa, pb = tri[hit][:, a], tri[hit][:, b]
    points = pa + t[..., None] * (pb - pa)  # (H, 3, 3): one point per edge
    return points[crossing[hit]].reshape(-1, 2, 3)


def chain_segments(
    segments: NDArray, tolerance: float
) -> tuple[list[NDArray[np.float64]], list[NDArray[np.float64]]]:
    """Chain segments that share end points into polylines.

    Parameters
    ----------
    segments : ndarray, shape (S, 2, D)
        End points of the segments (D = 2 or 3).
    tolerance : float
        End points closer than this are the same point.

    Returns
    -------
    polylines : list of ndarray, shape (K_i, D)
        Longest chains first; a closed loop repeats its first point at its end.
    arcs : list of ndarray, shape (K_i,)
        Arc length of every vertex, continuing from one polyline to the next.
    """
    seg = np.asarray(segments, dtype=np.float64)
    if seg.ndim != 3 or seg.shape[1] != 2:
        raise ValueError(f"segments: expected (S, 2, D), got {seg.shape}")
    if len(seg) == 0:
        return [], []
    lengths = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    seg = seg[lengths > tolerance]
    if len(seg) == 0:
        return [], []
    ends = seg.reshape(-1, seg.shape[2])
    # One node per distinct end point (end points within the tolerance grid's cell merge).
    _, first, node = np.unique(
        np.round(ends / tolerance).astype(np.int64), axis=0, return_index=True, return_inverse=True
    )
    node = node.reshape(-1)
    seg_nodes = node.reshape(-1, 2)
    incident: dict[int, list[int]] = {}
    for s, (p, q) in enumerate(seg_nodes):
        incident.setdefault(int(p), []).append(s)
        incident.setdefault(int(q), []).append(s)
    position = ends[first]
    used = np.zeros(len(seg_nodes), bool)
    chains: list[list[int]] = []
    # Start open chains at dead ends first, then whatever loops remain.
    starts = [k for k, segs in incident.items() if len(segs) == 1] + list(incident)
    for start in starts:
        while any(not used[s] for s in incident[start]):
            chain, current = [start], start
            while True:
                nxt = next((s for s in incident[current] if not used[s]), None)
                if nxt is None:
                    break
                used[nxt] = True
                p, q = (int(x) for x in seg_nodes[nxt])
                current = q if p == current else p
                chain.append(current)
            chains.append(chain)
    polylines = [position[c] for c in chains]
    polylines.sort(key=lambda pl: -float(np.linalg.norm(np.diff(pl, axis=0), axis=1).sum()))
    arcs, offset = [], 0.0
    for pl in polylines:
        arc = offset + np.concatenate(
            [[0.0], np.cumsum(np.linalg.norm(np.diff(pl, axis=0), axis=1))]
        )
        arcs.append(arc)
        offset = float(arc[-1])
    return polylines, arcs


def _arc_of(
    points_uv: NDArray, polylines: list[NDArray], arcs: list[NDArray], step: float
) -> NDArray:
    """Arc length of the profile point closest to each of ``points_uv`` (M, 2)."""
    if not polylines or len(points_uv) == 0:
        return np.full(len(points_uv), np.nan)
    samples, sample_arc = [], []
    for pl, arc in zip(polylines, arcs):
        for k in range(len(pl) - 1):
            count = max(1, int(np.ceil((arc[k + 1] - arc[k]) / step)))
            t = np.arange(count) / count
            samples.append(pl[k] + t[:, None] * (pl[k + 1] - pl[k]))
            sample_arc.append(arc[k] + t * (arc[k + 1] - arc[k]))
        samples.append(pl[-1:])
        sample_arc.append(arc[-1:])
    _, nearest = cKDTree(np.concatenate(samples)).query(points_uv)
    return np.concatenate(sample_arc)[nearest]


def cut_section(
    section: SectionSpec,
    nominal: TriangleMesh,
    points_nominal: NDArray,
    deviation_mm: NDArray,
    outlier: NDArray,
) -> SectionCut:
    """The nominal's profile in the section plane and the measured points in its slab.

    Parameters
    ----------
    section : SectionSpec
        The plane (nominal frame) and the slab's thickness.
    nominal : TriangleMesh
        The nominal, its frame, mm.
    points_nominal : ndarray, shape (N, 3)
        Measured points in the nominal frame, mm.
    deviation_mm : ndarray, shape (N,)
        Their signed deviations, mm.
    outlier : ndarray, shape (N,), bool
        Which are outliers.

    Returns
    -------
    SectionCut
        Profile and points in the plane's ``(u, v)`` coordinates; empty arrays when the plane
        misses the part or no point lies in the slab.
    """
    p = np.asarray(points_nominal, dtype=np.float64)
    dev = np.asarray(deviation_mm, dtype=np.float64)
    out = np.asarray(outlier, dtype=bool)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points_nominal: expected (N, 3), got {p.shape}")
    if dev.shape != (len(p),) or out.shape != (len(p),):
        raise ValueError(
            f"deviation_mm, outlier: expected ({len(p)},) each, got {dev.shape} and {out.shape}"
        )
    origin = np.asarray(section.point_mm, dtype=np.float64)
    normal = section.unit_normal()
    u, v = section_axes(normal)
    basis = np.stack([u, v], axis=1)  # (3, 2)
    segments = cut_mesh(nominal, origin, normal)
    segments_uv = (segments - origin) @ basis if len(segments) else np.zeros((0, 2, 2))
    lower, upper = nominal.bounds()
    size = float(np.linalg.norm(upper - lower)) or 1.0
    polylines, arcs = chain_segments(segments_uv, tolerance=1e-6 * size)
    offset = (p - origin) @ normal
    index = np.flatnonzero(np.abs(offset) <= 0.5 * section.thickness_mm)
    points_uv = (p[index] - origin) @ basis
    return SectionCut(
        spec=section,
        origin=origin,
        normal=normal,
        u_axis=u,
        v_axis=v,
        segments_uv=segments_uv,
        polylines_uv=polylines,
        polylines_arc_mm=arcs,
        point_index=index.astype(np.int64),
        points_uv=points_uv,
        offset_mm=offset[index],
        deviation_mm=dev[index],
        outlier=out[index],
        arc_mm=_arc_of(points_uv, polylines, arcs, _ARC_STEP_SHARE * size),
    )


def sections_of(result: InspectionResult) -> list[SectionCut]:
    """Every section of ``result.spec`` cut through the result's nominal and points, in order."""
    return [
        cut_section(s, result.nominal, result.points_nominal, result.deviation_mm, result.outlier)
        for s in result.spec.sections
    ]
