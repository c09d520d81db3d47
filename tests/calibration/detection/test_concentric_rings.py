"""Ring conics named by their sizes when the rays' labels are off; a diameter's evidence and
direction; ring points cut back to where the other rings' pencil puts them."""

from __future__ import annotations

import cv2
import numpy as np

from calibration.detection.concentric_rings import (
    _diameter_lines,
    _line_evidence,
    _lines_angle_deg,
    _normal_clear_of,
    _pencil_centre,
    _prune_by_pencil,
    _relabel_by_ratios,
)
from calibration.detection.conics import fit_conic, sampson_distances


def _circle(radius_px: float, centre=(320.0, 240.0)) -> np.ndarray:
    cx, cy = centre
    return np.array([[1.0, 0, -cx], [0, 1.0, -cy], [-cx, -cy, cx * cx + cy * cy - radius_px**2]])


def test_labels_shifted_by_a_missed_ring_are_put_right() -> None:
    radii = np.array([10.0, 20.0, 30.0, 40.0, 50.0])
    scale = 3.7  # px per mm
    # Rings 1..4 seen, but counted from 0 (the innermost ring was missed).
    conics = {k: _circle(scale * radii[k + 1]) for k in range(4)}
    renamed = _relabel_by_ratios(conics, radii)
    assert sorted(renamed) == [1, 2, 3, 4]
    for n, conic in renamed.items():
        np.testing.assert_allclose(conic, _circle(scale * radii[n]))


def test_a_spurious_outer_conic_does_not_decide() -> None:
    radii = np.array([10.0, 20.0, 30.0, 40.0, 50.0])
    scale = 2.0
    conics = {0: _circle(scale * 20), 1: _circle(scale * 30), 2: _circle(scale * 40)}
    conics[3] = _circle(scale * 50)
    conics[4] = _circle(scale * 80)  # the card's edge
    renamed = _relabel_by_ratios(conics, radii)
    assert sorted(renamed) == [1, 2, 3, 4]
    np.testing.assert_allclose(renamed[4], _circle(scale * 50))


def test_sizes_that_fit_no_spec_give_nothing() -> None:
    radii = np.array([10.0, 20.0, 30.0])
    conics = {0: _circle(10.0), 1: _circle(10.0 * 1.17)}
    assert _relabel_by_ratios(conics, radii) == {}


def _rings_and_x_diameter(thickness_px: int) -> tuple[np.ndarray, np.ndarray]:
    """A darkness map: five rings 13 px apart around (320, 240), one diameter along x."""
    d = np.zeros((480, 640))
    for r in (26, 39, 52, 65, 78):
        cv2.circle(d, (320, 240), r, 0.6, thickness_px)
    cv2.line(d, (242, 240), (398, 240), 0.6, thickness_px)
    return cv2.GaussianBlur(d, (0, 0), 1.0), np.array([320.0, 240.0])


def test_a_printed_diameter_shows_evidence_and_any_other_line_through_o_none() -> None:
    # thick rings (they fill much of any line) and one printed diameter along x
    d, c = _rings_and_x_diameter(4)
    ring_dark = 0.55
    x_axis = np.array([0.0, 1.0, -240.0])
    ends_x = np.array([[242.0, 240.0], [398.0, 240.0]])
    assert _line_evidence(d, x_axis, c, ends_x, 10.0, ring_dark) > 0.3 * ring_dark
    diagonal = np.array([1.0, -1.0, -80.0]) / np.sqrt(2.0)
    ends_d = c + 78.0 * np.array([[1.0, 1.0], [-1.0, -1.0]]) / np.sqrt(2.0)
    assert abs(_line_evidence(d, diagonal, c, ends_d, 10.0, ring_dark)) < 0.1 * ring_dark
    # (the pencil of these circles has its centre at c)
    conics = {k: _circle(r, (320.0, 240.0)) for k, r in enumerate((26.0, 39.0, 52.0))}
    np.testing.assert_allclose(_pencil_centre(conics, np.array([2.0, 3.0, 4.0]), c), c, atol=1e-6)


def _rings_with_diameters(angles_deg: tuple[float, float]) -> tuple[np.ndarray, dict]:
    """A darkness map in units of its threshold: five rings, two diameters at the angles."""
    z = np.zeros((480, 640))
    c = (320, 240)
    radii = (26, 39, 52, 65, 78)
    for r in radii:
        cv2.circle(z, c, r, 3.0, 2)
    for a in np.radians(angles_deg):
        e = 78 * np.array([np.cos(a), np.sin(a)])
        cv2.line(z, tuple(int(v) for v in c - e), tuple(int(v) for v in c + e), 3.0, 2)
    conics = {k: _circle(float(r)) for k, r in enumerate(radii)}
    return cv2.GaussianBlur(z, (0, 0), 0.8), conics


def test_the_diameters_are_found_through_the_centre_not_a_stripe_beside_it() -> None:
    z, conics = _rings_with_diameters((20.0, 75.0))
    # a laser stripe (hidden: negative) through the target near the centre, with the dark
    # halo a closing leaves beside it: a Hough pair may hold the halo's line
    cv2.line(z, (0, 200), (639, 330), -1.0, 7)
    cv2.line(z, (0, 207), (639, 337), 2.0, 1)
    lines = _diameter_lines(z, np.array([320.0, 240.0]), conics, 2.0, 13.0)
    assert lines is not None
    found = sorted(float(np.degrees(np.arctan2(-ln[0], ln[1])) % 180) for ln in lines)
    np.testing.assert_allclose(found, [20.0, 75.0], atol=0.5)
    assert _lines_angle_deg(*lines) > 50


def test_without_two_printed_diameters_the_scan_gives_nothing() -> None:
    z, conics = _rings_with_diameters((20.0,))
    assert _diameter_lines(z, np.array([320.0, 240.0]), conics, 2.0, 13.0) is None


def test_a_stripe_along_a_diameter_leaves_the_other_parallel_as_evidence() -> None:
    d, c = _rings_and_x_diameter(2)
    bright = np.zeros_like(d)
    bright[245:256, :] = 1.0  # a stripe just below the diameter covers one parallel
    x_axis = np.array([0.0, 1.0, -240.0])
    ends_x = np.array([[242.0, 240.0], [398.0, 240.0]])
    assert _line_evidence(d, x_axis, c, ends_x, 10.0, 0.55, bright) > 0.3 * 0.55
    bright[236:246, :] = 1.0  # ... and the diameter itself: nothing to tell
    assert _line_evidence(d, x_axis, c, ends_x, 10.0, 0.55, bright) == 0.0


def test_a_ring_that_follows_something_else_over_part_of_its_length_is_cut_back() -> None:
    # Four rings; the outer one's points follow a curve 9 px inside it over a quarter of
    # its length (a stripe's halo where the ring is hidden). Its conic still surrounds the
    # centre and its ratio passes; the other rings' pencil puts the ring elsewhere there.
    rng = np.random.default_rng(3)
    c = np.array([320.0, 240.0])
    radii = np.array([20.0, 35.0, 50.0, 65.0])
    scale = 2.0
    th = np.linspace(0, 2 * np.pi, 240, endpoint=False)
    rings = {}
    for k, r in enumerate(radii):
        rho = np.full_like(th, scale * r)
        if k == 3:
            rho[(th > 0.5) & (th < 2.0)] -= 9.0
        pts = c + rho[:, None] * np.column_stack([np.cos(th), np.sin(th)])
        pts += rng.normal(0.0, 0.05, pts.shape)
        rings[k] = (pts, fit_conic(pts), np.zeros(1))
    pruned = _prune_by_pencil(rings, radii, c, 30.0)
    assert sorted(pruned) == [0, 1, 2, 3]
    for k in range(3):  # the good rings keep every point
        assert len(pruned[k][0]) == 240
    outer = pruned[3]
    assert 150 <= len(outer[0]) < 240
    true_pts = c + scale * radii[3] * np.column_stack([np.cos(th), np.sin(th)])
    assert np.max(np.abs(sampson_distances(outer[1], true_pts))) < 0.1
    assert np.max(np.abs(sampson_distances(rings[3][1], true_pts))) > 2.0  # as it was


def test_profiles_across_a_diameter_are_kept_clear_of_a_ring_running_beside_it() -> None:
    # An ellipse (a ring seen at a steep tilt) whose flank runs nearly along a vertical line
    # through x = 320 + 58: points on that line 30 px above and below the crossing are far
    # from it along the line, but a horizontal profile through them meets the flank.
    ellipse = np.array([[1 / 60.0**2, 0, 0], [0, 1 / 160.0**2, 0], [0, 0, -1.0]])
    shift = np.array([[1.0, 0, -320.0], [0, 1.0, -240.0], [0, 0, 1.0]])
    conic = shift.T @ ellipse @ shift
    pts = np.array([[378.0, 210.0], [378.0, 270.0], [300.0, 240.0], [378.0, 60.0]])
    clear = _normal_clear_of(conic, pts, np.array([1.0, 0.0]), 8.0)
    np.testing.assert_array_equal(clear, [False, False, True, True])
    # along a vertical profile the same points are clear of the flank but not of the ends
    clear_v = _normal_clear_of(conic, pts, np.array([0.0, 1.0]), 8.0)
    np.testing.assert_array_equal(clear_v, [True, True, True, True])
