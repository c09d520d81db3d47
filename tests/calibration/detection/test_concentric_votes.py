"""Candidate centres voted by the printed lines' edges, and the darkest lines through one."""

from __future__ import annotations

import cv2
import numpy as np

from calibration.detection.concentric_votes import axes_through, full_image_px, voted_centres
from tests.calibration.synth_concentric import seen_rings


def _rings_map(
    rng: np.random.Generator, size=(640, 480), clutter: int = 6
) -> tuple[np.ndarray, np.ndarray]:
    """A darkness map in units of its threshold: five concentric rings of 20-60 mm seen
    through a random homography (tilts up to about 60 deg), small in the frame, among
    ``clutter`` single circles of 30-150 px and as many long lines; its image of O."""
    w, h = size
    z = np.zeros((h, w), np.float32)
    radii = (20.0, 30.0, 40.0, 50.0, 60.0)
    _, conics, o = seen_rings(rng, radii)
    # (the rings drawn as the points where their conics change sign, 2 px thick)
    ys, xs = np.mgrid[:h, :w]
    pts = np.stack([xs - 320.0 + o[0], ys - 240.0 + o[1], np.ones_like(xs, float)], axis=-1)
    for conic in conics.values():
        q = np.einsum("...i,ij,...j->...", pts, conic, pts)
        gx = np.einsum("...i,i->...", pts, conic[0]) * 2
        gy = np.einsum("...i,i->...", pts, conic[1]) * 2
        z[np.abs(q) / np.maximum(np.hypot(gx, gy), 1e-12) < 1.0] = 3.0
    for _ in range(clutter):
        c = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        cv2.circle(z, c, int(rng.uniform(30, 150)), 3.0, 2)
        p, q = rng.uniform(0, w, 2), rng.uniform(0, h, 2)
        cv2.line(z, (int(p[0]), int(q[0])), (int(p[1]), int(q[1])), 3.0, 2)
    noise = rng.normal(0.0, 0.3, z.shape).astype(np.float32)
    return cv2.GaussianBlur(z, (0, 0), 0.8) + noise, np.array([320.0, 240.0])


def test_the_centre_of_concentric_rings_is_among_the_first_peaks():
    # Clutter's single circles collect votes too, but five rings' edges outvote them near O
    # (within a few px: a tilt spreads the votes over the ellipses' evolutes, about their
    # centres, which perspective moves off O; the rays' judgement follows)
    rng = np.random.default_rng(41)
    ranks = []
    for _ in range(10):
        z, o = _rings_map(rng)
        peaks = voted_centres(z)
        assert len(peaks) > 0
        near = np.flatnonzero(np.linalg.norm(peaks - o, axis=1) < 8.0)
        ranks.append(int(near[0]) if len(near) else 99)
    assert max(ranks) < 3, ranks
    assert sum(r == 0 for r in ranks) >= 8, ranks


def test_a_large_view_votes_on_a_reduced_map_and_keeps_its_pixels():
    # A 1600x1200 view is voted on at half size; the peaks come back in its own pixels
    rng = np.random.default_rng(42)
    z, o = _rings_map(rng, clutter=0)
    big = cv2.resize(z, None, fx=2.5, fy=2.5, interpolation=cv2.INTER_LINEAR)
    peaks = voted_centres(big)
    # (the map's pixel (x, y) is at 2.5 (x, y) + 0.75 of the big one's)
    assert np.linalg.norm(peaks[0] - (2.5 * o + 0.75)) < 8.0


def test_reduced_pixels_map_back_to_the_full_maps_pixel_centres():
    # A size the factor does not divide: OpenCV's resize scales each axis by its own ratio
    # (5184x3456 to 740x493: 7.005 and 7.010), pixel centres onto pixel centres
    full, reduced = (5184, 3456), (740, 493)
    corners = np.array([[-0.5, -0.5], [739.5, 492.5], [0.0, 0.0]])
    np.testing.assert_allclose(
        full_image_px(corners, reduced, full),
        [[-0.5, -0.5], [5183.5, 3455.5], [5184 / 740 / 2 - 0.5, 3456 / 493 / 2 - 0.5]],
    )
    # ... as OpenCV maps them: a dot at full-size pixel (4000, 3000) lands on that pixel
    dot = np.zeros((3456, 5184), np.float32)
    dot[2996:3005, 3996:4005] = 1.0
    small = cv2.resize(dot, reduced, interpolation=cv2.INTER_AREA)
    ys, xs = np.mgrid[: small.shape[0], : small.shape[1]]
    centroid = np.array([(xs * small).sum(), (ys * small).sum()]) / small.sum()
    np.testing.assert_allclose(
        full_image_px(centroid[None], reduced, full)[0], [4000, 3000], atol=0.5
    )


def test_a_map_without_edges_votes_for_nothing():
    assert voted_centres(np.zeros((120, 160))).shape == (0, 2)
    assert voted_centres(np.full((120, 160), -1.0)).shape == (0, 2)  # (all hidden)


def test_the_darkest_lines_through_a_point_are_its_diameters():
    z = np.zeros((480, 640))
    c = np.array([320.0, 240.0])
    for a in np.radians([25.0, 110.0]):
        e = 200 * np.array([np.cos(a), np.sin(a)])
        cv2.line(z, tuple(int(v) for v in c - e), tuple(int(v) for v in c + e), 3.0, 2)
    cv2.line(z, (0, 50), (639, 60), 3.0, 2)  # a line that misses c
    z[230:250, 350:400] = -1.0  # the print hidden on part of one
    angles = axes_through(z, c, 60.0)
    found = sorted(float(np.degrees(a)) % 180 for a in angles[::2])
    np.testing.assert_allclose(found, [25.0, 110.0], atol=1.0)
    np.testing.assert_allclose(np.subtract(angles[1::2], angles[::2]), np.pi)
