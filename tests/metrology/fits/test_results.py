from __future__ import annotations

import json
import math

import numpy as np
import pytest

from metrology.fits.results import CircleFit, CylinderFit, LineFit, PlaneFit, SphereFit


def test_a_failed_fit_is_falsy_and_says_why():
    fit = SphereFit(reason="degenerate: something")
    assert not fit and not fit.ok
    assert fit.to_json() == {"kind": "sphere", "ok": False, "reason": "degenerate: something"}
    assert math.isnan(fit.diameter_mm)


@pytest.mark.parametrize(
    ("fit", "keys"),
    [
        (PlaneFit(), ["normal", "d_mm", "centroid_mm", "normal_std", "d_std_mm"]),
        (SphereFit(), ["center_mm", "radius_mm", "diameter_mm", "center_std_mm", "radius_std_mm"]),
        (
            CylinderFit(),
            ["axis", "point_mm", "radius_mm", "diameter_mm", "axis_std", "point_std_mm",
             "radius_std_mm"],
        ),
        (
            CircleFit(),
            ["center_mm", "normal", "radius_mm", "diameter_mm", "center_std_mm", "normal_std",
             "radius_std_mm"],
        ),
        (LineFit(), ["point_mm", "direction", "point_std_mm", "direction_std"]),
    ],
)  # fmt: skip
def test_json_lists_the_parameters_in_order_and_has_no_nan(fit, keys):
    data = fit.to_json()
    assert list(data) == ["kind", "ok", *keys, "n_points", "n_inliers", "rms_mm", "range_mm"]
    json.dumps(data, allow_nan=False)
    assert data["ok"] is True and all(data[k] in (None, [None] * 3) for k in keys)  # NaN: null


def test_json_adds_the_minimum_zone_when_there_is_one():
    fit = PlaneFit(
        normal=np.array([0.0, 0, 1]), d_mm=1.0, rms_mm=0.1, range_mm=0.4, min_zone_mm=0.3
    )
    data = fit.to_json()
    assert data["normal"] == [0.0, 0.0, 1.0] and data["d_mm"] == 1.0
    assert data["min_zone_mm"] == 0.3 and data["d_std_mm"] is None


def test_signed_distances():
    p = np.array([[0.0, 0.0, 3.0], [2.0, 0.0, 0.0]])
    plane = PlaneFit(normal=np.array([0.0, 0, 1]), d_mm=-1.0)
    assert np.allclose(plane.signed_distance(p), [2.0, -1.0])
    sphere = SphereFit(center_mm=np.zeros(3), radius_mm=1.0)
    assert np.allclose(sphere.signed_distance(p), [2.0, 1.0]) and sphere.diameter_mm == 2.0
    cyl = CylinderFit(axis=np.array([0.0, 0, 1]), point_mm=np.zeros(3), radius_mm=1.0)
    assert np.allclose(cyl.signed_distance(p), [-1.0, 1.0])
    circle = CircleFit(center_mm=np.zeros(3), normal=np.array([0.0, 0, 1]), radius_mm=1.0)
    assert np.allclose(circle.signed_distance(p), [-1.0, 1.0])
    assert np.allclose(circle.distance(p), [np.hypot(3.0, 1.0), 1.0])
    line = LineFit(point_mm=np.zeros(3), direction=np.array([1.0, 0, 0]))
    assert np.allclose(line.signed_distance(p), [3.0, 0.0])
