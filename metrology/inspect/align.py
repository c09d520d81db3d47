"""Aligning a scanned cloud to its nominal mesh: a global search, a robust best-fit, RPS.

The cloud may hold only the sides a sensor saw, noise, stray points and real form deviations;
none of them may pull the pose. The search:

1. **Global**: FPFH features of a voxel-thinned cloud matched to those of points sampled on the
   nominal, RANSAC on the matches (Open3D), a few seeds: candidate poses.
2. **Symmetric alternatives**: each candidate also turned a half and a quarter turn about the
   nominal's principal axes: a near-symmetric part's wrong pose is compared, not missed.
3. **Coarse best-fit** of each candidate (iteratively re-weighted point-to-plane ICP against the
   mesh itself, Tukey weights), scored by the truncated mean squared distance; the best wins,
   and a distinct runner-up that scores nearly as well marks the pose ambiguous.
4. **Fine best-fit** of the winner by :func:`scipy.optimize.least_squares` on the true
   point-to-surface distance (closest points re-found at each evaluation, Cauchy loss), whose
   Jacobian gives the pose's covariance.

``rps_align`` aligns on three datum planes instead (3-2-1): primary, secondary, tertiary.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from metrology.inspect.result import AlignmentResult
from metrology.inspect.surface import NominalSurface

__all__ = [
    "AlignOptions",
    "apply",
    "best_fit",
    "coarse_fit",
    "global_candidates",
    "pose_distance_mm",
    "rps_frame",
    "symmetric_alternatives",
]

_REG = o3d.pipelines.registration


@dataclass(frozen=True)
class AlignOptions:
    """Settings of the search (sizes relative to the nominal's bounding-box diagonal)."""

    voxel_fraction: float = 0.02
    """Voxel of the global search, as a share of the diagonal."""
    ransac_runs: int = 3
    ransac_iterations: int = 60_000
    coarse_points: int = 6_000
    fine_points: int = 60_000
    ambiguity_ratio: float = 1.5
    """A distinct pose scoring within this factor of the best marks the alignment ambiguous."""
    seed: int = 0


def _to_pcd(points: NDArray, normals: NDArray | None = None) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    return pcd


def _fpfh(pcd: o3d.geometry.PointCloud, voxel: float) -> o3d.pipelines.registration.Feature:
    return _REG.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100)
    )


def apply(transform: NDArray, points: NDArray) -> NDArray:
    """``transform`` (4, 4) applied to ``points`` (N, 3)."""
    return points @ transform[:3, :3].T + transform[:3, 3]


def pose_distance_mm(a: NDArray, b: NDArray, corners: NDArray) -> float:
    """Largest distance between the cloud-to-nominal poses ``a`` and ``b`` at the nominal's
    extremities ``corners`` (8, 3): how far apart the two poses put the part."""
    # Map the corners back to the cloud with one pose and forward with the other.
    back = apply(np.linalg.inv(a), corners)
    return float(np.max(np.linalg.norm(apply(b, back) - corners, axis=1)))


def global_candidates(
    points_cloud: NDArray, surface: NominalSurface, options: AlignOptions
) -> list[NDArray]:
    """Candidate ``nominal_from_cloud`` poses (4, 4) from FPFH + RANSAC, without a guess."""
    rng = np.random.default_rng(options.seed)
    voxel = options.voxel_fraction * surface.diagonal_mm
    cloud = _to_pcd(points_cloud).voxel_down_sample(voxel)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * voxel, max_nn=30))
    # A scan sees a part from outside: normals turned away from the cloud's centre.
    centre = np.asarray(cloud.points).mean(axis=0)
    normals = np.asarray(cloud.normals)
    outward = np.einsum("ij,ij->i", np.asarray(cloud.points) - centre, normals) >= 0
    cloud.normals = o3d.utility.Vector3dVector(np.where(outward[:, None], normals, -normals))
    area = float(surface.mesh.face_areas().sum())
    sampled, sampled_normals = surface.sample(max(2_000, int(4.0 * area / voxel**2)), rng)
    nominal = _to_pcd(sampled, sampled_normals).voxel_down_sample(voxel)
    cloud_f, nominal_f = _fpfh(cloud, voxel), _fpfh(nominal, voxel)
    poses = []
    for run in range(options.ransac_runs):
        o3d.utility.random.seed(int(options.seed * 1000 + run))
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            found = _ransac(cloud, nominal, cloud_f, nominal_f, voxel, run % 2 == 0, options)
        if found.fitness > 0:
            poses.append(np.asarray(found.transformation, dtype=np.float64))
    return poses


def _ransac(
    cloud: o3d.geometry.PointCloud,
    nominal: o3d.geometry.PointCloud,
    cloud_f: o3d.pipelines.registration.Feature,
    nominal_f: o3d.pipelines.registration.Feature,
    voxel: float,
    mutual: bool,
    options: AlignOptions,
) -> o3d.pipelines.registration.RegistrationResult:
    return _REG.registration_ransac_based_on_feature_matching(
        cloud,
        nominal,
        cloud_f,
        nominal_f,
        mutual_filter=mutual,
        max_correspondence_distance=1.5 * voxel,
        estimation_method=_REG.TransformationEstimationPointToPoint(False),
        ransac_n=3,
        checkers=[
            _REG.CorrespondenceCheckerBasedOnEdgeLength(0.9),
            _REG.CorrespondenceCheckerBasedOnDistance(1.5 * voxel),
        ],
        criteria=_REG.RANSACConvergenceCriteria(options.ransac_iterations, 0.9999),
    )


def symmetric_alternatives(pose: NDArray, surface: NominalSurface) -> list[NDArray]:
    """``pose`` turned a half turn about each principal axis of the nominal and a quarter turn
    both ways about each, through its centre: where a near-symmetric part's wrong poses lie."""
    points, _ = surface.sample(20_000, np.random.default_rng(0))
    centre = points.mean(axis=0)
    _, _, axes = np.linalg.svd(points - centre, full_matrices=False)
    out = []
    for axis in axes:
        for angle in (np.pi, np.pi / 2, -np.pi / 2):
            turn = np.eye(4)
            turn[:3, :3] = Rotation.from_rotvec(angle * axis).as_matrix()
            turn[:3, 3] = centre - turn[:3, :3] @ centre
            out.append(turn @ pose)
    return out


def _tukey_weights(r: NDArray, scale: float) -> NDArray:
    u = r / (4.685 * scale)
    return np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)


def _robust_scale(r: NDArray, floor: float) -> float:
    return max(1.4826 * float(np.median(np.abs(r))), floor)


def _small_motion(x: NDArray, centre: NDArray) -> NDArray:
    """The pose of parameters ``x`` = (rotation vector about ``centre``, translation)."""
    step = np.eye(4)
    step[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
    step[:3, 3] = centre - step[:3, :3] @ centre + x[3:]
    return step


def _jacobian(points: NDArray, normals: NDArray, centre: NDArray) -> NDArray:
    """d(signed distance)/d(rotation vector, translation) at zero motion, ``(N, 6)``."""
    return np.hstack([np.cross(points - centre, normals), normals])


def coarse_fit(
    points_cloud: NDArray,
    surface: NominalSurface,
    pose: NDArray,
    *,
    iterations: int = 30,
    floor_mm: float = 1e-3,
) -> tuple[NDArray, float]:
    """Iteratively re-weighted point-to-plane ICP from ``pose``; the pose and its score.

    The score is the mean of squared distances truncated at 3 % of the diagonal (and at 6x
    the robust scale): lower is better, comparable between candidates on the same points.
    """
    scale = 0.05 * surface.diagonal_mm
    for _ in range(iterations):
        moved = apply(pose, points_cloud)
        near = surface.closest(moved)
        r = near.signed_mm
        scale = min(scale, _robust_scale(r, floor_mm) * 2.0) if _ else _robust_scale(r, floor_mm)
        w = _tukey_weights(r, scale)
        if np.count_nonzero(w) < 12:
            break
        centre = moved.mean(axis=0)
        j = _jacobian(moved, near.normals, centre)
        a = (j * w[:, None]).T @ j + 1e-9 * np.eye(6)
        x = np.linalg.solve(a, -(j * w[:, None]).T @ r)
        pose = _small_motion(x, centre) @ pose
        if np.linalg.norm(x[:3]) * surface.diagonal_mm + np.linalg.norm(x[3:]) < 1e-4:
            break
    r = surface.closest(apply(pose, points_cloud)).signed_mm
    cut = 0.03 * surface.diagonal_mm
    return pose, float(np.mean(np.minimum(r * r, cut * cut)))


def best_fit(
    points_cloud: NDArray,
    surface: NominalSurface,
    options: AlignOptions,
    *,
    select: Callable[[NDArray, NDArray], NDArray] | None = None,
    initial: list[NDArray] | None = None,
) -> AlignmentResult:
    """The pose that best fits the cloud to the nominal, found without a guess.

    Parameters
    ----------
    points_cloud : ndarray, shape (N, 3)
    surface : NominalSurface
    options : AlignOptions
    select : callable, optional
        ``select(points_nominal, face_normals) -> mask (N,)``: fit only these points (a local
        best-fit of one region), re-selected as the pose changes.
    initial : list of ndarray (4, 4), optional
        Candidate poses to start from instead of the global search.

    Returns
    -------
    AlignmentResult
        Falsy when no candidate converged or the pose stays ambiguous (``warnings`` say why).
    """
    rng = np.random.default_rng(options.seed)
    count = len(points_cloud)
    coarse = points_cloud[rng.choice(count, min(count, options.coarse_points), replace=False)]
    seeds = initial if initial is not None else global_candidates(points_cloud, surface, options)
    if not seeds:
        return _failed(surface, "the global search found no candidate pose")
    corners = surface.corners()
    distinct_mm = max(0.02 * surface.diagonal_mm, 0.5)

    def refine_all(starts: list[NDArray]) -> list[tuple[NDArray, float]]:
        return [coarse_fit(coarse, surface, s) for s in starts]

    fitted = refine_all(seeds)
    best_pose = min(fitted, key=lambda f: f[1])[0]
    fitted += refine_all(symmetric_alternatives(best_pose, surface))
    fitted.sort(key=lambda f: f[1])
    best_pose, best_score = fitted[0]
    runner_up = next(
        (s for p, s in fitted[1:] if pose_distance_mm(p, best_pose, corners) > distinct_mm), None
    )
    method = "fpfh-ransac + robust point-to-plane icp" if initial is None else "robust icp"
    fine = _fine_fit(points_cloud, surface, best_pose, options, rng, select)
    warnings: list[str] = []
    ambiguous = False
    if runner_up is not None and runner_up < options.ambiguity_ratio * max(best_score, 1e-12):
        ambiguous = True
        warnings.append(
            f"ambiguous pose: another pose {distinct_mm:.2g}+ mm away fits nearly as well "
            f"(score {runner_up:.3g} against {best_score:.3g} mm²); the part's symmetry is not "
            "broken by what the scan saw"
        )
    return AlignmentResult(
        nominal_from_cloud=fine.pose,
        method=method + (" (local best-fit)" if select is not None else ""),
        rms_mm=fine.rms_mm,
        points_used=fine.points_used,
        iterations=fine.iterations,
        converged=fine.converged,
        pose_u_mm=fine.pose_u_mm(corners),
        covariance=fine.covariance,
        candidates=len(fitted),
        runner_up_rms_mm=None if runner_up is None else float(np.sqrt(runner_up)),
        ambiguous=ambiguous,
        warnings=tuple(warnings + ([] if fine.converged else ["the fine fit did not converge"])),
    )


def _failed(surface: NominalSurface, reason: str) -> AlignmentResult:
    return AlignmentResult(
        nominal_from_cloud=np.eye(4),
        method="none",
        rms_mm=float("nan"),
        points_used=0,
        iterations=0,
        converged=False,
        pose_u_mm=float("nan"),
        covariance=np.full((6, 6), np.nan),
        candidates=0,
        warnings=(reason,),
    )


@dataclass(frozen=True)
class _Fine:
    pose: NDArray
    rms_mm: float
    points_used: int
    iterations: int
    converged: bool
    covariance: NDArray
    centre: NDArray

    def pose_u_mm(self, corners: NDArray) -> float:
        """Largest 1-sigma displacement over ``corners`` (8, 3) from the pose covariance."""
        worst = 0.0
        for c in corners:
            j = np.hstack([-_skew(c - self.centre), np.eye(3)])
            worst = max(worst, float(np.sqrt(np.trace(j @ self.covariance @ j.T))))
        return worst


def _skew(v: NDArray) -> NDArray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def _fine_fit(
    points_cloud: NDArray,
    surface: NominalSurface,
    pose: NDArray,
    options: AlignOptions,
    rng: np.random.Generator,
    select: Callable[[NDArray, NDArray], NDArray] | None,
) -> _Fine:
    """Least squares on the point-to-surface distance with a Cauchy loss, from ``pose``."""
    count = len(points_cloud)
    pick = rng.choice(count, min(count, options.fine_points), replace=False)
    points = points_cloud[pick]
    if select is not None:
        near = surface.closest(apply(pose, points))
        points = points[select(apply(pose, points), near.normals)]
    moved0 = apply(pose, points)
    centre = moved0.mean(axis=0)
    scale = _robust_scale(surface.closest(moved0).signed_mm, 1e-3)
    cache: dict[bytes, tuple[NDArray, NDArray]] = {}

    def evaluate(x: NDArray) -> tuple[NDArray, NDArray]:
        key = x.tobytes()
        if key not in cache:
            moved = apply(_small_motion(x, centre), moved0)
            near = surface.closest(moved)
            cache.clear()
            cache[key] = (near.signed_mm, _jacobian(moved, near.normals, centre))
        return cache[key]

    result = least_squares(
        lambda x: evaluate(x)[0],
        np.zeros(6),
        jac=lambda x: evaluate(x)[1],
        loss="cauchy",
        f_scale=3.0 * scale,
        x_scale=np.r_[np.full(3, 1.0 / surface.diagonal_mm), np.ones(3)],
        xtol=1e-10,
        ftol=1e-10,
        max_nfev=60,
    )
    r, j = evaluate(result.x)
    inliers = np.abs(r) < 4.685 * scale
    sigma = _robust_scale(r[inliers], 1e-4) if np.any(inliers) else scale
    ji = j[inliers]
    try:
        covariance = sigma**2 * np.linalg.inv(ji.T @ ji)
    except np.linalg.LinAlgError:
        covariance = np.full((6, 6), np.inf)
    return _Fine(
        pose=_small_motion(result.x, centre) @ pose,
        rms_mm=float(np.sqrt(np.mean(r[inliers] ** 2))) if np.any(inliers) else float("nan"),
        points_used=int(np.count_nonzero(inliers)),
        iterations=int(result.nfev),
        converged=bool(result.status > 0),
        covariance=covariance,
        centre=centre,
    )


def rps_frame(planes: list[tuple[NDArray, NDArray]]) -> NDArray:
    """The 3-2-1 frame (4, 4) of three datum planes, each ``(unit normal, point on it)``.

    The primary's normal is the z axis, the secondary's normal made orthogonal to it the x
    axis, and the three planes' common point the origin: two such frames, one of the nominal
    datums and one of the measured, give the RPS alignment ``nominal @ inv(measured)``.
    """
    (n1, p1), (n2, p2), (n3, p3) = planes
    z = n1 / np.linalg.norm(n1)
    x = n2 - (n2 @ z) * z
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    a = np.vstack([n1, n2, n3])
    origin = np.linalg.solve(a, np.array([n1 @ p1, n2 @ p2, n3 @ p3]))
    frame = np.eye(4)
    frame[:3, :3] = np.column_stack([x, y, z])
    frame[:3, 3] = origin
    return frame
