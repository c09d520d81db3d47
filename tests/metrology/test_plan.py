from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from metrology.acceptance import load_acceptance_spec
from metrology.plan import MeasurementSpec, Region, load_plan
from scanner.core.config import CONFIG_DIR, ConfigError

PLANS = sorted((CONFIG_DIR / "plans").glob("*_sweep.toml"))
SPECS = sorted((CONFIG_DIR / "plans").glob("acceptance_*.toml"))

#: A valid plan: three features (two spheres, a plane) and two measurements between them.
GOOD = (Path(__file__).parent / "good_plan.toml").read_text(encoding="utf-8")


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "plan.toml"
    p.write_text(text, encoding="utf-8")
    return p


def line_of(text: str, needle: str, occurrence: int = 1) -> int:
    lines = [i + 1 for i, line in enumerate(text.splitlines()) if needle in line]
    return lines[occurrence - 1]


@pytest.mark.parametrize("path", PLANS, ids=lambda p: p.name)
def test_shipped_plans_load(path: Path):
    plan = load_plan(path)
    assert plan.features and plan.measurements
    assert plan.cell in ("paper", "modern")


@pytest.mark.parametrize("path", SPECS, ids=lambda p: p.name)
def test_shipped_acceptance_specs_load(path: Path):
    spec = load_acceptance_spec(path)
    assert spec.calibrated_distance_mm == 100.0
    assert [s.calibrated_diameter_mm for s in spec.spheres] == [25.4, 25.4]


def test_shipped_plans_match_their_cells():
    """The plan's sphere nominals are the cell's sphere centres (the cell file is the truth)."""
    from scanner.core.config import load_toml

    for path in PLANS:
        plan = load_plan(path)
        cell = load_toml(CONFIG_DIR / "cells" / f"{plan.cell}.toml")
        spheres = {o["id"]: o for o in cell["sweep"]["objects"] if o["type"] == "sphere"}
        for f in plan.features:
            if f.kind == "sphere":
                assert list(f.nominal.center_mm) == spheres[f.name]["center_mm"]
                assert f.nominal.diameter_mm == spheres[f.name]["diameter_mm"]


def test_good_plan_loads_with_defaults_and_bounds(tmp_path: Path):
    plan = load_plan(write(tmp_path, GOOD))
    assert [f.name for f in plan.features] == ["a", "b", "floor"]
    assert plan.threshold_for(plan.feature("a")) == 0.2
    assert plan.threshold_for(plan.feature("floor")) is None  # 0 turns RANSAC off
    spacing, height = plan.measurements
    assert spacing.bounds == (-0.1, 0.1)
    assert height.bounds == (-0.05, 0.1)
    assert spacing.unit == "mm"


def test_form_tolerance_is_one_sided():
    m = MeasurementSpec(name="f", type="flatness", features=("p",), tolerance=0.05)
    assert m.bounds == (None, 0.05)
    assert m.nominal_value == 0.0
    assert MeasurementSpec(name="a", type="angle", features=("p", "q"), tolerance=0.1).unit == "deg"


@pytest.mark.parametrize(
    ("old", "new", "key", "words", "anchor"),
    [
        ('features = ["a", "b"]', 'features = ["a", "c"]', "measurements[0].features",
         "unknown feature 'c'", ('features = ["a", "c"]', 1)),
        ('kind = "plane"', 'kind = "plain"', "features[2].kind", "expected one of", ('kind = "plain"', 1)),
        ("radius_mm = 20.0 }\n\n[[features]]\nname = \"floor\"",
         "radius_mm = -1.0 }\n\n[[features]]\nname = \"floor\"",
         "features[1].region.radius_mm", "expected a positive number", ("radius_mm = -1.0", 1)),
        ("box_max_mm = [150.0, 50.0, -10.0]", "box_max_mm = [150.0, 50.0, -30.0]",
         "features[2].region.box_max_mm", "above box_min_mm", ("box_max_mm", 1)),
        ("lower = -0.05", "lower = -0.05\ntolerance = 0.1", "measurements[1].tolerance",
         "either tolerance or lower/upper", ("tolerance = 0.1", 2)),
        ('type = "distance"\nfeatures = ["a", "b"]', 'type = "diameter"\nfeatures = ["floor"]',
         "measurements[0].features", "a diameter needs a sphere", ('features = ["floor"]', 1)),
        ("nominal = 15.0", "nominal = 15.0\ncolour = 3", "measurements[1].colour", "unknown key",
         ("colour = 3", 1)),
        ("nominal = { diameter_mm = 25.4 }", "nominal = { diameter_mm = 'big' }",
         "features[0].nominal.diameter_mm", "expected a number", ("diameter_mm = 'big'", 1)),
        ("nominal = 15.0", "nominal = 1e308", "measurements[1].nominal",
         "expected a finite number within", ("nominal = 1e308", 1)),
        ("lower = -0.05", "lower = -inf", "measurements[1].lower",
         "expected a finite number, got -inf", ("lower = -inf", 1)),
    ],
)  # fmt: skip
def test_errors_name_file_line_and_key(tmp_path: Path, old, new, key, words, anchor):
    assert old in GOOD
    text = GOOD.replace(old, new, 1)
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_plan(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}, line {line_of(text, *anchor)}: {key}: "), msg
    assert words in msg
    assert "\n" not in msg


def test_region_needs_one_shape(tmp_path: Path):
    text = GOOD.replace(
        "region = { seed_mm = [0.0, 0.0, 0.0], radius_mm = 20.0 }",
        "region = { seed_mm = [0.0, 0.0, 0.0], radius_mm = 20.0, box_min_mm = [0, 0, 0] }",
    )
    with pytest.raises(ConfigError, match=re.escape("features[0].region: expected either")):
        load_plan(write(tmp_path, text))


def test_duplicate_names_and_missing_file(tmp_path: Path):
    text = GOOD.replace('name = "b"', 'name = "a"')
    with pytest.raises(ConfigError, match=r"features\[1\]\.name: duplicate feature name 'a'"):
        load_plan(write(tmp_path, text))
    with pytest.raises(ValueError, match="cannot read config"):
        load_plan(tmp_path / "nope.toml")


def test_region_selects_box_and_ball():
    pts = np.array([[0.0, 0, 0], [5, 0, 0], [11, 0, 0], [3, 4, 0.5]])
    ball = Region(seed_mm=(0.0, 0.0, 0.0), radius_mm=5.0)
    assert ball.select(pts).tolist() == [True, True, False, False]
    box = Region(box_min_mm=(-1.0, -1.0, -1.0), box_max_mm=(6.0, 5.0, 1.0))
    assert box.select(pts).tolist() == [True, True, False, True]
    with pytest.raises(ValueError, match="either box_min_mm"):
        Region()
