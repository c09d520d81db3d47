"""Ring conics named by their sizes when the rays' labels are off; a diameter's evidence."""

from __future__ import annotations

import cv2
import numpy as np

from calibration.detection.concentric_rings import (
    _line_evidence,
    _pencil_centre,
    _relabel_by_ratios,
)


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


def test_a_printed_diameter_shows_evidence_and_any_other_line_through_o_none() -> None:
    # thick rings 13 px apart (they fill much of any line) and one printed diameter along x
    d = np.zeros((480, 640))
    c = np.array([320.0, 240.0])
    for r in (26, 39, 52, 65, 78):
        cv2.circle(d, (320, 240), r, 0.6, 4)
    cv2.line(d, (242, 240), (398, 240), 0.6, 4)
    d = cv2.GaussianBlur(d, (0, 0), 1.0)
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
