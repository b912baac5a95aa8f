"""Core information math against independent formulas (inverse, slogdet, dual identity)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_pool, random_spd
from hypothesis import given, settings
from hypothesis import strategies as st

from selenv.core.information import (
    LogDetGainState,
    as_candidates,
    information_matrix,
    logdet_objective,
    naive_greedy_logdet,
    whiten,
)
from selenv.core.linalg import logdet_spd, solve_spd, validate_spd


def test_whiten_matches_inverse_formula(rng):
    H, R = random_pool(rng, 7, 5, m=3)
    G = whiten(H, R)
    for k in range(7):
        want = H[k].T @ np.linalg.inv(R[k]) @ H[k]
        np.testing.assert_allclose(G[k].T @ G[k], want, rtol=1e-10, atol=1e-12)


def test_dual_identity(rng):
    Q0 = random_spd(rng, 6)
    Hs = rng.normal(size=(4, 6))
    lhs = np.linalg.slogdet(Q0 + Hs.T @ Hs)[1]
    rhs = np.linalg.slogdet(Q0)[1] + np.linalg.slogdet(np.eye(4) + Hs @ np.linalg.inv(Q0) @ Hs.T)[1]
    assert lhs == pytest.approx(rhs, rel=1e-12)
    G = Hs[:, None, :]
    assert logdet_objective(Q0, G, range(4)) == pytest.approx(lhs - np.linalg.slogdet(Q0)[1])


@pytest.mark.parametrize("m,pad", [(1, False), (2, False), (2, True), (3, True)])
def test_state_tracks_exact_quantities(rng, m, pad):
    d, N = 6, 25
    Q0 = random_spd(rng, d)
    H, R = random_pool(rng, N, d, m=m, pad=pad)
    G = whiten(H, R)
    st_ = LogDetGainState(Q0, G, track_gains=True, track_whitened=True)
    for j in [3, 17, 0, 9, 22]:
        A = information_matrix(Q0, G, st_.order)
        base = np.linalg.slogdet(A)[1]
        direct = np.array([np.linalg.slogdet(A + G[k].T @ G[k])[1] - base for k in range(N)])
        np.testing.assert_allclose(st_.gains, direct, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(st_.P, np.linalg.inv(A), rtol=1e-8, atol=1e-10)
        L = np.linalg.cholesky(A)
        Zref = np.stack([np.linalg.solve(L, G[k].T).T for k in range(N)])
        np.testing.assert_allclose(st_.Z, Zref, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(np.einsum("kid,kjd->kij", st_.Z, st_.Z), st_.S, atol=1e-9)
        gain = st_.add(j)
        assert gain == pytest.approx(direct[j], rel=1e-9)
        assert st_.gain_of(j) > 0
    assert st_.objective == pytest.approx(logdet_objective(Q0, G, st_.order), rel=1e-10)


@pytest.mark.parametrize("m,pad", [(1, False), (2, True)])
def test_rank_one_greedy_equals_naive_greedy(m, pad):
    from selenv.agents.fim_solvers import greedy_whitened

    for seed in range(10):
        r = np.random.default_rng(seed)
        Q0 = random_spd(r, 5, 0.3)
        H, R = random_pool(r, 40, 5, m=m, pad=pad)
        G = whiten(H, R)
        assert list(greedy_whitened(Q0, G, 8).indices) == naive_greedy_logdet(Q0, G, 8)


@st.composite
def _instance(draw):
    seed = draw(st.integers(0, 2**31 - 1))
    d = draw(st.integers(1, 5))
    N = draw(st.integers(3, 9))
    m = draw(st.integers(1, 2))
    r = np.random.default_rng(seed)
    Q0 = random_spd(r, d, draw(st.sampled_from([1e-2, 1.0, 1e2])))
    H, R = random_pool(r, N, d, m=m)
    perm = r.permutation(N)
    cut1 = draw(st.integers(0, N - 1))
    cut2 = draw(st.integers(cut1, N - 1))
    X, Y, s = perm[:cut1], perm[:cut2], perm[N - 1]
    return Q0, whiten(H, R), X, Y, s


@settings(max_examples=150, deadline=None)
@given(_instance())
def test_f_is_normalized_monotone_submodular(inst):
    Q0, G, X, Y, s = inst
    f = lambda S: logdet_objective(Q0, G, list(S))  # noqa: E731
    assert f([]) == pytest.approx(0.0, abs=1e-12)  # eq. (12)
    tol = 1e-9 * (1 + abs(f(Y)))
    assert f(X) <= f(Y) + tol  # eq. (11)
    assert f([*X, s]) - f(X) >= f([*Y, s]) - f(Y) - tol  # eq. (10)


def test_linalg_helpers_against_numpy(rng):
    A = random_spd(rng, 7)
    b = rng.normal(size=7)
    np.testing.assert_allclose(solve_spd(A, b), np.linalg.solve(A, b), rtol=1e-10)
    assert logdet_spd(A) == pytest.approx(np.linalg.slogdet(A)[1], rel=1e-12)


@pytest.mark.parametrize(
    "bad,match",
    [
        (np.array([[1.0, 2.0], [0.0, 1.0]]), "symmetric"),
        (np.array([[1.0, 0.0], [0.0, -1.0]]), "positive definite"),
        (np.array([[np.nan, 0.0], [0.0, 1.0]]), "finite"),
        (np.ones((2, 3)), "shape"),
    ],
)
def test_validate_spd_errors_name_the_argument(bad, match):
    with pytest.raises(ValueError, match=f"Q0.*{match}|{match}.*Q0|Q0 must"):
        validate_spd(bad, "Q0")


def test_as_candidates_bad_input(rng):
    Q0 = random_spd(rng, 3)
    H = rng.normal(size=(5, 3))
    with pytest.raises(ValueError, match="Q0"):
        as_candidates(-Q0, H, np.ones(5))
    Hn = H.copy()
    Hn[2, 1] = np.nan
    with pytest.raises(ValueError, match="H must be finite"):
        as_candidates(Q0, Hn, np.ones(5))
    with pytest.raises(ValueError, match="R"):
        as_candidates(Q0, H, np.ones(4))
    with pytest.raises(ValueError, match="R"):
        as_candidates(Q0, H, -np.ones(5))
    with pytest.raises(ValueError, match=r"columns|shape"):
        as_candidates(Q0, rng.normal(size=(5, 1, 4)), np.eye(1))
    R_bad = np.stack([np.eye(2)] * 5)
    R_bad[3] = [[1.0, 2.0], [2.0, 1.0]]
    with pytest.raises(ValueError, match=r"R\[3\]"):
        as_candidates(Q0, rng.normal(size=(5, 2, 3)), R_bad)
    with pytest.raises(TypeError, match="H"):
        as_candidates(Q0, "abc", np.ones(5))


def test_state_rejects_double_pick_and_out_of_range(rng):
    Q0 = random_spd(rng, 3)
    G = rng.normal(size=(4, 1, 3))
    s = LogDetGainState(Q0, G)
    s.add(1)
    with pytest.raises(ValueError, match="already selected"):
        s.add(1)
    with pytest.raises(ValueError, match=r"range|lie in"):
        s.add(4)
