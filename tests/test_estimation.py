"""Gauss-Newton MAP against the closed-form linear-Gaussian posterior and a nonlinear case."""

from __future__ import annotations

import numpy as np
from conftest import random_spd

from selenv.core.estimation import gauss_newton_map


def test_linear_case_equals_closed_form_posterior(rng):
    d, N, m = 4, 6, 2
    Hm = rng.normal(size=(N, m, d))
    R = np.stack([random_spd(rng, m, 0.3) for _ in range(N)])
    mu0, P0 = rng.normal(size=d), random_spd(rng, d)
    y = rng.normal(size=(N, m))
    res = gauss_newton_map(lambda t: Hm @ t, lambda t: Hm, y, R, mu0, P0)
    # information form of the posterior, computed with explicit inverses (independent path)
    Hs = Hm.reshape(-1, d)
    Rb = np.zeros((N * m, N * m))
    for k in range(N):
        Rb[k * m : (k + 1) * m, k * m : (k + 1) * m] = R[k]
    info = Hs.T @ np.linalg.inv(Rb) @ Hs + np.linalg.inv(P0)
    mean = np.linalg.solve(info, Hs.T @ np.linalg.inv(Rb) @ y.ravel() + np.linalg.solve(P0, mu0))
    np.testing.assert_allclose(res.theta, mean, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(res.cov, np.linalg.inv(info), rtol=1e-8, atol=1e-12)
    assert res.converged


def test_nonlinear_ranges_recover_truth():
    rng = np.random.default_rng(1)
    anchors = rng.uniform(-100, 100, size=(8, 2))
    truth = np.array([10.0, -20.0])

    def h(t):
        return np.linalg.norm(anchors - t, axis=1)[:, None]

    def jac(t):
        diff = t - anchors
        return (diff / np.linalg.norm(diff, axis=1)[:, None])[:, None, :]

    y = h(truth) + 0.01 * rng.normal(size=(8, 1))
    R = np.full((8, 1, 1), 1e-4)
    res = gauss_newton_map(h, jac, y, R, np.array([0.0, 0.0]), np.eye(2) * 1e4)
    assert res.converged
    np.testing.assert_allclose(res.theta, truth, atol=0.05)
