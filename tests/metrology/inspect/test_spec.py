"""Inspection specs load, validate once and name the file, line and key of what is wrong."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from metrology.inspect.spec import InspectionRegion, load_inspection_spec
from scanner.core.config import ConfigError, resolve_config

GOOD = """
name = "bracket"
lower_mm = -0.05
upper_mm = 0.08

[[regions]]
name = "top"
normal = [0, 0, 1]
max_angle_deg = 8
upper_mm = 0.03

[[regions]]
name = "boss"
center_mm = [70, 20, 40]
radius_mm = 12

[[sections]]
name = "A-A"
point_mm = [0, 30, 0]
normal = [0, 1, 0]

[alignment]
method = "best_fit"
region = "top"
"""


def test_shipped_default_spec_loads() -> None:
    spec = load_inspection_spec(resolve_config("default", "inspect"))
    assert (spec.lower_mm, spec.upper_mm) == (-0.1, 0.1)
    assert spec.regions == ()


def test_spec_loads_regions_sections_and_bands(tmp_path: Path) -> None:
    path = tmp_path / "s.toml"
    path.write_text(GOOD)
    spec = load_inspection_spec(path)
    top, boss = spec.regions
    assert spec.band_of(top) == (-0.05, 0.03)
    assert spec.band_of(boss) == (-0.05, 0.08)
    assert spec.sections[0].unit_normal().tolist() == [0.0, 1.0, 0.0]
    assert spec.alignment.region == "top"


@pytest.mark.parametrize(
    "change,message",
    [
        (("upper_mm = 0.08", "upper_mm = -0.08"), "upper_mm: expected >= 0"),
        (('region = "top"', 'region = "bottom"'), "alignment.region: unknown region 'bottom'"),
        (('name = "boss"', 'name = "top"'), "duplicate region name 'top'"),
        (("radius_mm = 12", "radius_mm = 12\nnormal = [0, 0, 1]"), "expected one selector"),
        (
            ("max_angle_deg = 8", "max_angle_deg = 120"),
            "max_angle_deg: expected a number in (0, 90]",
        ),
        (
            ('method = "best_fit"', 'method = "rps"'),
            "alignment.method: rps expects three [[alignment.datums]]",
        ),
        (('name = "A-A"', 'name = "A-A"\nthickness_mm = 0'), "thickness_mm: expected a positive"),
    ],
)
def test_bad_spec_names_file_line_and_key(
    tmp_path: Path, change: tuple[str, str], message: str
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(GOOD.replace(*change, 1))
    with pytest.raises(ConfigError) as info:
        load_inspection_spec(path)
    text = str(info.value)
    assert str(path) in text and ", line " in text
    assert message in text


def test_region_selectors_pick_the_right_points() -> None:
    p = np.array([[0.0, 0.0, 0.0], [5.0, 5.0, 5.0], [20.0, 0.0, 0.0]])
    n = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    box = InspectionRegion("b", box_min_mm=(-1, -1, -1), box_max_mm=(6, 6, 6))
    ball = InspectionRegion("s", center_mm=(20, 0, 0), radius_mm=1)
    up = InspectionRegion("u", normal=(0, 0, 2), max_angle_deg=1)
    assert box.select(p, n).tolist() == [True, True, False]
    assert ball.select(p, n).tolist() == [False, False, True]
    assert up.select(p, n).tolist() == [True, False, True]


def test_the_documented_spec_loads(tmp_path: Path) -> None:
    """docs/INSPECT.md's example is a spec that loads (the page does not drift)."""
    doc = Path(__file__).parents[3] / "docs" / "INSPECT.md"
    example = re.search(r"```toml\n(.*?)```", doc.read_text(encoding="utf-8"), re.S)
    assert example is not None
    path = tmp_path / "doc.toml"
    path.write_text(example.group(1))
    spec = load_inspection_spec(path)
    assert spec.alignment.method == "rps"
    assert [d.kind for d in spec.alignment.datums] == ["plane", "line", "point"]
