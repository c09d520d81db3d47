"""Views without the orientation marker: relabelled by a quarter turn, resolved by the robot."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.detection.observations import TargetObservation
from calibration.pipeline import calibrate_session
from calibration.symmetry import relabel, resolve_quarter_turns, turn
from scanner.core.conventions import angle_between_rotations_deg, make_transform
from scanner.core.targets import ConcentricCirclesTarget, OrientationMarker
from scanner.formats.session import Frame, Session
from tests.calibration._observations import (
    DIST_TRUE,
    K_TRUE,
    RADII,
    SIZE,
    poses,
    project,
    synthetic_observation,
)

TARGET = ConcentricCirclesTarget(
    ring_diameters_mm=tuple(float(2 * r) for r in RADII),
    line_width_mm=0.6,
    orientation_marker=OrientationMarker(diameter_mm=6.0, center_mm=(66.0, 0.0)),
)


def _named(obs: TargetObservation) -> TargetObservation:
    """The synthetic observation with the detector's point names."""
    names = ["O"]
    for k in range(len(RADII)):
        names += [f"r{k}+x", f"r{k}-x", f"r{k}+y", f"r{k}-y"]
    return dataclasses.replace(obs, point_names=names)


def _marker_less(obs: TargetObservation, quarter_turns: int) -> TargetObservation:
    """What the detector reports without the marker: labels turned by ``quarter_turns``."""
    return dataclasses.replace(relabel(obs, -quarter_turns), labelling="symmetry")


@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_relabel_undoes_a_quarter_turn_of_the_labels(k: int) -> None:
    rng = np.random.default_rng(k)
    T = poses(1, rng)[0]
    obs = _named(synthetic_observation(T, K_TRUE, DIST_TRUE, rng, 0.0))
    found = _marker_less(obs, k)
    if k:
        assert not np.allclose(found.points_target, obs.points_target)
    # The module's convention, checked through the camera rather than through relabel
    # itself: the found labels are seen where cam_from_true @ turn(-k) puts them.
    seen = project(T @ turn(-k), found.points_target, K_TRUE, DIST_TRUE)
    np.testing.assert_allclose(seen, obs.points_px, atol=1e-6)
    back = relabel(found, k)
    np.testing.assert_allclose(back.points_target, obs.points_target, atol=1e-9)
    assert back.point_names == obs.point_names
    for name in "OABCD":
        np.testing.assert_allclose(back.named_px[name], obs.named_px[name])
    assert [a.axis for a in back.axis_points] == ["x", "y"]
    np.testing.assert_allclose(back.axis_points[0].points_px, obs.axis_points[0].points_px)
    assert back.labelling == "unique"


@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_the_quarter_turn_closest_to_the_prediction_wins(k: int) -> None:
    rng = np.random.default_rng(10 + k)
    cam_from_true = make_transform(Rotation.random(random_state=k), rng.normal(0, 100, 3))
    found = cam_from_true @ turn(-k)
    wobble = make_transform(Rotation.from_rotvec(rng.normal(0, np.radians(3), 3)), np.zeros(3))
    q = resolve_quarter_turns(found, wobble @ cam_from_true)
    assert q and q.quarter_turns == k and q.angle_deg < 10
    # A prediction half-way between two turns decides nothing.
    half = make_transform(Rotation.from_euler("z", 45, degrees=True), np.zeros(3))
    assert not resolve_quarter_turns(found, cam_from_true @ half)


def _session(tmp_path: Path, n: int, marker_less: dict[int, int], seed: int):
    """A camera-only session of ``n`` posed views (images never read: the observations are
    given) and its truth; views in ``marker_less`` are labelled turned by their value."""
    rng = np.random.default_rng(seed)
    flange_from_cam = make_transform(
        Rotation.from_euler("xyz", [2, -3, 91], degrees=True), [40, -5, 90]
    )
    base_from_target = make_transform(Rotation.from_euler("x", 180, degrees=True), [700, 50, 20])
    frames, observations = [], {}
    for i, cam_from_target in enumerate(poses(n, rng)):
        base_from_flange = base_from_target @ np.linalg.inv(flange_from_cam @ cam_from_target)
        frames.append(Frame(i, tmp_path / f"t{i}.png", None, base_from_flange))
        obs = _named(synthetic_observation(cam_from_target, K_TRUE, DIST_TRUE, rng, 0.05))
        observations[i] = _marker_less(obs, marker_less[i]) if i in marker_less else obs
    session = Session(tmp_path, "calibration", SIZE[0], SIZE[1], frames, target=TARGET)
    return session, observations, flange_from_cam


def test_views_without_the_marker_are_all_used(tmp_path: Path) -> None:
    """Issue #15 item 2: a 20-view session with 5 marker-less views uses all 20."""
    marker_less = {2: 1, 5: 2, 9: 3, 13: 1, 17: 3}
    session, observations, flange_from_cam = _session(tmp_path, 20, marker_less, seed=3)
    result = calibrate_session(session, observations=observations, progress=False)
    labelling = result.calibration.quality.record["labelling"]
    assert labelling["symmetry"] == sorted(marker_less)
    assert {int(i): r["quarter_turns"] for i, r in labelling["resolved"].items()} == marker_less
    assert labelling["unresolved"] == {}
    assert sorted(v.frame_id for v in result.hand_eye_views) == list(range(20))
    assert sorted(result.intrinsics.view_indices) == list(range(20))
    # The same hand-eye as when every view shows its marker, and near the truth.
    session, observations, _ = _session(tmp_path, 20, {}, seed=3)
    every = calibrate_session(session, observations=observations, progress=False)
    found = result.calibration.flange_from_cam
    assert angle_between_rotations_deg(found, every.calibration.flange_from_cam) < 1e-5
    assert angle_between_rotations_deg(found, flange_from_cam) < 0.02
    assert np.linalg.norm(found[:3, 3] - flange_from_cam[:3, 3]) < 0.1
