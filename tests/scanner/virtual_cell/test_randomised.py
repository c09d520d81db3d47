import numpy as np

from scanner.virtual_cell.randomised import (
    draw_conditions,
    paper_dark_surroundings,
    render_view,
)


def test_same_seed_draws_and_renders_the_same_view():
    a = render_view(draw_conditions(np.random.default_rng(5)), np.random.default_rng(6))
    b = render_view(draw_conditions(np.random.default_rng(5)), np.random.default_rng(6))
    assert a.conditions == b.conditions
    assert np.array_equal(a.image, b.image)


def test_target_centre_projects_where_the_conditions_put_it():
    for seed in range(5):
        rng = np.random.default_rng(seed)
        v = render_view(draw_conditions(rng), rng)
        pc = v.cam_from_target[:3, 3]
        uv = (v.K @ pc)[:2] / pc[2]
        assert np.allclose(uv, v.center_px, atol=1e-9)
        assert np.allclose(v.center_px, v.conditions.centre_px, atol=1e-6)


def test_truth_ring_crossings_lie_on_printed_ink():
    c = paper_dark_surroundings(noise_grey=0.5)
    v = render_view(c, np.random.default_rng(0))
    img = v.image.astype(float)
    inside = [p for n, p in zip(v.point_names, v.points_px) if n != "O" and 2 < p[0] < c.width - 3]
    ink = np.array([img[round(p[1]), round(p[0])] for p in inside])
    # Paper ~190, ink ~30 (0.6 mm line ~1.9 px, blurred): every crossing is well below paper.
    assert len(inside) == 4 * 14
    assert ink.max() < 0.7 * c.paper_grey
    # Half a ring spacing out of ring 0, off the diameters (45 deg), is paper.
    r = v.spec.ring_radii_mm[0] + 2.0
    H = v.K @ v.cam_from_target[:3, [0, 1, 3]]
    q = H @ np.array([r / np.sqrt(2), r / np.sqrt(2), 1.0])
    assert img[round(q[1] / q[2]), round(q[0] / q[2])] > 0.8 * c.paper_grey


def test_view_with_centre_outside_is_not_detectable():
    rng = np.random.default_rng(1)
    c = draw_conditions(rng)
    c = type(c)(**{**c.__dict__, "centre_px": (-50.0, c.height / 2)})
    v = render_view(c, rng)
    assert not v.detectable
    assert "centre" in v.why_not


def test_target_free_view_is_not_detectable():
    rng = np.random.default_rng(2)
    v = render_view(draw_conditions(rng, has_target=False), rng)
    assert not v.detectable
    assert v.surround_frac == 1.0
