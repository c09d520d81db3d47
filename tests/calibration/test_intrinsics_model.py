"""The distortion model is chosen by the data, and the projection uncertainty is mapped."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from calibration import intrinsics_model
from calibration.intrinsics import IntrinsicsResult, calibrate_intrinsics
from scanner.core.conventions import make_transform
from tests.calibration._observations import (
    DIST_TRUE,
    K_TRUE,
    SIZE,
    poses,
    project,
    synthetic_observation,
)
from tests.cancelling import CancelAt, Cancelled


def model_error_px(res: IntrinsicsResult, dist_true: np.ndarray) -> tuple[float, float]:
    """Largest distance over the image between the true and the estimated camera model's
    projections of the same rays: as they are, and after the best small turn of the camera
    frame (a turn every pose absorbs, as mrcal compares models)."""
    uu, vv = np.meshgrid(np.arange(0, SIZE[0], 32), np.arange(0, SIZE[1], 32))
    uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(float)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    xy = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), K_TRUE, dist_true, None, None, criteria)
    rays = np.column_stack([xy.reshape(-1, 2), np.ones(len(uv))])

    def gap(w: np.ndarray) -> np.ndarray:
        turn = make_transform(Rotation.from_rotvec(w), np.zeros(3))
        return (project(turn, rays, res.K, res.dist) - uv).ravel()

    plain = np.linalg.norm(gap(np.zeros(3)).reshape(-1, 2), axis=1).max()
    turned = np.linalg.norm(least_squares(gap, np.zeros(3)).fun.reshape(-1, 2), axis=1).max()
    return float(plain), float(turned)


@pytest.mark.parametrize("seed", [0, 2])
def test_a_distortion_free_lens_with_eight_views_gets_no_distortion_terms(seed: int) -> None:
    rng = np.random.default_rng(seed)
    obs = [synthetic_observation(T, K_TRUE, np.zeros(5), rng, 0.1) for T in poses(8, rng)]
    auto = calibrate_intrinsics(obs, SIZE)
    full = calibrate_intrinsics(obs, SIZE, distortion="full")
    assert auto.distortion_model == "none"
    assert np.all(auto.dist == 0.0)
    assert auto.model_selection is not None and auto.model_selection.folds == 3
    # Five terms fitted to eight views wander where no view looked; none stay within 0.2 px.
    assert model_error_px(auto, np.zeros(5))[1] < 0.2
    assert model_error_px(full, np.zeros(5))[0] > 3 * model_error_px(auto, np.zeros(5))[0]
    # The map says so: the full model's projection is far less certain.
    assert full.uncertainty_map.max_px > 1.2 * auto.uncertainty_map.max_px


def test_a_distorted_lens_keeps_its_radial_and_decentring_terms() -> None:
    rng = np.random.default_rng(0)
    obs = [synthetic_observation(T, K_TRUE, DIST_TRUE, rng, 0.05) for T in poses(20, rng)]
    res = calibrate_intrinsics(obs, SIZE)
    assert res.distortion_model in ("k1k2p1p2", "full")
    scores = {s.name: s for s in res.model_selection.scores}
    # Without distortion terms the held-out views are ten times worse than with them.
    assert scores["none"].held_out_rms_px > 5 * scores[res.distortion_model].held_out_rms_px
    assert model_error_px(res, DIST_TRUE)[1] < 0.15
    record = res.quality()
    assert record["distortion_model"] == res.distortion_model
    assert record["model_selection"]["chosen"] == res.distortion_model
    assert (
        0
        < record["projection_uncertainty_px"]["median"]
        <= record["projection_uncertainty_px"]["max"]
    )


def test_a_decentring_term_the_held_out_views_cannot_see_is_kept() -> None:
    # p1 = -4e-4 (0.1 px in the image): a held-out view's pose absorbs it with the principal
    # point, so held-out errors cannot tell; k1 k2 alone put cy 2.4-2.7 px off (seeds 0-2).
    rng = np.random.default_rng(0)
    dist = np.array([-0.06, 0.1, -4e-4, 0.0, 0.0])
    obs = [synthetic_observation(T, K_TRUE, dist, rng, 0.05) for T in poses(20, rng)]
    res = calibrate_intrinsics(obs, SIZE)
    radial = calibrate_intrinsics(obs, SIZE, distortion="k1k2")
    assert res.distortion_model in ("k1k2p1p2", "full")
    assert np.all(np.abs(res.K[:2, 2] - K_TRUE[:2, 2]) < 0.5)
    assert abs(radial.K[1, 2] - K_TRUE[1, 2]) > 1.5  # what the simpler model would have given
    assert "the most terms of" in res.model_selection.reason


def test_without_any_projection_uncertainty_the_fewest_terms_win(monkeypatch) -> None:
    def singular(*args, **kwargs):
        raise np.linalg.LinAlgError("singular matrix")

    monkeypatch.setattr(intrinsics_model, "projection_uncertainty", singular)
    rng = np.random.default_rng(0)
    obs = [synthetic_observation(T, K_TRUE, np.zeros(5), rng, 0.1) for T in poses(8, rng)]
    selection = calibrate_intrinsics(obs, SIZE).model_selection
    assert all(s.uncertainty_rms_px == np.inf for s in selection.scores)
    assert selection.chosen == "none"
    assert "no projection uncertainty could be computed" in selection.reason


def test_uncertainty_map_grows_where_no_view_looked() -> None:
    """Views that all sit in the image's centre leave the corners least certain."""
    rng = np.random.default_rng(4)
    central = []
    for T in poses(10, rng, max_tilt_deg=35.0):
        T = T.copy()
        T[:3, 3] = T[:3, 3] * [0.2, 0.2, 1.6]  # farther and towards the axis: a small target
        central.append(T)
    obs = [synthetic_observation(T, K_TRUE, DIST_TRUE, rng, 0.05) for T in central]
    res = calibrate_intrinsics(obs, SIZE, distortion="k1k2")
    sigma = res.uncertainty_map.sigma_px
    h, w = sigma.shape
    centre = sigma[h // 3 : 2 * h // 3, w // 3 : 2 * w // 3].mean()
    corners = np.mean([sigma[0, 0], sigma[0, -1], sigma[-1, 0], sigma[-1, -1]])
    assert corners > 3 * centre


def test_an_unknown_distortion_model_is_refused() -> None:
    with pytest.raises(ValueError, match="distortion: expected 'auto' or one of none"):
        calibrate_intrinsics([], SIZE, distortion="k9")


def _views_and_start(n: int, seed: int) -> tuple[list, np.ndarray]:
    """``n`` views of a distortion-free lens and their true poses (rotation vector, mm)."""
    rng = np.random.default_rng(seed)
    truth = poses(n, rng)
    obs = [synthetic_observation(T, K_TRUE, np.zeros(5), rng, 0.1) for T in truth]
    start = np.array([np.r_[Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]] for T in truth])
    return obs, start


def test_a_cancelled_model_choice_stops_within_one_fold(monkeypatch) -> None:
    """The check runs before each fold: what it raises comes out part-way through the
    candidates, without the folds still to come."""
    obs, start = _views_and_start(8, seed=0)
    fits = []
    real_adjust = intrinsics_model._adjust

    def counting(*args, **kwargs):
        fits.append(1)
        return real_adjust(*args, **kwargs)

    monkeypatch.setattr(intrinsics_model, "_adjust", counting)
    check = CancelAt(4)  # before the fourth fold (the first of the second candidate)

    with pytest.raises(Cancelled):
        intrinsics_model.select_distortion_model(obs, K_TRUE, start, check_cancelled=check)
    assert check.calls == 4
    # The start's fit of all views, then three folds of two fits each (the fold's own and its
    # held-out poses'), of the 1 + 2 * 3 * 5 the whole choice makes.
    assert len(fits) == 1 + 2 * 3
    assert len(fits) < 1 + 2 * 3 * len(intrinsics_model.DISTORTION_MODELS)


def test_the_cancellation_check_changes_nothing_in_the_model_choice() -> None:
    obs, start = _views_and_start(8, seed=0)
    candidates = ("none", "full")  # the two ends (all five would double the time)
    calls = []
    plain = intrinsics_model.select_distortion_model(obs, K_TRUE, start, candidates=candidates)
    checked = intrinsics_model.select_distortion_model(
        obs, K_TRUE, start, candidates=candidates, check_cancelled=lambda: calls.append(1)
    )
    assert len(calls) == plain.folds * len(candidates)
    assert checked.to_json() == plain.to_json()  # to the bit
    # The folds run two at a time on threads by default: one at a time gives the same.
    alone = intrinsics_model.select_distortion_model(
        obs, K_TRUE, start, candidates=candidates, workers=1
    )
    assert alone.to_json() == plain.to_json()
    for a, b in zip(plain.scores, checked.scores):
        assert np.array_equal(a.per_view_px, b.per_view_px)
