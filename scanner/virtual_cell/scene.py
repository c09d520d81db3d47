"""Scene geometry of the virtual cell: printed targets and analytic surfaces, ray-cast exactly.

Every surface lives in one *world* frame (the robot base for posed frames, the camera for frames
without pose) and answers three questions for a batch of rays or points: where a ray meets it
first (:meth:`Surface.intersect`), its outward normal at a point, and its albedo there (with a
lower bound on the distance to the nearest albedo edge, which drives adaptive supersampling).
:func:`section_points` samples the exact curve where a plane (the laser's) meets a surface.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from scanner.core.targets import (
    ChessboardTarget,
    CircleGridTarget,
    ConcentricCirclesTarget,
    TargetSpec,
)
from scanner.formats.meshes import MeshRaycaster, TriangleMesh

__all__ = [
    "BoxSurface",
    "Cut",
    "CylinderSurface",
    "MeshSurface",
    "PlaneSurface",
    "PrintedTarget",
    "SphereSurface",
    "Surface",
    "first_hits",
    "section_points",
    "segment_blocked",
]

_FAR = 1e6  # "no edge nearby", mm


@dataclass(frozen=True)
class PrintedTarget:
    """The albedo of a printed target card in its own frame (mm, z = 0 on the face).

    Parameters
    ----------
    spec : TargetSpec
        Concentric circles, chessboard or circle grid.
    paper_albedo, ink_albedo : float
    card_margin_mm : float
        White margin around the printed marks; beyond the card is not this surface.
    circle_grid_diameter_ratio : float
        Printed circle diameter of a circle grid as a fraction of its pitch.
    """

    spec: TargetSpec
    paper_albedo: float = 0.85
    ink_albedo: float = 0.05
    card_margin_mm: float = 12.0
    circle_grid_diameter_ratio: float = 0.5

    def card_bounds_mm(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)`` of the white card in the target frame."""
        m = self.card_margin_mm
        s = self.spec
        if isinstance(s, ConcentricCirclesTarget):
            r = s.radius_mm + s.line_width_mm / 2
            mk = s.orientation_marker
            ext = max(r, float(np.hypot(*mk.center_mm)) + mk.diameter_mm / 2)
            return (-ext - m, ext + m, -ext - m, ext + m)
        if isinstance(s, ChessboardTarget):
            cols, rows = s.inner_corners
            q = s.square_mm
            return (-q - m, cols * q + m, -q - m, rows * q + m)
        pts = s.object_points()
        rad = s.pitch_mm * self.circle_grid_diameter_ratio / 2
        return (
            pts[:, 0].min() - rad - m,
            pts[:, 0].max() + rad + m,
            pts[:, 1].min() - rad - m,
            pts[:, 1].max() + rad + m,
        )

    def albedo(self, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
        """Albedo at target points and a lower bound on the distance to the nearest edge, mm.

        Parameters
        ----------
        x, y : ndarray, shape (N,)
            Target-frame coordinates on the card, mm.

        Returns
        -------
        albedo : ndarray, shape (N,)
        edge_mm : ndarray, shape (N,)
        """
        s = self.spec
        if isinstance(s, ConcentricCirclesTarget):
            ink, edge = _concentric_ink(s, x, y)
        elif isinstance(s, ChessboardTarget):
            ink, edge = _chessboard_ink(s, x, y)
        else:
            ink, edge = _circle_grid_ink(s, x, y, self.circle_grid_diameter_ratio)
        x0, x1, y0, y1 = self.card_bounds_mm()
        card_edge = np.minimum(
            np.minimum(np.abs(x - x0), np.abs(x - x1)), np.minimum(np.abs(y - y0), np.abs(y - y1))
        )
        alb = np.where(ink, self.ink_albedo, self.paper_albedo)
        return alb, np.minimum(edge, card_edge)


def _concentric_ink(s: ConcentricCirclesTarget, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
    hw = s.line_width_mm / 2
    radii = s.ring_radii_mm
    r = np.hypot(x, y)
    k = np.clip(np.searchsorted(radii, r), 1, len(radii) - 1)
    dr = np.minimum(np.abs(r - radii[k - 1]), np.abs(r - radii[k]))
    ink = dr <= hw
    edge = np.abs(dr - hw)
    big = s.radius_mm
    for a, b in ((x, y), (y, x)):  # the diameter along x (a = x) and along y
        inside = np.abs(a) <= big
        on_line = inside & (np.abs(b) <= hw)
        ink |= on_line
        e = np.where(np.abs(a) <= big + hw, np.abs(np.abs(b) - hw), _FAR)
        e = np.where(np.abs(b) <= hw, np.minimum(e, np.abs(np.abs(a) - big)), e)
        edge = np.minimum(edge, e)
    mk = s.orientation_marker
    rm = np.hypot(x - mk.center_mm[0], y - mk.center_mm[1])
    ink |= rm <= mk.diameter_mm / 2
    edge = np.minimum(edge, np.abs(rm - mk.diameter_mm / 2))
    return ink, edge


def _chessboard_ink(s: ChessboardTarget, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
    cols, rows = s.inner_corners
    q = s.square_mm
    i = np.floor(x / q)
    j = np.floor(y / q)
    inside = (i >= -1) & (i <= cols - 1) & (j >= -1) & (j <= rows - 1)
    ink = inside & ((i + j) % 2 == 0)
    ex = np.abs(x / q - np.round(x / q)) * q
    ey = np.abs(y / q - np.round(y / q)) * q
    near = (x >= -q - ex) & (x <= cols * q + ex) & (y >= -q - ey) & (y <= rows * q + ey)
    edge = np.where(near, np.minimum(ex, ey), _FAR)
    return ink, edge


def _circle_grid_ink(
    s: CircleGridTarget, x: NDArray, y: NDArray, ratio: float
) -> tuple[NDArray, NDArray]:
    centres = s.object_points()
    rad = s.pitch_mm * ratio / 2
    ink = np.zeros(x.shape, dtype=bool)
    edge = np.full(x.shape, _FAR)
    for cx, cy, _ in centres:
        d = np.hypot(x - cx, y - cy)
        ink |= d <= rad
        edge = np.minimum(edge, np.abs(d - rad))
    return ink, edge


@dataclass(frozen=True)
class Cut:
    """A plane ``normal . p + d = 0`` cutting a surface, and how to sample the cut.

    Parameters
    ----------
    normal : ndarray, shape (3,)
        Unit normal of the plane, world frame.
    d : float
        Offset of the plane, mm.
    step_mm : float
        Spacing of the sampled points along the cut.
    clip_center : ndarray, shape (3,), optional
    clip_radius : float
        Unbounded surfaces are cut only within ``clip_radius`` of ``clip_center``.
    """

    normal: NDArray
    d: float
    step_mm: float
    clip_center: NDArray | None = None
    clip_radius: float = np.inf

    def unclipped(self) -> Cut:
        """The same plane and step without the clip (for bounded parts of a surface)."""
        return replace(self, clip_center=None, clip_radius=np.inf)


class Surface:
    """A surface of the scene in the world frame. Subclasses implement the geometry."""

    id: str = ""
    albedo_value: float = 0.5
    textured = False
    """True when :meth:`albedo` varies over the surface (else ``albedo_value`` everywhere)."""

    def intersect(self, origin: NDArray, dirs: NDArray) -> NDArray:
        """Smallest positive ray parameter ``t`` (``origin + t * dirs``), inf where missed.

        Parameters
        ----------
        origin : ndarray, shape (3,)
        dirs : ndarray, shape (N, 3)
            Ray directions (any length; ``t`` is in units of their length).
        """
        raise NotImplementedError

    def normal(self, points: NDArray) -> NDArray:
        """Unit outward normals ``(N, 3)`` at surface points ``(N, 3)``."""
        raise NotImplementedError

    def albedo(self, points: NDArray) -> tuple[NDArray, NDArray]:
        """Albedo ``(N,)`` and a lower bound on the distance to an albedo edge ``(N,)``, mm."""
        n = len(points)
        return np.full(n, self.albedo_value), np.full(n, _FAR)

    def section(
        self,
        normal: NDArray,
        d: float,
        step_mm: float,
        clip_center: NDArray | None = None,
        clip_radius: float = np.inf,
    ) -> NDArray:
        """Points ``(M, 3)`` sampled every ``step_mm`` on this surface's cut by a plane.

        The plane is ``normal . p + d = 0``; unbounded surfaces are cut only within
        ``clip_radius`` of ``clip_center``.
        """
        cut = Cut(np.asarray(normal, dtype=np.float64), float(d), step_mm, clip_center, clip_radius)
        return self._section(cut)

    def _section(self, cut: Cut) -> NDArray:
        """:meth:`section` for one :class:`Cut`; subclasses implement the geometry."""
        raise NotImplementedError


def _rotate_rows(points: NDArray, rot: NDArray) -> NDArray:
    """``points @ rot.T`` for ``(N, 3)`` points, without a slow BLAS call on a thin matrix."""
    out = np.empty_like(points)
    for k in range(3):
        out[:, k] = points @ rot[k]
    return out


@dataclass
class PlaneSurface(Surface):
    """A plane, optionally a rectangle, optionally printed with a target.

    ``world_from_local`` places the plane: local z is its normal (towards the viewer), local x,y
    span it; the rectangle is ``bounds_mm = (x_min, x_max, y_min, y_max)`` in local coordinates.
    """

    world_from_local: NDArray
    id: str = "plane"
    bounds_mm: tuple[float, float, float, float] | None = None
    albedo_value: float = 0.5
    printed: PrintedTarget | None = None
    two_sided: bool = True

    def __post_init__(self) -> None:
        m = np.asarray(self.world_from_local, dtype=np.float64)
        self._rot = m[:3, :3]
        self._p0 = m[:3, 3]
        self._n = m[:3, 2]
        if self.printed is not None and self.bounds_mm is None:
            self.bounds_mm = self.printed.card_bounds_mm()
        self.textured = self.printed is not None

    def local(self, points: NDArray) -> NDArray:
        return _rotate_rows(points - self._p0, self._rot.T)

    def intersect(self, origin: NDArray, dirs: NDArray) -> NDArray:
        o = np.asarray(origin, dtype=np.float64)
        denom = dirs @ self._n
        num = (self._p0 - o) @ self._n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / denom
        ok = np.isfinite(t) & (t > 1e-9)
        if not self.two_sided:
            ok &= denom < 0
        if self.bounds_mm is not None:
            tt = np.where(ok, t, 0.0)
            x0, x1, y0, y1 = self.bounds_mm
            for k, (low, high) in enumerate(((x0, x1), (y0, y1))):
                axis = self._rot[:, k]
                c = (o - self._p0) @ axis + tt * (dirs @ axis)
                ok &= (c >= low) & (c <= high)
        return np.where(ok, t, np.inf)

    def normal(self, points: NDArray) -> NDArray:
        return np.broadcast_to(self._n, points.shape).copy()

    def albedo(self, points: NDArray) -> tuple[NDArray, NDArray]:
        if self.printed is None:
            return super().albedo(points)
        loc = self.local(points)
        return self.printed.albedo(loc[:, 0], loc[:, 1])

    def _section(self, cut: Cut) -> NDArray:
        # Line of the two planes in local coordinates: points with z = 0 and n_l . p + d_l = 0.
        n_l = self._rot.T @ cut.normal
        d_l = float(cut.normal @ self._p0 + cut.d)
        a, b = n_l[0], n_l[1]
        if np.hypot(a, b) < 1e-9:
            return np.zeros((0, 3))
        g = np.hypot(a, b)
        base = -d_l / g**2 * np.array([a, b])
        direction = np.array([-b, a]) / g
        lo, hi = -1e5, 1e5
        if cut.clip_center is not None and np.isfinite(cut.clip_radius):
            c_l = self.local(np.asarray(cut.clip_center, dtype=np.float64)[None])[0]
            mid = float((c_l[:2] - base) @ direction)
            lo, hi = mid - cut.clip_radius, mid + cut.clip_radius
        if self.bounds_mm is not None:
            x0, x1, y0, y1 = self.bounds_mm
            for k, (low, high) in enumerate(((x0, x1), (y0, y1))):
                if abs(direction[k]) < 1e-12:
                    if not low <= base[k] <= high:
                        return np.zeros((0, 3))
                    continue
                s0, s1 = sorted(((low - base[k]) / direction[k], (high - base[k]) / direction[k]))
                lo, hi = max(lo, s0), min(hi, s1)
            if hi <= lo:
                return np.zeros((0, 3))
        s = np.arange(lo, hi, cut.step_mm)
        loc = np.zeros((len(s), 3))
        loc[:, :2] = base + s[:, None] * direction
        return loc @ self._rot.T + self._p0


def _orthonormal_pair(axis: NDArray) -> tuple[NDArray, NDArray]:
    """Two unit vectors completing ``axis`` (unit) to a right-handed orthonormal frame."""
    e1 = np.cross(axis, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 0.1:
        e1 = np.cross(axis, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


@dataclass
class SphereSurface(Surface):
    """A sphere (world frame), centre and diameter in mm."""

    center: NDArray
    diameter_mm: float
    id: str = "sphere"
    albedo_value: float = 0.7

    def __post_init__(self) -> None:
        self.center = np.asarray(self.center, dtype=np.float64)
        self.radius = self.diameter_mm / 2

    def intersect(self, origin: NDArray, dirs: NDArray) -> NDArray:
        o = np.asarray(origin, dtype=np.float64)
        return _bounded(self.center, self.radius * 1.001, o, dirs, self._exact)

    def _exact(self, origin: NDArray, dirs: NDArray) -> NDArray:
        w = np.asarray(origin, dtype=np.float64) - self.center
        a = np.einsum("ij,ij->i", dirs, dirs)
        b = dirs @ w
        c = w @ w - self.radius**2
        if c > 0:  # origin outside: rays pointing away or passing wide miss
            far = b * b < a * c
            if np.all(far):
                return np.full(len(dirs), np.inf)
        disc = b * b - a * c
        hit = disc >= 0
        sq = np.sqrt(np.where(hit, disc, 0.0))
        t1 = (-b - sq) / a
        t2 = (-b + sq) / a
        t = np.where(t1 > 1e-9, t1, t2)
        return np.where(hit & (t > 1e-9), t, np.inf)

    def normal(self, points: NDArray) -> NDArray:
        v = points - self.center
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def _section(self, cut: Cut) -> NDArray:
        f = float(cut.normal @ self.center + cut.d)
        if abs(f) >= self.radius:
            return np.zeros((0, 3))
        c = self.center - f * cut.normal
        rho = np.sqrt(self.radius**2 - f**2)
        e1, e2 = _orthonormal_pair(cut.normal)
        n = max(int(np.ceil(2 * np.pi * rho / cut.step_mm)), 16)
        th = np.linspace(0, 2 * np.pi, n, endpoint=False)
        return c + rho * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)


def _bounded(
    center: NDArray, radius: float, origin: NDArray, dirs: NDArray, exact: object
) -> NDArray:
    """Run ``exact(origin, dirs_subset)`` only for rays passing within ``radius`` of ``center``."""
    w = center - origin
    a = np.einsum("ij,ij->i", dirs, dirs)
    b = dirs @ w
    ww = float(w @ w)
    near = (ww - b * b / a <= radius**2) & ((b > 0) | (ww <= radius**2))
    out = np.full(len(dirs), np.inf)
    idx = np.flatnonzero(near)
    if len(idx):
        out[idx] = exact(origin, dirs[idx])  # type: ignore[operator]
    return out


@dataclass
class CylinderSurface(Surface):
    """A closed cylinder between axis end points ``p0`` and ``p1`` (world frame), mm."""

    p0: NDArray
    p1: NDArray
    diameter_mm: float
    id: str = "cylinder"
    albedo_value: float = 0.6

    def __post_init__(self) -> None:
        self.p0, self.p1 = (np.asarray(p, dtype=np.float64) for p in (self.p0, self.p1))
        axis = self.p1 - self.p0
        self.length = float(np.linalg.norm(axis))
        self.axis = axis / self.length
        self.radius = self.diameter_mm / 2

    def _side_t(self, o: NDArray, dirs: NDArray) -> NDArray:
        w = o - self.p0
        da = dirs @ self.axis
        dp = dirs - da[:, None] * self.axis
        wp = w - (w @ self.axis) * self.axis
        a = np.einsum("ij,ij->i", dp, dp)
        b = dp @ wp
        c = wp @ wp - self.radius**2
        disc = b * b - a * c
        hit = (disc >= 0) & (a > 1e-18)
        sq = np.sqrt(np.where(hit, disc, 0.0))
        out = np.full(len(dirs), np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            for t in ((-b - sq) / a, (-b + sq) / a):
                s = w @ self.axis + t * da
                ok = hit & (t > 1e-9) & (s >= 0) & (s <= self.length) & (t < out)
                out = np.where(ok, t, out)
        return out

    def _cap_t(self, o: NDArray, dirs: NDArray) -> NDArray:
        out = np.full(len(dirs), np.inf)
        denom = dirs @ self.axis
        with np.errstate(divide="ignore", invalid="ignore"):
            for c in (self.p0, self.p1):
                t = ((c - o) @ self.axis) / denom
                q = o - c + dirs * np.where(np.isfinite(t), t, 0.0)[:, None]
                r2 = np.einsum("ij,ij->i", q, q)
                ok = np.isfinite(t) & (t > 1e-9) & (r2 <= self.radius**2) & (t < out)
                out = np.where(ok, t, out)
        return out

    def intersect(self, origin: NDArray, dirs: NDArray) -> NDArray:
        o = np.asarray(origin, dtype=np.float64)
        centre = (self.p0 + self.p1) / 2
        bound = float(np.hypot(self.length / 2, self.radius)) * 1.001
        return _bounded(
            centre,
            bound,
            o,
            dirs,
            lambda o_, d_: np.minimum(self._side_t(o_, d_), self._cap_t(o_, d_)),
        )

    def normal(self, points: NDArray) -> NDArray:
        s = (points - self.p0) @ self.axis
        radial = points - self.p0 - s[:, None] * self.axis
        rn = np.linalg.norm(radial, axis=1)
        on_side = np.abs(rn - self.radius) < 1e-6 * max(1.0, self.radius)
        out = radial / np.maximum(rn, 1e-12)[:, None]
        cap = np.where(s[:, None] > self.length / 2, self.axis, -self.axis)
        return np.where(on_side[:, None], out, cap)

    def _section(self, cut: Cut) -> NDArray:
        e1, e2 = _orthonormal_pair(self.axis)
        na = float(cut.normal @ self.axis)
        parts = []
        if abs(na) > 1e-9:
            n = max(int(np.ceil(2 * np.pi * self.radius / cut.step_mm * 3)), 32)
            th = np.linspace(0, 2 * np.pi, n, endpoint=False)
            ring = self.radius * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)
            s = -(cut.normal @ self.p0 + cut.d + ring @ cut.normal) / na
            ok = (s >= 0) & (s <= self.length)
            parts.append(self.p0 + ring[ok] + s[ok, None] * self.axis)
        else:  # plane parallel to the axis: two straight lines
            f0 = float(cut.normal @ self.p0 + cut.d)
            nn = np.array([cut.normal @ e1, cut.normal @ e2])
            g = np.linalg.norm(nn)
            if g > 1e-12 and abs(f0) < self.radius * g:
                phi0 = np.arctan2(nn[1], nn[0])
                dphi = np.arccos(-f0 / (self.radius * g))
                s = np.arange(0, self.length, cut.step_mm)
                for phi in (phi0 + dphi, phi0 - dphi):
                    rim = self.radius * (np.cos(phi) * e1 + np.sin(phi) * e2)
                    parts.append(self.p0 + rim + s[:, None] * self.axis)
        for c in (self.p0, self.p1):  # chord of each end cap
            cap = PlaneSurface(
                _frame(c, e1, e2, self.axis), bounds_mm=(-self.radius, self.radius) * 2
            )
            p = cap._section(cut.unclipped())
            if len(p):
                parts.append(p[np.linalg.norm(p - c, axis=1) <= self.radius])
        return np.concatenate(parts) if parts else np.zeros((0, 3))


def _frame(origin: NDArray, ex: NDArray, ey: NDArray, ez: NDArray) -> NDArray:
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = ex, ey, ez, origin
    return m


@dataclass
class BoxSurface(Surface):
    """A box: ``world_from_box`` places its centre and axes; ``size_mm`` its full extents."""

    world_from_box: NDArray
    size_mm: tuple[float, float, float]
    id: str = "box"
    albedo_value: float = 0.6
    _faces: list[PlaneSurface] = field(default_factory=list, init=False, repr=False)

    def __post_init__(self) -> None:
        m = np.asarray(self.world_from_box, dtype=np.float64)
        half = np.asarray(self.size_mm, dtype=np.float64) / 2
        self._faces = []
        for k in range(3):
            i, j = (k + 1) % 3, (k + 2) % 3
            for sign in (1.0, -1.0):
                ez = sign * m[:3, k]
                ex = m[:3, i]
                ey = np.cross(ez, ex)
                c = m[:3, 3] + sign * half[k] * m[:3, k]
                # ey is +-m[:, j]; bounds are symmetric so the sign does not matter.
                self._faces.append(
                    PlaneSurface(
                        _frame(c, ex, ey, ez),
                        bounds_mm=(-half[i], half[i], -half[j], half[j]),
                        two_sided=False,
                    )
                )

    def intersect(self, origin: NDArray, dirs: NDArray) -> NDArray:
        o = np.asarray(origin, dtype=np.float64)
        bound = float(np.linalg.norm(self.size_mm)) / 2 * 1.001
        centre = np.asarray(self.world_from_box, dtype=np.float64)[:3, 3]

        def exact(o_: NDArray, d_: NDArray) -> NDArray:
            return np.min(np.stack([f.intersect(o_, d_) for f in self._faces]), axis=0)

        return _bounded(centre, bound, o, dirs, exact)

    def normal(self, points: NDArray) -> NDArray:
        dist = np.stack([np.abs(f.local(points)[:, 2]) for f in self._faces])
        k = np.argmin(dist, axis=0)
        normals = np.stack([f._n for f in self._faces])
        return normals[k]

    def _section(self, cut: Cut) -> NDArray:
        parts = [f._section(cut.unclipped()) for f in self._faces]
        parts = [p for p in parts if len(p)]
        return np.concatenate(parts) if parts else np.zeros((0, 3))


@dataclass
class MeshSurface(Surface):
    """Any triangle mesh (a CAD part): ``world_from_mesh`` places it; flat-shaded triangles.

    The truth of a part scanned in the virtual cell is the mesh itself, so its facets are
    the surface (no smoothing of normals between triangles).
    """

    mesh: TriangleMesh
    world_from_mesh: NDArray
    id: str = "part"
    albedo_value: float = 0.6
    _caster: MeshRaycaster = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.world_mesh = self.mesh.transformed(self.world_from_mesh)
        self._caster = MeshRaycaster(self.world_mesh)

    def intersect(self, origin: NDArray, dirs: NDArray) -> NDArray:
        return self._caster.cast(origin, dirs)[0]

    def normal(self, points: NDArray) -> NDArray:
        return self._caster.normals_at(points)

    def _section(self, cut: Cut) -> NDArray:
        return self.world_mesh.section(cut.normal, cut.d, cut.step_mm)


def object_from_euler(center: NDArray, euler_xyz_deg: NDArray) -> NDArray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("xyz", euler_xyz_deg, degrees=True).as_matrix()
    m[:3, 3] = center
    return m


def first_hits(surfaces: list[Surface], origin: NDArray, dirs: NDArray) -> tuple[NDArray, NDArray]:
    """Nearest hit of each ray: ``(t (N,), surface index (N,), -1 where nothing is hit)``."""
    n = len(dirs)
    t_best = np.full(n, np.inf)
    idx = np.full(n, -1, dtype=np.int32)
    for k, s in enumerate(surfaces):
        t = s.intersect(origin, dirs)
        closer = t < t_best
        t_best = np.where(closer, t, t_best)
        idx[closer] = k
    return t_best, idx


def segment_blocked(
    surfaces: list[Surface], start: NDArray, ends: NDArray, rel_eps: float = 1e-7
) -> NDArray:
    """True where the open segment from ``start`` (3,) to each of ``ends`` (N, 3) hits a surface."""
    dirs = ends - start
    blocked = np.zeros(len(ends), dtype=bool)
    for s in surfaces:
        t = s.intersect(start, dirs)
        blocked |= t < 1.0 - rel_eps
    return blocked


def section_points(
    surfaces: list[Surface],
    normal: NDArray,
    d: float,
    step_mm: float,
    clip_center: NDArray | None = None,
    clip_radius: float = np.inf,
) -> tuple[NDArray, NDArray]:
    """Exact cut of every surface by the plane ``normal . p + d = 0`` (world frame).

    Returns
    -------
    points : ndarray, shape (M, 3)
    surface_index : ndarray, shape (M,)
    """
    pts, ids = [], []
    for k, s in enumerate(surfaces):
        p = s.section(normal, d, step_mm, clip_center, clip_radius)
        if len(p):
            pts.append(p)
            ids.append(np.full(len(p), k, dtype=np.int32))
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int32)
    return np.concatenate(pts), np.concatenate(ids)
