"""Per-frame points to one cloud: Open3D tensor cloud, filters, and ICP between sweeps.

Sweeps are stitched by their robot poses (the triangulation already put every point in the
base frame). :func:`refine_sweeps` optionally corrects residual offsets between overlapping
sweeps with point-to-plane ICP and reports each correction: a large one means the calibration
or the robot poses are off, which ICP would otherwise hide.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from scanner.core.conventions import angle_between_rotations_deg

__all__ = [
    "SweepCorrection",
    "build_cloud",
    "filter_cloud",
    "incidence_cosines",
    "refine_sweeps",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SweepCorrection:
    """The rigid correction ICP applied to one sweep (``base_from_base_corrected``)."""

    sweep: int
    transform: NDArray
    translation_mm: float
    rotation_deg: float
    fitness: float
    rmse_mm: float
    applied: bool
    note: str = ""


def build_cloud(
    points_base: NDArray, attributes: Mapping[str, NDArray] | None = None
) -> o3d.t.geometry.PointCloud:
    """A tensor cloud from ``(N, 3)`` base-frame points (mm) and per-point attributes.

    Attributes are stored as ``(N, 1)`` tensors of their dtype (``(N, k)`` kept as is).
    """
    pts = np.ascontiguousarray(points_base, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points_base: expected shape (N, 3), got {pts.shape}")
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(pts))
    for key, arr in (attributes or {}).items():
        a = np.asarray(arr)
        if a.shape[0] != pts.shape[0]:
            raise ValueError(f"{key}: expected {pts.shape[0]} values, got {a.shape[0]}")
        if a.dtype == np.int64:
            a = a.astype(np.int32)
        columns = int(np.prod(a.shape[1:])) if a.ndim > 1 else 1  # (N, 1), also for N = 0
        cloud.point[key] = o3d.core.Tensor(np.ascontiguousarray(a.reshape(pts.shape[0], columns)))
    return cloud


def filter_cloud(
    cloud: o3d.t.geometry.PointCloud,
    voxel_mm: float | None = None,
    outlier_neighbors: int = 0,
    outlier_std_ratio: float = 2.0,
    normals_radius_mm: float | None = None,
    isolated_radius_mm: float | None = None,
    isolated_min_neighbors: int = 3,
) -> o3d.t.geometry.PointCloud:
    """Voxel downsampling, statistical outlier removal, removal of isolated points (fewer than
    ``isolated_min_neighbors`` others within ``isolated_radius_mm``) and normals, each
    optional, in that order.

    Downsampling averages the attributes of each voxel (integer ids included, so ids of merged
    points are only indicative).
    """
    out = cloud
    if voxel_mm is not None and voxel_mm > 0:
        n0 = len(out.point.positions)
        out = out.voxel_down_sample(float(voxel_mm))
        log.info("voxel %.3f mm: %d -> %d points", voxel_mm, n0, len(out.point.positions))
    if outlier_neighbors > 0 and len(out.point.positions) > outlier_neighbors:
        n0 = len(out.point.positions)
        out, _ = out.remove_statistical_outliers(int(outlier_neighbors), float(outlier_std_ratio))
        log.info("outliers: %d -> %d points", n0, len(out.point.positions))
    if isolated_radius_mm is not None and isolated_radius_mm > 0 and len(out.point.positions):
        n0 = len(out.point.positions)
        out, _ = out.remove_radius_outliers(int(isolated_min_neighbors), float(isolated_radius_mm))
        log.info("isolated points: %d -> %d points", n0, len(out.point.positions))
    if normals_radius_mm is not None and normals_radius_mm > 0 and len(out.point.positions) >= 3:
        out.estimate_normals(max_nn=30, radius=float(normals_radius_mm))
    return out


def incidence_cosines(
    points_base: NDArray,
    frame_index: NDArray,
    base_from_cam: NDArray,
    laser_origin_cam: NDArray | None = None,
    normals_radius_mm: float = 1.5,
) -> tuple[NDArray, NDArray]:
    """Cosines of the viewing and illumination angles of each point's surface.

    The surface normal comes from the cloud itself (principal axes of the neighbours within
    ``normals_radius_mm``: several profile spacings, since one profile alone is a line); the
    viewing direction from the frame's camera centre, the illumination direction from the laser's
    emitter. Near 0 means grazing: there the stripe is wide, dim and skewed across its width,
    and its centre is biased (on a sphere, points near the silhouette or the terminator bias
    the fitted radius).

    Parameters
    ----------
    points_base : ndarray, shape (N, 3)
        Base frame, mm.
    frame_index : ndarray, shape (N,), int
        Index of each point's frame into ``base_from_cam``.
    base_from_cam : ndarray, shape (F, 4, 4)
        Camera pose of each frame.
    laser_origin_cam : ndarray, shape (3,), optional
        Where the laser fan is emitted, camera frame, mm (from the sensor's drawing; an angle
        limit needs it to a few mm only). ``None``: the laser cosines are NaN.
    normals_radius_mm : float

    Returns
    -------
    cos_view, cos_laser : ndarray, shape (N,)
        In [0, 1]; NaN where a point has too few neighbours for a normal.
    """
    pts = np.ascontiguousarray(points_base, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points_base: expected shape (N, 3), got {pts.shape}")
    idx = np.asarray(frame_index, dtype=np.int64)
    if idx.shape != (len(pts),):
        raise ValueError(f"frame_index: expected shape ({len(pts)},), got {idx.shape}")
    poses = np.asarray(base_from_cam, dtype=np.float64).reshape(-1, 4, 4)
    if normals_radius_mm <= 0:
        raise ValueError(f"normals_radius_mm: expected > 0, got {normals_radius_mm}")
    nan = np.full(len(pts), np.nan)
    if len(pts) < 3:
        return nan, nan.copy()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normals_radius_mm, max_nn=30))
    normals = np.asarray(pc.normals)
    # Open3D leaves a default normal where a point has fewer than three neighbours.
    counts = cKDTree(pts).query_ball_point(pts, normals_radius_mm, return_length=True)
    few = np.asarray(counts) < 3

    def cosines(origins: NDArray) -> NDArray:
        to_origin = origins - pts
        to_origin /= np.linalg.norm(to_origin, axis=1, keepdims=True)
        c = np.abs(np.einsum("ij,ij->i", normals, to_origin))
        c[few] = np.nan
        return c

    cos_view = cosines(poses[idx, :3, 3])
    if laser_origin_cam is None:
        return cos_view, nan
    o = np.asarray(laser_origin_cam, dtype=np.float64).reshape(3)
    laser_base = np.einsum("kij,j->ki", poses[:, :3, :3], o) + poses[:, :3, 3]
    return cos_view, cosines(laser_base[idx])


def _legacy(points: NDArray, voxel_mm: float, normals_radius_mm: float) -> o3d.geometry.PointCloud:
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if voxel_mm > 0:
        pc = pc.voxel_down_sample(voxel_mm)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normals_radius_mm, max_nn=30))
    return pc


def _overlap(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    tree: cKDTree,
    reach_mm: float,
) -> NDArray[np.int64]:
    """Indices of source points on surface the target also measured: a target point within
    ``reach_mm`` with a normal within 20 deg (not an edge, a wall or the other side).
    ``tree`` indexes the target's points."""
    src = np.asarray(source.points)
    dist, idx = tree.query(src, distance_upper_bound=reach_mm)
    near = np.isfinite(dist)
    cos = np.zeros(len(src))
    cos[near] = np.abs(
        np.einsum(
            "ij,ij->i", np.asarray(source.normals)[near], np.asarray(target.normals)[idx[near]]
        )
    )
    return np.flatnonzero(near & (cos > np.cos(np.radians(20.0))))


def _pinned_icp(
    source: NDArray,
    target: NDArray,
    target_normals: NDArray,
    tree: cKDTree,
    reach_mm: float,
    min_conditioning: float,
    iterations: int = 30,
) -> tuple[NDArray, float, int]:
    """Robust point-to-plane ICP that moves a cloud only along the directions its overlap pins.

    Gauss-Newton on the point-to-plane residuals, Tukey-weighted (scale from the median
    residual), solved in the eigenbasis of the normal matrix (rotations scaled by the points'
    spread): directions weaker than ``min_conditioning`` times the strongest (a plane slides
    along itself, a cylinder turns about its axis) are left as the poses put them instead of
    being filled with noise - the degeneracy-aware update of Zhang, Kaess and Singh (ICRA
    2016). ``scipy.optimize.least_squares`` cannot leave an unobservable direction alone,
    hence the explicit iteration.

    ``tree`` indexes ``target``. Returns ``(source_corrected_from_source (4, 4), inlier rmse,
    directions pinned)``.
    """
    transform = np.eye(4)
    pinned = 0
    rmse = 0.0
    for _ in range(iterations):
        moved = source @ transform[:3, :3].T + transform[:3, 3]
        dist, idx = tree.query(moved, distance_upper_bound=reach_mm)
        ok = np.isfinite(dist)
        if ok.sum() < 10:
            break
        p, q, n = moved[ok], target[idx[ok]], target_normals[idx[ok]]
        r = np.einsum("ij,ij->i", p - q, n)
        scale = max(1.4826 * float(np.median(np.abs(r))), 1e-6)
        u = r / (4.685 * scale)
        w = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)
        rmse = float(np.sqrt(np.sum(w * r * r) / max(np.sum(w), 1e-12)))
        centre = np.average(p, axis=0, weights=w) if w.sum() > 0 else p.mean(axis=0)
        arm = p - centre
        spread = float(np.sqrt(np.average(np.sum(arm**2, axis=1), weights=w))) or 1.0
        jac = np.hstack([np.cross(arm, n) / spread, n])
        normal_matrix = jac.T @ (jac * w[:, None])
        gradient = jac.T @ (w * r)
        eig, vec = np.linalg.eigh(normal_matrix)
        keep = eig > min_conditioning * eig[-1]
        pinned = int(keep.sum())
        step = -vec[:, keep] @ ((vec[:, keep].T @ gradient) / eig[keep])
        delta = np.eye(4)
        delta[:3, :3] = Rotation.from_rotvec(step[:3] / spread).as_matrix()
        delta[:3, 3] = centre + step[3:] - delta[:3, :3] @ centre
        transform = delta @ transform
        if np.linalg.norm(step[3:]) < 1e-7 and np.linalg.norm(step[:3]) < 1e-7:
            break
    return transform, rmse, pinned


def refine_sweeps(
    points_base: NDArray,
    sweep_id: NDArray,
    max_distance_mm: float = 1.0,
    voxel_mm: float = 0.5,
    normals_radius_mm: float = 3.0,
    min_fitness: float = 0.3,
    warn_translation_mm: float = 0.2,
    warn_rotation_deg: float = 0.1,
    min_conditioning: float = 0.01,
) -> tuple[NDArray, list[SweepCorrection]]:
    """Align each sweep to the union of the sweeps before it with robust point-to-plane ICP.

    Only the overlap takes part: source points with a reference point within
    ``max_distance_mm`` whose normals agree within 20 deg (so a wall one sweep sees and
    the other does not cannot pull it). The fit (:func:`_pinned_icp`) moves a sweep only
    along the directions the overlap pins (``min_conditioning``): a sweep overlapping the
    others on one plane is corrected across that plane, not slid along it. The correction is
    about the sweep's own centroid: ``translation_mm`` is how far it moved the sweep's points
    there. It is not applied when too little of the sweep overlaps (``min_fitness``).

    Parameters
    ----------
    points_base : ndarray, shape (N, 3)
        All points, base frame, mm.
    sweep_id : ndarray, shape (N,), int
        Sweep of each point. The lowest id is the reference and never moves.
    max_distance_mm : float
        Largest offset between sweeps looked for (robot and calibration errors).
    voxel_mm : float
        Downsampling of the ICP's working copies (the output keeps every point).
    normals_radius_mm : float
        Normal estimation radius (several profile spacings: a single profile is a line and has
        no normal).
    min_fitness : float
        Fraction of a sweep's points that must overlap the reference.
    warn_translation_mm, warn_rotation_deg : float
        Corrections above either are logged as warnings.
    min_conditioning : float
        Smallest accepted ratio of the weakest to the strongest direction of the fit.

    Returns
    -------
    points : ndarray, shape (N, 3)
        Corrected points (a new array).
    corrections : list of SweepCorrection
        One per non-reference sweep.
    """
    pts = np.array(points_base, dtype=np.float64)
    sid = np.asarray(sweep_id)
    if sid.shape != (pts.shape[0],):
        raise ValueError(f"sweep_id: expected shape ({pts.shape[0]},), got {sid.shape}")
    sweeps = np.unique(sid)
    corrections: list[SweepCorrection] = []
    if sweeps.size < 2:
        return pts, corrections
    ref_mask = sid == sweeps[0]
    for s in sweeps[1:]:
        mask = sid == s
        centre = pts[mask].mean(axis=0) if mask.any() else np.zeros(3)
        target = _legacy(pts[ref_mask] - centre, voxel_mm, normals_radius_mm)
        source = _legacy(pts[mask] - centre, voxel_mm, normals_radius_mm)
        if len(target.points) < 10 or len(source.points) < 10:
            corrections.append(
                SweepCorrection(int(s), np.eye(4), 0.0, 0.0, 0.0, 0.0, False, "too few points")
            )
            ref_mask |= mask
            continue
        tree = cKDTree(np.asarray(target.points))
        shared = _overlap(source, target, tree, max_distance_mm)
        fitness = len(shared) / len(source.points)
        note = ""
        t = np.eye(4)
        rmse = 0.0
        if fitness < min_fitness:
            note = f"overlap too small (fitness {fitness:.2f})"
        else:
            t, rmse, pinned = _pinned_icp(
                np.asarray(source.points)[shared],
                np.asarray(target.points),
                np.asarray(target.normals),
                tree,
                max_distance_mm,
                min_conditioning,
            )
            if pinned == 0:
                note = "the overlap pins no direction"
            elif pinned < 6:
                log.info("sweep %d: the overlap pins %d of 6 directions", s, pinned)
        trans = float(np.linalg.norm(t[:3, 3]))
        rot = angle_between_rotations_deg(np.eye(3), t[:3, :3])
        applied = not note
        if applied:
            pts[mask] = (pts[mask] - centre) @ t[:3, :3].T + t[:3, 3] + centre
            if trans > warn_translation_mm or rot > warn_rotation_deg:
                log.warning(
                    "sweep %d: ICP moved it by %.3f mm and %.3f deg: calibration or robot "
                    "poses are likely off",
                    s,
                    trans,
                    rot,
                )
        about_base = np.eye(4)
        about_base[:3, :3] = t[:3, :3]
        about_base[:3, 3] = t[:3, 3] + centre - t[:3, :3] @ centre
        corrections.append(
            SweepCorrection(int(s), about_base, trans, rot, fitness, rmse, applied, note)
        )
        ref_mask |= mask
    return pts, corrections
