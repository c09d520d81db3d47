"""The calibration's covariance estimator's building blocks (its whole, on the virtual cell,
is checked against the truth in test_pipeline)."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.covariance import intrinsics_covariance_matrix, jackknife_covariance
from calibration.intrinsics import IntrinsicsResult
from calibration.intrinsics_adjust import PARAM_NAMES


def test_the_jackknife_recovers_the_covariance_of_a_mean():
    # leave-one-group-out means of groups of normal samples: their jackknife covariance is the
    # covariance of the full mean
    rng = np.random.default_rng(0)
    cov_true = np.array([[4.0, 1.2], [1.2, 1.0]])
    n, groups = 2000, 10
    trials = []
    for _ in range(200):
        x = rng.multivariate_normal([0, 0], cov_true, n)
        parts = np.array_split(np.arange(n), groups)
        est = np.array([np.delete(x, g, axis=0).mean(axis=0) for g in parts])
        trials.append(jackknife_covariance(est))
    np.testing.assert_allclose(np.mean(trials, axis=0), cov_true / n, rtol=0.1)


def test_intrinsics_covariance_from_std_and_correlation():
    std = {"fx": 0.5, "fy": 0.4, "cx": 0.2, "cy": 0.3, "k1": 1e-4}
    corr = np.eye(9)
    corr[0, 1] = corr[1, 0] = 0.9
    res = IntrinsicsResult(np.eye(3), np.zeros(5), (640, 480), "default", std=std, correlation=corr)
    c = intrinsics_covariance_matrix(res)
    assert c[0, 1] == pytest.approx(0.9 * 0.5 * 0.4)
    assert c[PARAM_NAMES.index("k3"), PARAM_NAMES.index("k3")] == 0.0  # held fixed
    assert np.all(np.linalg.eigvalsh(c) >= -1e-15)
