"""The inspection report: one self-contained page with the verdict, regions, sections, the
pictures and the interactive viewer."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from metrology.inspect.inspect import judge_regions
from metrology.inspect.report import (
    OUTLIER_RGB,
    colour_limit,
    deviation_colours,
    inspection_html,
    write_inspection_report,
)
from metrology.inspect.result import AlignmentResult, InspectionResult, InspectionUncertainty
from metrology.inspect.spec import InspectionRegion, InspectionSpec, SectionSpec
from metrology.inspect.surface import NominalSurface
from metrology.inspect.viewer import cloud_viewer_html, feature_edges, project
from scanner.virtual_cell.parts import box_mesh

BUMP_CENTRE = np.array([30.0, 30.0, 30.0])


def _result(count: int = 20_000, seed: int = 5) -> InspectionResult:
    """A 100 x 60 x 30 box scanned with a 0.15 mm bump on its top, strays, identity pose."""
    mesh = box_mesh((100.0, 60.0, 30.0))
    rng = np.random.default_rng(seed)
    surface = NominalSurface(mesh)
    p, n = surface.sample(count, rng)
    bump = 0.15 * np.exp(-np.sum((p - BUMP_CENTRE) ** 2, axis=1) / (2 * 4.0**2))
    deviation = bump + rng.normal(0.0, 0.01, count)
    stray = rng.random(count) < 0.002
    deviation[stray] += rng.uniform(1.5, 3.0, np.count_nonzero(stray))
    points = p + n * deviation[:, None]
    spec = InspectionSpec(
        name="test box",
        regions=(
            InspectionRegion("top face", normal=(0.0, 0.0, 1.0), max_angle_deg=5.0),
            InspectionRegion(
                "bump area", center_mm=(30.0, 30.0, 30.0), radius_mm=6.0, upper_mm=0.05
            ),
        ),
        sections=(
            SectionSpec("A-A", (0.0, 30.0, 0.0), (0.0, 1.0, 0.0), thickness_mm=1.0),
            SectionSpec("B-B", (30.0, 0.0, 0.0), (1.0, 0.0, 0.0), thickness_mm=1.0),
        ),
    )
    outlier = np.abs(deviation) > spec.outlier_limit_mm
    regions = judge_regions(spec, points, n, deviation, outlier)
    alignment = AlignmentResult(
        nominal_from_cloud=np.eye(4), method="identity (test)", rms_mm=0.01,
        points_used=count, iterations=0, converged=True, pose_u_mm=0.001,
        covariance=np.eye(6) * 1e-8, warnings=("a test warning",),
    )  # fmt: skip
    return InspectionResult(
        nominal=mesh, spec=spec, alignment=alignment, points_nominal=points,
        deviation_mm=deviation, outlier=outlier, face_normals=n, stats=regions[0].stats,
        regions=regions, uncertainty=InspectionUncertainty(0.01, 0.001, 0.01005),
        verdict="fail" if any(r.status == "fail" for r in regions) else "pass",
        nominal_path="box.stl", cloud_path="", spec_path="box.toml",
        seconds={"align": 1.0, "deviations": 0.5},
    )  # fmt: skip


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> tuple[InspectionResult, Path, str]:
    result = _result()
    path = write_inspection_report(result, tmp_path_factory.mktemp("report") / "inspect.html")
    return result, path, path.read_text(encoding="utf-8")


def test_the_report_is_written_and_self_contained(report) -> None:
    _, path, text = report
    assert path.is_file() and text.startswith("<!DOCTYPE html>")
    assert not re.search(r"""(src|href)\s*=\s*["']?\s*(https?:)?//""", text, re.IGNORECASE)
    assert "<link" not in text.lower()
    assert "@import" not in text
    for tag in re.findall(r"<script[^>]*>", text):
        assert "src" not in tag


def test_the_report_shows_verdict_regions_and_sections(report) -> None:
    result, _, text = report
    assert result.verdict == "fail"  # the bump area's own band ends at +0.05 mm
    assert 'class="summary fail"' in text and "FAIL" in text
    assert "2 of 3 regions pass" in text
    for name in ("all", "top face", "bump area", "A-A", "B-B"):
        assert name in text
    assert "a test warning" in text
    assert "identity (test)" in text


def test_the_report_embeds_the_viewer_and_the_pictures(report) -> None:
    _, _, text = report
    assert "<canvas" in text and 'id="inspect-viewer"' in text
    assert text.count("data:image/png;base64,") >= 5  # picture, views, histogram, 2 sections


def test_a_passing_result_says_pass(tmp_path) -> None:
    result = _result(count=5_000)
    regions = [r for r in result.regions if r.name != "bump area"]
    result.regions = regions
    result.verdict = "pass"
    text = inspection_html(result)
    assert 'class="summary pass"' in text and "2 of 2 regions pass" in text


def test_deviation_colours_are_diverging_and_outliers_grey() -> None:
    limit = colour_limit(-0.1, 0.1)
    assert limit == pytest.approx(0.2)
    rgb = deviation_colours(np.array([-1.0, 0.0, 1.0, 0.0]), np.array([0, 0, 0, 1], bool), limit)
    assert rgb.dtype == np.uint8 and rgb.shape == (4, 3)
    assert rgb[0, 2] > rgb[0, 0]  # below: blue
    assert rgb[2, 0] > rgb[2, 2]  # above: red
    assert np.all(rgb[1] > 230)  # on the nominal: nearly white
    assert tuple(rgb[3]) == OUTLIER_RGB


def test_the_viewer_subsamples_big_clouds() -> None:
    rng = np.random.default_rng(2)
    n = 100_000
    text = cloud_viewer_html(
        rng.random((n, 3)), np.zeros(n), np.zeros((n, 3), np.uint8), np.zeros(n, bool),
        np.zeros((0, 2, 3)), max_points=1_000,
    )  # fmt: skip
    assert "1\u2009000 of 100\u2009000 points" in text
    assert "</script>" in text and text.count("<script>") == 1


def test_the_viewer_refuses_mismatched_arrays() -> None:
    with pytest.raises(ValueError, match="colours"):
        cloud_viewer_html(
            np.zeros((3, 3)), np.zeros(3), np.zeros((2, 3)), np.zeros(3, bool), np.zeros((0, 2, 3))
        )


def test_feature_edges_of_a_box_are_its_twelve_edges() -> None:
    edges = feature_edges(box_mesh((100.0, 60.0, 30.0)))
    assert edges.shape == (12, 2, 3)
    lengths = np.sort(np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1))
    np.testing.assert_allclose(lengths, [30] * 4 + [60] * 4 + [100] * 4)


def test_named_views_look_where_they_say() -> None:
    up = np.array([[0.0, 0.0, 1.0]])
    x, y = np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]])
    np.testing.assert_allclose(project(up, 0.0, 90.0), [[0, 0, 1]], atol=1e-12)  # top: z at eye
    np.testing.assert_allclose(project(y, 0.0, 90.0), [[0, 1, 0]], atol=1e-12)  # y up on screen
    np.testing.assert_allclose(project(up, 0.0, 0.0), [[0, 1, 0]], atol=1e-12)  # front: z up
    np.testing.assert_allclose(project(x, -90.0, 0.0), [[0, 0, 1]], atol=1e-12)  # side: from +x
