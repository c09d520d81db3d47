"""Section cuts against the truth: a box cut by a plane is a rectangle of known size, and the
points in the slab are the ones within half its thickness."""

from __future__ import annotations

import numpy as np
import pytest

from metrology.inspect.sections import chain_segments, cut_mesh, cut_section, section_axes
from metrology.inspect.spec import SectionSpec
from scanner.virtual_cell.parts import box_mesh


def _no_points() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool)


@pytest.mark.parametrize(
    ("normal", "u_true", "v_true"),
    [
        ((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
        ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
        ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
        ((0.0, -2.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ],
)
def test_section_axes_read_like_a_drawing(normal, u_true, v_true) -> None:
    u, v = section_axes(np.array(normal))
    np.testing.assert_allclose(u, u_true, atol=1e-12)
    np.testing.assert_allclose(v, v_true, atol=1e-12)


def test_section_axes_are_orthonormal_in_the_plane() -> None:
    rng = np.random.default_rng(3)
    for n in rng.normal(size=(50, 3)):
        u, v = section_axes(n)
        n = n / np.linalg.norm(n)
        basis = np.stack([u, v, n])
        np.testing.assert_allclose(basis @ basis.T, np.eye(3), atol=1e-12)


def test_section_axes_refuse_a_zero_normal() -> None:
    with pytest.raises(ValueError, match="non-zero"):
        section_axes(np.zeros(3))


def test_a_box_cut_across_is_a_closed_rectangle_of_its_size() -> None:
    box = box_mesh((100.0, 60.0, 30.0))
    cut = cut_section(SectionSpec("A-A", (0.0, 30.0, 0.0), (0.0, 1.0, 0.0)), box, *_no_points())
    seg = cut.segments_uv
    assert seg.shape[1:] == (2, 2) and len(seg) >= 4
    np.testing.assert_allclose(seg.reshape(-1, 2).min(axis=0), [0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(seg.reshape(-1, 2).max(axis=0), [100.0, 30.0], atol=1e-9)
    assert cut.profile_length_mm == pytest.approx(2 * (100.0 + 30.0), abs=1e-9)
    # Every end point lies on the rectangle's outline.
    ends = seg.reshape(-1, 2)
    on_outline = np.isclose(ends[:, 0], 0) | np.isclose(ends[:, 0], 100)
    on_outline |= np.isclose(ends[:, 1], 0) | np.isclose(ends[:, 1], 30)
    assert on_outline.all()
    # Chained into one closed loop whose arc length is the perimeter.
    assert len(cut.polylines_uv) == 1
    loop = cut.polylines_uv[0]
    np.testing.assert_allclose(loop[0], loop[-1], atol=1e-9)
    assert cut.polylines_arc_mm[0][-1] == pytest.approx(260.0, abs=1e-9)


def test_a_horizontal_cut_off_the_origin_gives_the_footprint() -> None:
    box = box_mesh((100.0, 60.0, 30.0))
    cut = cut_section(SectionSpec("B-B", (50.0, 30.0, 12.5), (0.0, 0.0, 1.0)), box, *_no_points())
    ends = cut.segments_uv.reshape(-1, 2)
    # (u, v) = (x, y) shifted by the plane's point.
    np.testing.assert_allclose(ends.min(axis=0), [-50.0, -30.0], atol=1e-9)
    np.testing.assert_allclose(ends.max(axis=0), [50.0, 30.0], atol=1e-9)
    assert cut.profile_length_mm == pytest.approx(320.0, abs=1e-9)


def test_an_oblique_cut_has_the_length_of_its_diagonal() -> None:
    box = box_mesh((100.0, 60.0, 30.0))
    # A vertical plane through the footprint's diagonal: a rectangle of height 30 and the
    # diagonal's length.
    normal = np.array([60.0, -100.0, 0.0])
    cut = cut_section(SectionSpec("D", (0.0, 0.0, 0.0), tuple(normal)), box, *_no_points())
    diagonal = float(np.hypot(100.0, 60.0))
    assert cut.profile_length_mm == pytest.approx(2 * (diagonal + 30.0), rel=1e-9)


def test_a_plane_that_misses_the_part_gives_nothing() -> None:
    box = box_mesh()
    rng = np.random.default_rng(1)
    points = rng.uniform(0, 30, (100, 3))
    cut = cut_section(
        SectionSpec("far", (0.0, 0.0, 500.0), (0.0, 0.0, 1.0)),
        box,
        points,
        np.zeros(100),
        np.zeros(100, bool),
    )
    assert cut.segments_uv.shape == (0, 2, 2)
    assert cut.polylines_uv == [] and cut.profile_length_mm == 0.0
    assert cut.point_index.size == 0


def test_the_points_within_half_the_thickness_are_selected() -> None:
    box = box_mesh((100.0, 60.0, 30.0))
    rng = np.random.default_rng(7)
    points = rng.uniform([0, 0, 0], [100, 60, 30], (5000, 3))
    deviation = rng.normal(0.0, 0.05, 5000)
    outlier = rng.random(5000) < 0.05
    section = SectionSpec("A-A", (0.0, 30.0, 0.0), (0.0, 1.0, 0.0), thickness_mm=2.0)
    cut = cut_section(section, box, points, deviation, outlier)
    expected = np.flatnonzero(np.abs(points[:, 1] - 30.0) <= 1.0)
    np.testing.assert_array_equal(cut.point_index, expected)
    np.testing.assert_allclose(cut.points_uv, points[expected][:, [0, 2]], atol=1e-12)
    np.testing.assert_allclose(cut.offset_mm, points[expected, 1] - 30.0, atol=1e-12)
    np.testing.assert_array_equal(cut.deviation_mm, deviation[expected])
    np.testing.assert_array_equal(cut.outlier, outlier[expected])
    assert np.all(np.abs(cut.offset_mm) <= 1.0)


def test_arc_length_follows_the_profile() -> None:
    box = box_mesh((100.0, 60.0, 30.0))
    # Points on the top edge of the A-A rectangle, 10 mm apart along x.
    xs = np.arange(10.0, 91.0, 10.0)
    points = np.column_stack([xs, np.full_like(xs, 30.0), np.full_like(xs, 30.0)])
    section = SectionSpec("A-A", (0.0, 30.0, 0.0), (0.0, 1.0, 0.0))
    cut = cut_section(section, box, points, np.zeros(len(xs)), np.zeros(len(xs), bool))
    step = np.abs(np.diff(cut.arc_mm))
    np.testing.assert_allclose(step, 10.0, atol=0.1)
    assert np.all((cut.arc_mm >= 0) & (cut.arc_mm <= 260.0))


def test_cut_mesh_segments_lie_in_the_plane() -> None:
    box = box_mesh()
    point, normal = np.array([20.0, 10.0, 5.0]), np.array([1.0, 2.0, 3.0])
    seg = cut_mesh(box, point, normal)
    assert len(seg) > 0
    distance = (seg.reshape(-1, 3) - point) @ (normal / np.linalg.norm(normal))
    np.testing.assert_allclose(distance, 0.0, atol=1e-9)


def test_chain_segments_joins_open_chains_and_loops() -> None:
    square = np.array(
        [[[0, 0], [1, 0]], [[1, 1], [1, 0]], [[1, 1], [0, 1]], [[0, 0], [0, 1]]], float
    )
    line = np.array([[[5, 0], [6, 0]], [[6, 0], [6, 2]]], float)
    polylines, arcs = chain_segments(np.concatenate([square, line]), tolerance=1e-9)
    assert [len(p) for p in polylines] == [5, 3]
    np.testing.assert_allclose(polylines[0][0], polylines[0][-1])
    assert arcs[0][-1] == pytest.approx(4.0) and arcs[1][-1] == pytest.approx(7.0)
    assert {tuple(polylines[1][0]), tuple(polylines[1][-1])} == {(5.0, 0.0), (6.0, 2.0)}


def test_cut_section_refuses_mismatched_arrays() -> None:
    with pytest.raises(ValueError, match="deviation_mm"):
        cut_section(
            SectionSpec("A", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
            box_mesh(),
            np.zeros((3, 3)),
            np.zeros(2),
            np.zeros(3, bool),
        )
