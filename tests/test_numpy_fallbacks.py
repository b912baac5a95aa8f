"""The private-numpy fast paths of ``selenv.core.npfast`` against their public fallbacks.

Each fast path is run with ``npfast.FAST`` on and off (monkeypatched) on the same inputs: the
kernels are the same LAPACK / einsum ones, so values agree to rounding (rtol 1e-12) and every
pass / fail verdict is identical; then the callers (batched DMV weights, the clustering window
pass, the Kalman update's validation) are run end to end both ways.
"""

from __future__ import annotations

import numpy as np
import pytest

from selenv.core import npfast
from selenv.core.fusion.batch import dmv_omega_batch, pecmv_batch
from selenv.core.kalman import kf_update


def _spd_stack(rng: np.random.Generator, B: int, n: int) -> np.ndarray:
    A = rng.normal(size=(B, n, n))
    return A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(n)


def test_this_numpy_has_the_fast_paths() -> None:
    """CI's numpy has them (else the fast path tests below would test the fallback twice)."""
    assert npfast.has_fast_paths() == {"solve": True, "cholesky_lo": True, "einsum": True}


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_solve_fast_equals_fallback(n: int, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(n)
    a, b = _spd_stack(rng, 7, n), rng.normal(size=(7, n, 3))
    fast = npfast.solve(a, b)
    monkeypatch.setattr(npfast, "FAST", False)
    slow = npfast.solve(a, b)
    np.testing.assert_allclose(fast, slow, rtol=1e-12, atol=0)
    np.testing.assert_allclose(np.einsum("bij,bjk->bik", a, slow), b, rtol=1e-8, atol=1e-10)
    with pytest.raises(np.linalg.LinAlgError):
        npfast.solve(np.zeros((2, n, n)), b[:2])


@pytest.mark.parametrize("n", [1, 3, 4])
def test_cholesky_fast_equals_fallback_and_nan_fills_failures(
    n: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    rng = np.random.default_rng(10 + n)
    a = _spd_stack(rng, 6, n)
    a[2] = -a[2]  # not positive definite: NaN-filled
    a[4, 0, 0] = np.nan
    with np.errstate(all="ignore"):
        fast = npfast.cholesky_lo(a)
        monkeypatch.setattr(npfast, "FAST", False)
        slow = npfast.cholesky_lo(a)
    np.testing.assert_array_equal(np.isnan(fast[:, -1, -1]), np.isnan(slow[:, -1, -1]))
    assert np.isnan(slow[2]).all() and np.isnan(slow[4, -1, -1])
    ok = [0, 1, 3, 5]
    np.testing.assert_allclose(fast[ok], slow[ok], rtol=1e-12, atol=0)
    np.testing.assert_allclose(slow[ok] @ np.swapaxes(slow[ok], 1, 2), a[ok], rtol=1e-10)


def test_einsum_fast_equals_fallback(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(3)
    X = rng.normal(size=(9, 4, 4))
    fast = npfast.einsum("...ij,...ji->...", X, X)
    monkeypatch.setattr(npfast, "FAST", False)
    np.testing.assert_allclose(npfast.einsum("...ij,...ji->...", X, X), fast, rtol=1e-12)


def _callers(seed: int) -> dict[str, np.ndarray]:
    from selenv.core.riccati import riccati_pass
    from selenv.families.clustering.filters import window_pass
    from selenv.families.clustering.scenario import ClusteringConfig, make_clustering_problem

    rng = np.random.default_rng(seed)
    out: dict[str, np.ndarray] = {}
    for m in (1, 2, 3):
        for B in (1, 3, 40):
            P_i, P_j = _spd_stack(rng, B, 4), _spd_stack(rng, B, 4)
            H_i, H_j = rng.normal(size=(B, m, 4)), rng.normal(size=(B, m, 4))
            R = _spd_stack(rng, B, m)
            out[f"omega{m}-{B}"] = dmv_omega_batch(P_i, P_j, H_i, H_j, R)
            out[f"pecmv{m}-{B}"] = pecmv_batch(P_i, P_j, H_i, H_j, R).P
    problem = make_clustering_problem(ClusteringConfig(), rng)
    F, Q, H = problem.axis_model((0, 1))
    P0 = _spd_stack(rng, 4, 5)
    R = np.zeros((4, 4, 4)) + np.eye(4) * rng.uniform(0.1, 1.0, size=(4, 4, 1))
    out["window"] = window_pass(P0, F, Q, H, R, 15)
    out["riccati"] = riccati_pass(P0, F, Q, H, R, 15)
    x, P = rng.normal(size=4), _spd_stack(rng, 1, 4)[0]
    out["kf"] = kf_update(x, P, rng.normal(size=2), rng.normal(size=(2, 4)), np.eye(2)).P
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_callers_give_the_same_results_on_the_fallbacks(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    fast = _callers(seed)
    monkeypatch.setattr(npfast, "FAST", False)
    slow = _callers(seed)
    assert fast.keys() == slow.keys()
    for k in fast:
        np.testing.assert_allclose(slow[k], fast[k], rtol=1e-9, atol=0, err_msg=k)
    np.testing.assert_allclose(fast["window"], fast["riccati"], rtol=1e-9)
