"""Signed distances to the nominal against a box whose distances are known in closed form."""

from __future__ import annotations

import numpy as np

from metrology.inspect.surface import NominalSurface
from scanner.virtual_cell.parts import box_mesh


def _box_signed_distance(p: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Exact signed distance to the box [0, size]: positive outside."""
    centre, half = size / 2, size / 2
    q = np.abs(p - centre) - half
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    inside = np.minimum(q.max(axis=1), 0)
    return outside + inside


def test_signed_distance_matches_the_box_in_and_out() -> None:
    rng = np.random.default_rng(0)
    size = np.array([100.0, 60.0, 30.0])
    surface = NominalSurface(box_mesh(tuple(size)))
    p = rng.uniform(-20, 120, (5000, 3))
    got = surface.closest(p).signed_mm
    # float32 inside the BVH: about 1e-7 of the coordinates
    np.testing.assert_allclose(got, _box_signed_distance(p, size), atol=5e-5)


def test_sampled_points_lie_on_the_surface_uniformly_by_area() -> None:
    rng = np.random.default_rng(1)
    surface = NominalSurface(box_mesh((100.0, 60.0, 30.0)))
    p, n = surface.sample(60_000, rng)
    np.testing.assert_allclose(surface.closest(p).signed_mm, 0.0, atol=2e-5)
    top = np.mean(n[:, 2] > 0.5)
    assert abs(top - 6000 / 2 / (6000 + 3000 + 1800)) < 0.01
    np.testing.assert_allclose(surface.corners().min(axis=0), 0.0)
    assert surface.diagonal_mm == np.linalg.norm([100, 60, 30])
