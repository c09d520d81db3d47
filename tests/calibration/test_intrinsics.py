import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.detection.conics import fit_conic, fit_line, harmonic_conjugate
from calibration.detection.observations import AxisObservation, RingObservation, TargetObservation
from calibration.intrinsics import calibrate_intrinsics, paper_intrinsics
from scanner.core.conventions import make_transform
from scanner.formats.reference_data import ZHANG_MSR_IMAGE_SIZE, zhang_msr_corners

SIZE = (1280, 1024)
K_TRUE = np.array([[1800.0, 0.0, 652.3], [0.0, 1797.5, 498.7], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.12, 0.08, 0.0005, -0.0003, -0.01])
RADII = np.linspace(20.0, 60.0, 10)


def real_data_dir() -> Path:
    env = os.environ.get("SCANNER_REAL_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real"


def poses(n: int, rng: np.random.Generator, max_tilt_deg: float = 45.0) -> list[np.ndarray]:
    out = []
    face = Rotation.from_euler("x", 180, degrees=True)
    for i in range(n):
        u = (0.15 + 0.7 * ((i % 5) + rng.uniform(0.2, 0.8)) / 5) * SIZE[0]
        v = (0.15 + 0.7 * (((i // 5) % 4) + rng.uniform(0.2, 0.8)) / 4) * SIZE[1]
        ray = np.linalg.solve(K_TRUE, [u, v, 1.0])
        ray /= np.linalg.norm(ray)
        align, _ = Rotation.align_vectors([[0, 0, 1.0]], [ray])
        tilt = np.radians(max_tilt_deg) * np.sqrt(rng.uniform(0.05, 1.0))
        az = rng.uniform(0, 2 * np.pi)
        rot = (
            align.inv()
            * Rotation.from_rotvec(tilt * np.array([np.cos(az), np.sin(az), 0.0]))
            * face
            * Rotation.from_euler("z", rng.uniform(0, 360), degrees=True)
        )
        out.append(make_transform(rot, ray * 350.0 * rng.uniform(0.9, 1.1)))
    return out


def project(T: np.ndarray, pts_t: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    rvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    uv, _ = cv2.projectPoints(pts_t.reshape(-1, 1, 3), rvec, T[:3, 3], K, dist)
    return uv.reshape(-1, 2)


def synthetic_observation(
    T: np.ndarray, K: np.ndarray, dist: np.ndarray, rng: np.random.Generator, noise_px: float
) -> TargetObservation:
    """What a perfect detector reports for one view, plus Gaussian noise on the edge points."""
    rings = []
    for k, r in enumerate(RADII):
        th = np.linspace(0, 2 * np.pi, 360, endpoint=False)
        pts = project(T, np.column_stack([r * np.cos(th), r * np.sin(th), 0 * th]), K, dist)
        inside = (
            (pts[:, 0] > 5)
            & (pts[:, 0] < SIZE[0] - 6)
            & (pts[:, 1] > 5)
            & (pts[:, 1] < SIZE[1] - 6)
        )
        pts = pts[inside] + rng.normal(0, noise_px, (int(inside.sum()), 2))
        rings.append(RingObservation(float(r), pts, fit_conic(pts, geometric=False), k))
    axes = []
    s = np.r_[np.linspace(-58, -3, 30), np.linspace(3, 58, 30)]
    for name, col in (("x", 0), ("y", 1)):
        p = np.zeros((len(s), 3))
        p[:, col] = s
        uv = project(T, p, K, dist) + rng.normal(0, noise_px, (len(s), 2))
        axes.append(AxisObservation(name, uv, fit_line(uv)))
    pts_t = [np.zeros(3)]
    for r in RADII:
        pts_t += [
            np.array([r, 0, 0]),
            np.array([-r, 0, 0]),
            np.array([0, r, 0]),
            np.array([0, -r, 0]),
        ]
    pts_t = np.asarray(pts_t)
    uv = project(T, pts_t, K, dist)
    named = {"O": uv[0], "A": uv[-4], "B": uv[-3], "C": uv[-2], "D": uv[-1]}
    vps = {
        "p": harmonic_conjugate(named["A"], named["B"], named["O"]),
        "q": harmonic_conjugate(named["C"], named["D"], named["O"]),
    }
    return TargetObservation(
        ok=True,
        reason="",
        image_size=SIZE,
        kind="concentric_circles",
        points_px=uv,
        points_target=pts_t,
        rings=rings,
        axis_points=axes,
        center_px=uv[0],
        named_px=named,
        vanishing_points=vps,
    )


def test_paper_method_is_exact_without_noise_and_distortion():
    rng = np.random.default_rng(1)
    obs = [synthetic_observation(T, K_TRUE, np.zeros(5), rng, 0.0) for T in poses(8, rng)]
    res = calibrate_intrinsics(obs, SIZE, method="paper")
    assert res.method == "paper"
    assert np.allclose(res.K, K_TRUE, rtol=1e-6, atol=1e-3)
    for variant in ("diameter_ends", "all_rings"):
        est = res.paper[variant]
        assert est, est.reason
        assert np.allclose(est.K, K_TRUE, rtol=1e-6, atol=1e-3)


def test_paper_method_needs_four_views_with_finite_vanishing_points():
    vp = (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))  # fronto-parallel: at infinity
    est = paper_intrinsics([vp] * 6)
    assert not est
    assert "expected >= 4" in est.reason


def test_default_recovers_intrinsics_and_distortion():
    rng = np.random.default_rng(2)
    obs = [synthetic_observation(T, K_TRUE, DIST_TRUE, rng, 0.03) for T in poses(20, rng)]
    # Independent noise on every point here: every point carries information, use them all.
    res = calibrate_intrinsics(obs, SIZE, max_points_per_ring=360)
    assert res.method == "default"
    assert abs(res.fx / K_TRUE[0, 0] - 1) < 3e-5
    assert abs(res.fy / K_TRUE[1, 1] - 1) < 3e-5
    assert abs(res.cx - K_TRUE[0, 2]) < 0.1
    assert abs(res.cy - K_TRUE[1, 2]) < 0.1
    assert res.rms_px == pytest.approx(0.03, rel=0.2)
    assert len(res.cam_from_target) == 20
    assert set(res.std) == {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}
    assert res.std["fx"] < 0.2
    assert res.correlation.shape == (9, 9)
    # The distortion model maps every pixel like the truth, within 0.05 px.
    uu, vv = np.meshgrid(np.arange(0, SIZE[0], 32), np.arange(0, SIZE[1], 32))
    uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(float)
    xy = cv2.undistortPointsIter(
        uv.reshape(-1, 1, 2),
        K_TRUE,
        DIST_TRUE,
        None,
        None,
        (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14),
    ).reshape(-1, 2)
    back = project(np.eye(4), np.column_stack([xy, np.ones(len(xy))]), res.K, res.dist)
    # Within 0.1 px (mostly the principal point, sigma ~0.1 px at this noise), shape 0.05 px.
    assert np.max(np.linalg.norm(back - uv, axis=1)) < 0.1


def test_default_rejects_an_outlier_view_with_a_reason():
    rng = np.random.default_rng(3)
    obs = [synthetic_observation(T, K_TRUE, DIST_TRUE, rng, 0.03) for T in poses(8, rng)]
    bad = obs[5]
    for k, ring in enumerate(bad.rings):  # a view whose rings were mislabelled by one
        ring.radius_mm = float(RADII[(k + 1) % len(RADII)])
    res = calibrate_intrinsics(obs, SIZE)
    assert 5 not in res.view_indices
    assert any(i == 5 and "outlier" in why for i, why in res.rejected)
    assert abs(res.fx / K_TRUE[0, 0] - 1) < 2e-4


def test_too_few_views_names_what_is_missing():
    rng = np.random.default_rng(4)
    obs = [synthetic_observation(T, K_TRUE, DIST_TRUE, rng, 0.03) for T in poses(3, rng)]
    obs.append(TargetObservation.failed("no ring pencil found", SIZE, "concentric_circles"))
    with pytest.raises(ValueError, match=r"expected >= 4 views.*no ring pencil found"):
        calibrate_intrinsics(obs, SIZE)


def test_fronto_parallel_views_warn_that_focal_length_is_poorly_determined():
    rng = np.random.default_rng(5)
    obs = [
        synthetic_observation(T, K_TRUE, np.zeros(5), rng, 0.03)
        for T in poses(6, rng, max_tilt_deg=3.0)
    ]
    res = calibrate_intrinsics(obs, SIZE, fixed=("k1", "k2", "p1", "p2", "k3"))
    assert any("fronto-parallel" in w for w in res.warnings)


def test_point_targets_go_through_the_same_adjustment():
    rng = np.random.default_rng(6)
    grid = np.array([(i * 20.0 - 60, j * 20.0 - 40, 0.0) for j in range(5) for i in range(7)])
    obs = []
    for T in poses(10, rng):
        uv = project(T, grid, K_TRUE, DIST_TRUE) + rng.normal(0, 0.05, (len(grid), 2))
        obs.append(TargetObservation(True, "", SIZE, "circle_grid", uv, grid))
    res = calibrate_intrinsics(obs, SIZE)
    assert abs(res.fx / K_TRUE[0, 0] - 1) < 1e-3
    assert abs(res.cx - K_TRUE[0, 2]) < 2.0
    with pytest.raises(ValueError, match="paper"):
        calibrate_intrinsics(obs, SIZE, method="paper")


@pytest.mark.real_data
def test_zhang_published_result_from_given_corners():
    root = real_data_dir() / "zhang_msr"
    if not (root / "Model.txt").is_file():
        pytest.skip(f"real data not found at {root} (set SCANNER_REAL_DATA)")
    model_t, views = zhang_msr_corners(root)
    size = ZHANG_MSR_IMAGE_SIZE
    obs = [TargetObservation(True, "", size, "chessboard", uv, model_t) for uv in views]
    # Zhang's published model: two radial terms (his skew 0.2 is negligible).
    res = calibrate_intrinsics(obs, size, fixed=("p1", "p2", "k3"))
    assert res.fx == pytest.approx(832.5, rel=1e-3)
    assert res.fy == pytest.approx(832.53, rel=1e-3)
    assert res.cx == pytest.approx(303.959, abs=1.0)
    assert res.cy == pytest.approx(206.585, abs=1.0)
    assert res.dist[0] == pytest.approx(-0.228601, abs=0.005)
    assert res.dist[1] == pytest.approx(0.190353, abs=0.02)
