"""Light plane: robust fit of stripe points on the target, and the paper's A-O-B method."""

import numpy as np
import pytest

from calibration.light_plane import (
    LaserView,
    PaperPlaneView,
    calibrate_light_plane,
    fit_plane,
    fit_plane_robust,
    paper_diameter_points,
    paper_light_plane,
)
from tests.calibration import _synthetic as S

N_TRUE = np.array([0.9, 0.05, 0.3]) / np.linalg.norm([0.9, 0.05, 0.3])
D_TRUE = -float(N_TRUE @ np.array([0.0, 0.0, 450.0]))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(abs(a @ b), -1, 1))))


def _stripe_on_target(cam, ct, rng, noise_px=0.1, n=300):
    """Pixels of the laser line on the target plane of pose ``ct``."""
    tn = ct[:3, 2]
    td = -tn @ ct[:3, 3]
    direction = np.cross(N_TRUE, tn)
    direction /= np.linalg.norm(direction)
    p0 = np.linalg.lstsq(np.vstack([N_TRUE, tn]), -np.array([D_TRUE, td]), rcond=None)[0]
    # Centre the segment on the target: the foot of the target origin on the line.
    p0 = p0 + direction * float((ct[:3, 3] - p0) @ direction)
    pts = p0 + np.outer(np.linspace(-70, 70, n), direction)
    return cam.project(pts) + rng.normal(0, noise_px, (n, 2))


def _laser_views(cam, rng, n, noise_px=0.1, extent=None):
    """``n`` laser frames, ids 0..n-1, each at a random target pose with its stripe."""
    views = []
    for i in range(n):
        ct = S.look_at_target(rng)
        views.append(LaserView(i, _stripe_on_target(cam, ct, rng, noise_px=noise_px), ct, extent))
    return views


def test_fit_plane_recovers_truth():
    rng = np.random.default_rng(0)
    e1 = np.cross(N_TRUE, [0, 1, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(N_TRUE, e1)
    uv = rng.uniform(-100, 100, (500, 2))
    pts = (
        -D_TRUE * N_TRUE + uv[:, :1] * e1 + uv[:, 1:] * e2 + rng.normal(0, 0.01, (500, 1)) * N_TRUE
    )
    fit = fit_plane(pts)
    assert fit
    assert _angle_deg(fit.normal, N_TRUE) < 0.01
    assert abs(fit.d - D_TRUE) < 0.005
    assert abs(fit.rms_mm - 0.01) < 0.002
    assert _angle_deg(fit.normal, N_TRUE) < 5 * fit.std_normal_deg
    # Outliers: RANSAC keeps the plane.
    bad = pts.copy()
    bad[:50] += N_TRUE * rng.uniform(2, 10, (50, 1))
    robust = fit_plane_robust(bad, threshold_mm=0.1)
    assert robust and robust.inliers[:50].sum() == 0
    assert _angle_deg(robust.normal, N_TRUE) < 0.01


def test_fit_plane_refuses_collinear_points_and_checks_shape():
    line = np.outer(np.arange(10.0), [1.0, 2.0, 3.0])
    fit = fit_plane(line)
    assert not fit and "collinear" in fit.reason
    with pytest.raises(ValueError, match="expected"):
        fit_plane(np.zeros((2, 3)))


def test_calibrate_light_plane_recovers_truth_and_rejects_a_bad_frame():
    rng = np.random.default_rng(1)
    cam = S.camera()
    views = _laser_views(cam, rng, 8, extent=(-100, 100, -100, 100))
    # One frame whose stripe is shifted by 8 px (wrong target pose or another line).
    views.append(LaserView(99, views[0].stripe_px + np.array([0.0, 8.0]), views[0].cam_from_target))
    res = calibrate_light_plane(views, cam)
    assert res, res.reason
    assert _angle_deg(res.plane.normal, N_TRUE) < 0.01
    assert abs(abs(res.plane.d) - abs(D_TRUE)) < 0.05
    assert [r["frame_id"] for r in res.rejected] == [99]
    assert len(res.per_frame) == 8
    assert res.rms_mm < 0.05


def test_a_frame_whose_target_pose_is_slightly_off_is_rejected_by_its_mean_offset():
    # The stripe noise (0.3 px) spreads each frame's points by ~0.1 mm, so a target pose
    # 0.15 mm off along its normal hides in the RMS; the frame's mean offset gives it away.
    rng = np.random.default_rng(3)
    cam = S.camera()
    views = _laser_views(cam, rng, 10, noise_px=0.3)
    shifted = views[4].cam_from_target.copy()
    shifted[:3, 3] += 0.15 * shifted[:3, 2]  # the target believed 0.15 mm off its true plane
    views[4] = LaserView(4, views[4].stripe_px, shifted)
    res = calibrate_light_plane(views, cam)
    assert res, res.reason
    assert [r["frame_id"] for r in res.rejected] == [4]
    assert "on average" in res.rejected[0]["reason"]
    # The same plane as without the frame; keeping it (offset test off) pulls d.
    without = calibrate_light_plane(views[:4] + views[5:], cam)
    assert np.allclose(res.plane.normal, without.plane.normal) and res.plane.d == without.plane.d
    kept = calibrate_light_plane(views, cam, offset_factor=1e9, min_offset_mm=1e9)
    assert kept.rejected == []
    assert abs(abs(kept.plane.d) - abs(D_TRUE)) > abs(abs(res.plane.d) - abs(D_TRUE))


def test_calibrate_light_plane_needs_two_frames():
    rng = np.random.default_rng(2)
    cam = S.camera()
    ct = S.look_at_target(rng)
    res = calibrate_light_plane([LaserView(0, _stripe_on_target(cam, ct, rng), ct)], cam)
    assert not res and ">= 2" in res.reason


def _paper_views(cam, rng, noise_px, n=7, r=80.0):
    views, truth = [], []
    for i in range(n):
        o = np.array([0.0, 0.0, 450.0]) + rng.uniform(-30, 30, 3)
        o -= (N_TRUE @ o + D_TRUE) * N_TRUE
        x = np.cross(N_TRUE, o / np.linalg.norm(o) + 0.3 * rng.normal(size=3))
        x /= np.linalg.norm(x)
        pts = np.vstack([o + r * x, o, o - r * x])
        uv = cam.project(pts) + rng.normal(0, noise_px, (3, 2))
        views.append(PaperPlaneView(i, uv[0], uv[1], uv[2]))
        truth.append(pts)
    return views, truth


def test_paper_equations_7_8_are_exact_without_noise():
    rng = np.random.default_rng(3)
    cam = S.camera()
    views, truth = _paper_views(cam, rng, 0.0)
    for v, t in zip(views, truth):
        pts = paper_diameter_points(cam, v.a_px, v.o_px, v.b_px, 80.0)
        assert np.abs(pts - t).max() < 1e-6
    res = paper_light_plane(views, cam, 80.0)
    assert res
    assert _angle_deg(res.plane.normal, N_TRUE) < 1e-6
    assert abs(res.plane.d - D_TRUE) < 1e-5


def test_paper_light_plane_with_noise_and_too_few_positions():
    rng = np.random.default_rng(4)
    cam = S.camera()
    views, _ = _paper_views(cam, rng, 0.05)
    res = paper_light_plane(views, cam, 80.0)
    assert res
    # The method rests on three points per position: 0.05 px gives tenths of a degree.
    assert _angle_deg(res.plane.normal, N_TRUE) < 1.0
    res = paper_light_plane(views[:1], cam, 80.0)
    assert not res and ">= 2" in res.reason
