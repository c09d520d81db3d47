"""Rings the coarse stage missed, named and measured from the pencil of two measured ones."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial.transform import Rotation

from calibration.detection.concentric_missing import _namings, recovered_rings
from calibration.detection.concentric_rings import (
    ConcentricDetectorSettings,
    _refine_ring,
    spline_window,
)
from calibration.detection.conics import sampson_distances

RADII_MM = np.array([12.0, 22.0, 32.0, 42.0])
SIZE = (480, 400)


def _image_from_target() -> np.ndarray:
    """``img_from_target`` (3, 3): the target plane tilted 35 deg, O at (240, 200) px."""
    k = np.array([[800.0, 0.0, 240.0], [0.0, 800.0, 200.0], [0.0, 0.0, 1.0]])
    rot = Rotation.from_euler("xy", [35.0, 12.0], degrees=True).as_matrix()
    return k @ np.column_stack([rot[:, 0], rot[:, 1], [0.0, 0.0, 500.0]])


def _ring_conic(img_from_target: np.ndarray, radius_mm: float) -> np.ndarray:
    inv = np.linalg.inv(img_from_target)
    conic = inv.T @ np.diag([1.0, 1.0, -(radius_mm**2)]) @ inv
    return conic / np.linalg.norm(conic)


def _ring_points(img_from_target: np.ndarray, radius_mm: float) -> np.ndarray:
    th = np.linspace(0.0, 2 * np.pi, 360, endpoint=False)
    xy1 = np.column_stack([radius_mm * np.cos(th), radius_mm * np.sin(th), np.ones_like(th)])
    uvw = xy1 @ img_from_target.T
    return uvw[:, :2] / uvw[:, 2:]


def _darkness(img_from_target: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A darkness map ``(H, W)`` of the four rings' printed lines (1 mm wide), each pixel the
    share of ink over 4 x 4 samples, blurred by 0.8 px and noisy."""
    w, h = SIZE
    n = 4
    offs = (np.arange(n) + 0.5) / n - 0.5
    uu, vv = np.meshgrid(np.arange(w * n) / n + offs[0], np.arange(h * n) / n + offs[0])
    uvw = np.stack([uu, vv, np.ones_like(uu)], axis=-1) @ np.linalg.inv(img_from_target).T
    rho = np.hypot(uvw[..., 0] / uvw[..., 2], uvw[..., 1] / uvw[..., 2])
    ink = np.min(np.abs(rho[..., None] - RADII_MM), axis=-1) < 0.5
    share = ink.reshape(h, n, w, n).mean(axis=(1, 3))
    return 0.3 * ndimage.gaussian_filter(share, 0.8) + rng.normal(0.0, 0.005, (h, w))


def test_the_one_naming_with_the_specs_ratios_is_found() -> None:
    hom = _image_from_target()
    measured = {
        k: (np.zeros((0, 2)), _ring_conic(hom, RADII_MM[k + 1]), np.zeros(1)) for k in (0, 1)
    }
    assert _namings(measured, RADII_MM) == [1]  # rings 1 and 2, counted from 0
    named = {k + 1: ring for k, ring in measured.items()}
    assert _namings(named, RADII_MM) == [0]
    # radii in one ratio: no naming is told from its neighbours (none agrees)
    geometric = np.array([10.0, 20.0, 40.0, 80.0])
    pair = {k: (np.zeros((0, 2)), _ring_conic(hom, geometric[k + 1]), np.zeros(1)) for k in (0, 1)}
    assert _namings(pair, geometric) == []
    assert recovered_rings(pair, geometric, np.zeros(2), lambda conic: None) is pair


def test_missing_rings_are_measured_where_the_two_rings_pencil_puts_them() -> None:
    rng = np.random.default_rng(43)
    hom = _image_from_target()
    d = _darkness(hom, rng)
    o_px = hom[:2, 2] / hom[2, 2]
    truth = {k: _ring_conic(hom, r) for k, r in enumerate(RADII_MM)}
    angles = np.linspace(0.0, 2 * np.pi, 360, endpoint=False)
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    axis_lines = [np.array([0.0, 1.0, -1e4]), np.array([1.0, 0.0, -1e4])]  # (far away)
    s = ConcentricDetectorSettings()
    spline = spline_window(d, list(truth.values()), o_px, 40.0)
    common = (o_px, dirs, angles, axis_lines, 3.0, 9.0, s, SIZE, None)
    # Rings 1 and 2 measured, named 0 and 1 by rays that missed ring 0
    measured = {k - 1: _refine_ring(spline, truth[k], *common) for k in (1, 2)}
    assert all(ring is not None for ring in measured.values())
    out = recovered_rings(
        measured, RADII_MM, o_px, lambda conic: _refine_ring(spline, conic, *common)
    )
    assert sorted(out) == [0, 1, 2, 3]
    assert out[1] is measured[0] and out[2] is measured[1]
    for k, (_, conic, _) in out.items():
        off = sampson_distances(conic, _ring_points(hom, RADII_MM[k]))
        assert np.max(np.abs(off)) < 0.1, k


def test_fewer_than_two_rings_are_refused() -> None:
    with pytest.raises(ValueError, match="expected at least 2 measured rings, got 1"):
        recovered_rings(
            {0: (np.zeros((0, 2)), np.eye(3), np.zeros(1))}, RADII_MM, np.zeros(2), lambda q: None
        )
