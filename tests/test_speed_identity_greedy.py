"""The faster public greedy set-up gives the same picks, and objectives and states to rtol 1e-9.

The references below are the previous implementation's logic, kept in small functions: the
batched Cholesky + solve whitening, ``scipy`` ``cho_solve`` / ``solve_triangular`` for the
initial state, the Sherman-Morrison update with ``symmetrize`` and ``np.outer`` and the loop
over the unique ``(a, b)`` entries of ``S``, and the objective by :func:`logdet_objective`.
They run on the same seeded inputs: picks are compared exactly, values to rtol 1e-9, and the
state bit for bit against the reference run on the same whitened pool (same operations). Errors are
compared with the fast validation paths switched off (the canonical checks alone).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from scipy.linalg import cho_solve, solve_triangular

import selenv.core.information as info_mod
from selenv.agents.fim_solvers import greedy, greedy_whitened, lazy_greedy
from selenv.core.information import LogDetGainState, as_candidates, logdet_objective, whiten
from selenv.core.linalg import cholesky_spd, symmetrize, validate_spd

# ------------------------------------------------------------------ previous implementation


def _ref_gains(S: np.ndarray) -> np.ndarray:
    m = S.shape[-1]
    if m == 1:
        return np.log1p(S[:, 0, 0])
    if m == 2:
        a, b, c = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
        return np.log1p(a + c + a * c - b * b)
    L = cholesky_spd(S + np.eye(m), "I + S_k")
    return 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)


def _ref_whiten(H3: np.ndarray, R3: np.ndarray) -> np.ndarray:
    """The previous whitening of every pool: batched Cholesky, then a batched solve."""
    return np.linalg.solve(cholesky_spd(R3, "R"), H3).astype(np.float64, copy=False)


def _ref_greedy(Q0: np.ndarray, G: np.ndarray, budget: int) -> dict[str, Any]:
    """The previous ``LogDetGainState`` (rank-one mode) driven by the greedy loop."""
    Q0 = validate_spd(Q0, "Q0")
    N, m, d = G.shape
    Gflat = G.reshape(N * m, d)
    L0 = cholesky_spd(Q0, "Q0")
    P = cho_solve((L0, True), np.eye(d))
    W = solve_triangular(L0, Gflat.T, lower=True).T.reshape(G.shape)
    S = np.einsum("kid,kjd->kij", W, W)
    gains = _ref_gains(S)
    selected = np.zeros(N, dtype=bool)
    order: list[int] = []
    objective = 0.0
    pairs = [(a, b) for a in range(m) for b in range(a, m)]
    for _ in range(budget):
        j = int(np.argmax(np.where(selected, -np.inf, gains)))
        for g in G[j]:
            if not np.any(g):
                continue
            u = P @ g
            q = float(g @ u)
            P = symmetrize(P - np.outer(u, u) / (1.0 + q))
            objective += float(np.log1p(q))
            c = (Gflat @ u).reshape(N, m)
            c *= 1.0 / np.sqrt(1.0 + q)
            for a, b in pairs:
                v = c[:, a] * c[:, b]
                S[:, a, b] -= v
                if a != b:
                    S[:, b, a] -= v
        gains = _ref_gains(S)
        selected[j] = True
        order.append(j)
    return {
        "order": tuple(order),
        "value": logdet_objective(Q0, G, order),
        "objective": objective,
        "P": P,
        "S": S,
        "gains": gains,
        "W": W,
    }


# ------------------------------------------------------------------ seeded problems


def _problem(seed: int, m: int | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    rng = np.random.default_rng(seed)
    d = int(rng.integers(1, 16))
    N = int(rng.integers(1, 250))
    K = int(rng.integers(0, min(N, 12) + 1))
    M = rng.normal(size=(d, d))
    Q0 = M @ M.T / d + 0.1 * np.eye(d)
    if seed % 7 == 3:
        Q0 = Q0 + 1e-12 * rng.normal(size=(d, d))  # not exactly symmetric: canonical path
    scale = 10.0 ** rng.uniform(-3, 3, size=(N, 1))
    if m is None:
        return Q0, rng.normal(size=(N, d)) * scale, 10.0 ** rng.uniform(-4, 4, size=N), K
    H = rng.normal(size=(N, m, d)) * scale[:, :, None]
    if seed % 5 == 0:
        H[:, -1] = 0.0  # zero padding rows
    A = rng.normal(size=(N, m, m))
    return Q0, H, A @ A.transpose(0, 2, 1) + 0.5 * np.eye(m), K


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Bit for bit (only for two computations with the same operations in one process)."""
    return a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("m", [None, 1, 2, 3])
def test_greedy_matches_previous_implementation(m: int | None) -> None:
    for seed in range(120):
        Q0, H, R, K = _problem(seed, m)
        H3 = H[:, None, :] if m is None else H
        R3 = R[:, None, None] if m is None else R
        G_ref = _ref_whiten(H3, R3)
        Q0_a, G = as_candidates(Q0, H, R)
        # one-row pools are whitened as H * (1 / sqrt(R)): the solve to one rounding
        np.testing.assert_allclose(G, G_ref, rtol=5e-16, atol=0, err_msg=str(seed))
        ref = _ref_greedy(Q0, G_ref, K)
        for sel in (greedy(Q0, H, R, K), greedy_whitened(Q0, G_ref, K)):
            assert sel.indices == ref["order"], seed
            assert sel.objective == pytest.approx(ref["value"], rel=1e-9, abs=0), seed
            assert sel.evaluations == K * G.shape[0]
        assert lazy_greedy(Q0, H, R, K).indices == ref["order"]
        # the state against the reference on the same whitened pool: the same operations in
        # one process, so bit for bit (P after K downdates is ill-conditioned in the pool)
        same = _ref_greedy(Q0, G, K)
        assert same["order"] == ref["order"]
        st = LogDetGainState(Q0_a, G)
        for j in same["order"]:
            st.add(j)
        assert st.objective == same["objective"]
        assert st.S is not None and st.gains is not None
        assert _same(st.P, same["P"]) and _same(st.S, same["S"])
        assert _same(st.gains, same["gains"])
        stw = LogDetGainState(Q0_a, G, track_whitened=True)
        assert stw.Z is not None and _same(stw.Z, same["W"])


def test_whiten_rows_equals_batched_solve() -> None:
    """``H * (1 / sqrt(R))`` is the 1 x 1 Cholesky + solve to one rounding, over a wide range."""
    for seed in range(60):
        rng = np.random.default_rng(seed)
        H = rng.normal(size=(300, 1, 7)) * 10.0 ** rng.uniform(-90, 90, size=(300, 1, 1))
        R = 10.0 ** rng.uniform(-99, 99, size=(300, 1, 1))
        got = info_mod._whiten_rows(H, R)
        np.testing.assert_allclose(got, _ref_whiten(H, R), rtol=5e-16, atol=0)
        np.testing.assert_allclose(got, whiten(H, R), rtol=5e-16, atol=0)


_BAD: list[tuple[Any, Any, Any]] = [
    (np.eye(3), np.ones((4, 3)), np.array([1.0, 2.0, np.nan, 1.0])),
    (np.eye(3), np.ones((4, 3)), np.array([1.0, 2.0, -1.0, 1.0])),
    (np.eye(3), np.ones((4, 3)), np.array([1.0, 2.0, 1e-200, 1.0])),
    (np.eye(3), np.ones((4, 3)), np.array([1.0, 2.0, 1e200, 1.0])),
    (np.eye(3), np.ones((4, 3)), np.ones(5)),
    (np.eye(3), np.ones((4, 2)), np.ones(4)),
    (np.eye(3), np.full((4, 3), 1e120), np.ones(4)),
    (np.eye(3), np.full((4, 3), np.inf), np.ones(4)),
    (np.eye(3), np.ones((4, 3)) + 0j, np.ones(4)),
    (np.eye(3), np.ones((4, 3)), 2.0),
    (np.eye(3), np.ones((4, 1, 3)), np.ones((4, 1, 1))),
    (np.eye(3), np.ones((4, 1, 3)), -np.ones((4, 1, 1))),
    (-np.eye(3), np.ones((4, 3)), np.ones(4)),
    (np.array([[1.0, 0.5], [0.4, 1.0]]), np.ones((4, 2)), np.ones(4)),
    (np.diag([1.0, 1e-200]), np.ones((4, 2)), np.ones(4)),
    (np.diag([1.0, np.nan]), np.ones((4, 2)), np.ones(4)),
    (np.eye(3)[:2], np.ones((4, 3)), np.ones(4)),
    (np.eye(3, dtype=bool), np.ones((4, 3)), np.ones(4)),
    ([[2.0, 0.0], [0.0, 1.0]], [[1.0, 0.0]], [1.0]),
]


def _outcome(fn: Any, *args: Any) -> tuple[str, str]:
    try:
        out = fn(*args)
    except (TypeError, ValueError) as exc:
        return type(exc).__name__, str(exc)
    return "ok", repr(out)


@pytest.mark.parametrize("case", range(len(_BAD)))
def test_errors_unchanged_by_fast_paths(case: int, monkeypatch: pytest.MonkeyPatch) -> None:
    Q0, H, R = _BAD[case]
    fast = _outcome(greedy, Q0, H, R, 1)
    fast_cand = _outcome(as_candidates, Q0, H, R)
    monkeypatch.setattr(info_mod, "_valid_prior", lambda Q0: None)
    monkeypatch.setattr(info_mod, "_scalar_pool_ok", lambda H, R: False)
    assert _outcome(greedy, Q0, H, R, 1) == fast
    assert _outcome(as_candidates, Q0, H, R) == fast_cand


def test_budget_and_objective_errors() -> None:
    Q0, H, R, _ = _problem(1, None)
    with pytest.raises(TypeError, match="budget"):
        greedy(Q0, H, R, 1.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="budget"):
        greedy(Q0, H, R, H.shape[0] + 1)
    with pytest.raises(ValueError, match="objective"):
        greedy(Q0, H, R, 1, objective="nope")
    _, G = as_candidates(Q0, H, R)
    with pytest.raises(ValueError, match="G"):
        greedy_whitened(Q0, np.full_like(G, np.nan), 1)


def test_closed_form_3x3_gains_agree_with_cholesky() -> None:
    """The solvers' vectorised ``m = 3`` Cholesky gains agree with LAPACK's to rounding,
    ``1e-13 (1 + S22) / l22^2`` (the error of the last pivot), on any BLAS kernel."""
    for seed in range(40):
        rng = np.random.default_rng(seed)
        W = rng.normal(size=(500, 3, int(rng.integers(1, 8)))) * 10.0 ** rng.uniform(
            -4, 4, size=(500, 1, 1)
        )
        S = np.einsum("kid,kjd->kij", W, W)
        ref = _ref_gains(S)
        got = info_mod._logdet_gains3(S)
        L = np.linalg.cholesky(S + np.eye(3))
        bound = 1e-13 * (1.0 + S[:, 2, 2]) / L[:, 2, 2] ** 2
        assert np.all(np.abs(got - ref) <= bound), seed


def test_m3_picks_identical_on_many_seeds_with_ties() -> None:
    """Selections (and so the recomputed objectives) are unchanged by the closed form, also
    with exact ties (duplicated candidates) and rank-deficient blocks (zero rows)."""
    for seed in range(300):
        Q0, H, R, K = _problem(1000 + seed, 3)
        if seed % 3 == 0:
            H = np.concatenate([H, H[: max(1, H.shape[0] // 4)]])  # exact duplicates
            R = np.concatenate([R, R[: max(1, R.shape[0] // 4)]])
        ref = _ref_greedy(Q0, _ref_whiten(H, R), K)
        sel = greedy(Q0, H, R, K)
        assert sel.indices == ref["order"], seed
        assert sel.objective == pytest.approx(ref["value"], rel=1e-9, abs=0), seed
