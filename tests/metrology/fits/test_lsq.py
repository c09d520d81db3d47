from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from metrology.fits.lsq import LSQ_SUBSAMPLE, gauss_newton_polish, solve_lsq


def _sphere(x, p):
    return np.linalg.norm(p - x[:3], axis=1) - x[3]


def _sphere_jac(x, p):
    q = p - x[:3]
    return np.c_[-q / np.linalg.norm(q, axis=1)[:, None], -np.ones(len(p))]


def _cloud(n: int, rng: np.random.Generator) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2])
    return 10.0 * d / np.linalg.norm(d, axis=1)[:, None] + rng.normal(0, 0.01, (n, 3))


def test_a_big_cloud_converges_to_the_full_least_squares():
    rng = np.random.default_rng(0)
    p = _cloud(LSQ_SUBSAMPLE + 20_000, rng)
    x0 = np.array([0.3, -0.2, 0.1, 9.5])
    x = solve_lsq(_sphere, _sphere_jac, x0, p, rng)
    full = least_squares(_sphere, x0, jac=_sphere_jac, args=(p,), method="lm", xtol=1e-14).x
    assert np.allclose(x, full, atol=1e-7)


def test_gauss_newton_polish_gives_up_when_the_cost_does_not_fall():
    rng = np.random.default_rng(1)
    p = _cloud(500, rng)

    def bad_jac(x, q):
        return -_sphere_jac(x, q)  # steps uphill

    assert gauss_newton_polish(_sphere, bad_jac, np.array([0.1, 0, 0, 9.9]), p) is None
    good = gauss_newton_polish(_sphere, _sphere_jac, np.array([0.01, 0, 0, 9.99]), p)
    assert good is not None and abs(good[3] - 10.0) < 0.01
