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
        cloud.point[key] = o3d.core.Tensor(np.ascontiguousarray(a.reshape(pts.shape[0], -1)))
    return cloud


def filter_cloud(
    cloud: o3d.t.geometry.PointCloud,
    voxel_mm: float | None = None,
    outlier_neighbors: int = 0,
    outlier_std_ratio: float = 2.0,
    normals_radius_mm: float | None = None,
) -> o3d.t.geometry.PointCloud:
    """Voxel downsampling, statistical outlier removal and normals, each optional, in that order.

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


def refine_sweeps(
    points_base: NDArray,
    sweep_id: NDArray,
    max_distance_mm: float = 2.0,
    voxel_mm: float = 0.5,
    normals_radius_mm: float = 3.0,
    min_fitness: float = 0.3,
    warn_translation_mm: float = 0.2,
    warn_rotation_deg: float = 0.1,
) -> tuple[NDArray, list[SweepCorrection]]:
    """Align each sweep to the union of the sweeps before it with point-to-plane ICP.

    Parameters
    ----------
    points_base : ndarray, shape (N, 3)
        All points, base frame, mm.
    sweep_id : ndarray, shape (N,), int
        Sweep of each point. The lowest id is the reference and never moves.
    max_distance_mm : float
        ICP correspondence distance.
    voxel_mm : float
        Downsampling of the ICP's working copies (the output keeps every point).
    normals_radius_mm : float
        Normal estimation radius of the reference (several profile spacings: a single profile
        is a line and has no normal).
    min_fitness : float
        Fraction of a sweep's points that must find a partner; below it the sweep is left as the
        poses put it (too little overlap to judge) and the correction is reported as not applied.
    warn_translation_mm, warn_rotation_deg : float
        Corrections above either are logged as warnings.

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
    reg = o3d.pipelines.registration
    ref_mask = sid == sweeps[0]
    for s in sweeps[1:]:
        mask = sid == s
        target = _legacy(pts[ref_mask], voxel_mm, normals_radius_mm)
        source = _legacy(pts[mask], voxel_mm, normals_radius_mm)
        if len(target.points) < 10 or len(source.points) < 10:
            corrections.append(
                SweepCorrection(int(s), np.eye(4), 0.0, 0.0, 0.0, 0.0, False, "too few points")
            )
            ref_mask |= mask
            continue
        result = reg.registration_icp(
            source,
            target,
            max_distance_mm,
            np.eye(4),
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=50),
        )
        t = np.asarray(result.transformation)
        trans = float(np.linalg.norm(t[:3, 3]))
        rot = angle_between_rotations_deg(np.eye(3), t[:3, :3])
        applied = result.fitness >= min_fitness
        note = "" if applied else f"overlap too small (fitness {result.fitness:.2f})"
        if applied:
            pts[mask] = pts[mask] @ t[:3, :3].T + t[:3, 3]
            if trans > warn_translation_mm or rot > warn_rotation_deg:
                log.warning(
                    "sweep %d: ICP moved it by %.3f mm and %.3f deg: calibration or robot "
                    "poses are likely off",
                    s,
                    trans,
                    rot,
                )
        corrections.append(
            SweepCorrection(
                int(s),
                t,
                trans,
                rot,
                float(result.fitness),
                float(result.inlier_rmse),
                applied,
                note,
            )
        )
        ref_mask |= mask
    return pts, corrections
