"""Ring conics named by their sizes when the rays' labels are off; ring points cut back to
where the other rings' pencil puts them; the fine stage's spline over a window."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from calibration.detection.concentric_rings import (
    SPLINE_WINDOW_GUARD_PX,
    _nested_rings,
    _prune_by_pencil,
    _relabel_by_ratios,
    concentric_affine_conics,
    spline_window,
)
from calibration.detection.conics import fit_conic, pencil_center, sampson_distances
from calibration.detection.profile_kernels import spline_along


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


def _ellipse(a_px: float, b_px: float, centre=(320.0, 240.0)) -> np.ndarray:
    cx, cy = centre
    return np.array(
        [
            [1 / a_px**2, 0, -cx / a_px**2],
            [0, 1 / b_px**2, -cy / b_px**2],
            [-cx / a_px**2, -cy / b_px**2, cx**2 / a_px**2 + cy**2 / b_px**2 - 1],
        ]
    )


def test_a_conic_crossing_the_others_is_dropped_and_nested_ones_kept() -> None:
    c = np.array([320.0, 240.0])
    rings = {k: _circle(20.0 * (k + 1)) for k in range(5)}
    assert sorted(_nested_rings(rings, c)) == [0, 1, 2, 3, 4]
    # Ring 2 fitted to a flat arc: 25 px across one way, 85 px the other, crossing 1 and 3.
    crossed = dict(rings)
    crossed[2] = _ellipse(85.0, 25.0)
    kept = _nested_rings(crossed, c)
    assert sorted(kept) == [0, 1, 3, 4]
    for k in kept:
        np.testing.assert_array_equal(kept[k], rings[k])
    # two conics crossing only each other, as deep as each other: the inner one goes
    tied = {0: _circle(20.0), 1: _ellipse(45.0, 35.0), 2: _ellipse(35.0, 45.0)}
    assert sorted(_nested_rings(tied, c)) == [0, 2]


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


def test_the_spline_window_gives_the_whole_images_values_around_the_rings() -> None:
    rng = np.random.default_rng(35)
    d = rng.random((480, 640))
    c = np.array([300.0, 200.0])
    # the largest ring's label need not be the highest: every conic counts
    rings = [_circle(90.0, centre=(300.0, 200.0)), _circle(40.0, centre=(300.0, 200.0))]
    reach = 20.0
    win = spline_window(d, rings, c, reach)
    u0, v0 = win.origin_px
    h, w = win.coef.shape
    g = SPLINE_WINDOW_GUARD_PX
    # the box holds the rings, the reach and the guard, and is far from the whole image
    assert u0 <= 300 - 90 - reach - g and v0 <= 200 - 90 - reach - g
    assert u0 + w >= 300 + 90 + reach + g and v0 + h >= 200 + 90 + reach + g
    assert w * h < 0.4 * d.size
    whole = ndimage.spline_filter(d, order=3)
    # profiles across the ring reaching ``reach`` out: the window's values, to the last bit
    angle = rng.uniform(0, 2 * np.pi, 400)
    normals = np.column_stack([np.cos(angle), np.sin(angle)])
    points = c + 90.0 * normals
    tau = np.arange(-reach, reach + 0.0625, 0.125)
    coef, origin = win.covering(points, normals, reach)
    assert coef is win.coef and win.whole is None
    want = spline_along(whole, points, normals, tau)
    np.testing.assert_array_equal(spline_along(coef, points, normals, tau, origin), want)
    # ... and a profile reaching into the guard is sampled on the whole map's spline
    far = c + 160.0 * normals
    coef, origin = win.covering(far, normals, reach)
    assert origin == (0, 0) and win.whole is not None
    want = spline_along(whole, far, normals, tau)
    np.testing.assert_array_equal(spline_along(coef, far, normals, tau, origin), want)


def test_the_spline_window_is_clipped_to_the_image_or_is_all_of_it() -> None:
    d = np.random.default_rng(36).random((200, 300))
    near_corner = spline_window(d, [_circle(50.0, centre=(20.0, 30.0))], np.array([20.0, 30.0]), 5)
    assert near_corner.origin_px == (0, 0)
    assert near_corner.coef.shape[0] < 200 and near_corner.coef.shape[1] < 300
    # a conic that does not close around the point (a hyperbola): the whole image
    hyperbola = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -100.0]])
    whole = spline_window(d, [hyperbola], np.array([150.0, 100.0]), 5.0)
    assert whole.origin_px == (0, 0) and whole.coef.shape == d.shape


def _rings_on_arcs(
    rng: np.random.Generator, radii: np.ndarray, arc: tuple[float, float], noise_px: float
) -> tuple[dict[int, np.ndarray], np.ndarray, np.ndarray]:
    """Points of each ring over ``arc`` (rad) through a mildly perspective homography (a
    small target seen 12 deg tilted), with noise; the homography and the image of O."""
    r = np.radians(12.0)
    rot = np.array([[1.0, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    k = np.array([[1200.0, 0, 640], [0, 1200.0, 512], [0, 0, 1]])
    image_from_target = k @ np.column_stack([rot[:, 0], rot[:, 1], [30.0, -20.0, 1500.0]])
    points = {}
    for i, radius in enumerate(radii):
        a = rng.uniform(*arc, 40)
        q = np.column_stack([radius * np.cos(a), radius * np.sin(a), np.ones_like(a)])
        p = q @ image_from_target.T
        points[i] = p[:, :2] / p[:, 2:] + rng.normal(0.0, noise_px, (40, 2))
    o = image_from_target[:, 2]
    return points, image_from_target, o[:2] / o[2]


def test_rings_seen_over_short_arcs_give_their_conics_together() -> None:
    # Each ring over 100 deg only (a stripe over the centre hides the rest): the joint fit
    # gives every ring's conic to a fraction of a pixel over the arc, and well within the
    # fine stage's reach (a quarter of the 12 px ring spacing) around the whole ring.
    rng = np.random.default_rng(3)
    radii = np.array([20.0, 35.0, 50.0, 65.0, 80.0])
    arc = (0.2, 0.2 + np.radians(100))
    points, image_from_target, o = _rings_on_arcs(rng, radii, arc, 0.3)
    # (the rays' origin a little off O, as a Hough crossing is)
    joint = concentric_affine_conics(points, radii, o + np.array([1.5, -1.0]), 1.5)
    assert joint is not None
    conics, centre = joint
    assert sorted(conics) == [0, 1, 2, 3, 4]
    assert np.linalg.norm(centre - o) < 1.0
    a = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    on_arc = (a >= arc[0]) & (a <= arc[1])
    for i, radius in enumerate(radii):
        q = np.column_stack([radius * np.cos(a), radius * np.sin(a), np.ones_like(a)])
        p = q @ image_from_target.T
        dist = np.abs(sampson_distances(conics[i], p[:, :2] / p[:, 2:]))
        assert np.max(dist[on_arc]) < 0.5
        assert np.max(dist) < 0.25 * 12.0
    pencil, ratio = pencil_center(conics[0], conics[4])
    np.testing.assert_allclose(pencil[:2], centre, atol=1e-6)
    assert abs(ratio / (radii[4] / radii[0]) ** 2 - 1) < 1e-6  # the spec's pencil


def test_rings_labelled_one_off_do_not_fit_together() -> None:
    # Rings 1-4 named 0-3 (the innermost lost under a stripe): concentric ellipses of one
    # shape cannot take radii whose ratios are not the printed ones.
    rng = np.random.default_rng(4)
    radii = np.array([20.0, 35.0, 50.0, 65.0, 80.0])
    points, _, o = _rings_on_arcs(rng, radii, (0.2, 0.2 + np.radians(100)), 0.3)
    assert concentric_affine_conics(points, radii, o, 1.5) is not None
    shifted = {k - 1: points[k] for k in range(1, 5)}
    assert concentric_affine_conics(shifted, radii, o, 1.5) is None


def test_a_few_mislabelled_rays_are_outvoted_and_many_refuse_the_joint_fit() -> None:
    rng = np.random.default_rng(6)
    radii = np.array([20.0, 35.0, 50.0, 65.0, 80.0])
    arc = (0.2, 0.2 + np.radians(100))
    points, image_from_target, o = _rings_on_arcs(rng, radii, arc, 0.3)

    def shifted(share: float) -> dict[int, np.ndarray]:
        # that share of each ring's points taken from the next ring out (a ray one ring off)
        n = int(share * 40)
        return {k: np.vstack([points[k + 1][:n], points[k][n:]]) for k in range(4)}

    few = concentric_affine_conics(shifted(0.05), radii, o, 1.5)
    assert few is not None
    a = np.linspace(*arc, 50)
    for k in range(4):
        q = np.column_stack([radii[k] * np.cos(a), radii[k] * np.sin(a), np.ones_like(a)])
        p = q @ image_from_target.T
        assert np.max(np.abs(sampson_distances(few[0][k], p[:, :2] / p[:, 2:]))) < 0.5
    assert concentric_affine_conics(shifted(0.3), radii, o, 1.5) is None


def test_too_few_points_give_no_joint_conics() -> None:
    rng = np.random.default_rng(5)
    radii = np.array([20.0, 35.0, 50.0])
    points, _, o = _rings_on_arcs(rng, radii, (0.0, 1.0), 0.3)
    assert concentric_affine_conics({0: points[0]}, radii, o, 1.5) is None
    assert concentric_affine_conics({k: v[:5] for k, v in points.items()}, radii, o, 1.5) is None
    points[1][3] = np.nan
    assert concentric_affine_conics(points, radii, o, 1.5) is None
