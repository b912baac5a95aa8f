"""The exact FIM solver and its relaxation bound against brute force and an independent solver.

Brute force (every subset) is the truth for the optimum; scipy's SLSQP on the same concave
program is an independent solver of the relaxation; random subsets, greedy and swap check that
a certified bound is never below a feasible value.
"""

from __future__ import annotations

import itertools
import math

import gymnasium as gym
import numpy as np
import pytest
from conftest import random_pool, random_spd
from scipy.optimize import minimize

from selenv.agents import fim_exact
from selenv.agents.fim_exact import (
    ExactSelection,
    branch_and_bound_whitened,
    relaxation_bound_whitened,
)
from selenv.agents.fim_solvers import (
    brute_force_whitened,
    greedy_whitened,
    partition_swap_whitened,
    swap_whitened,
)
from selenv.core.information import logdet_objective, whiten


def _instance(seed: int, m: int, n_lo: int = 8, n_hi: int = 15) -> tuple[np.ndarray, np.ndarray]:
    r = np.random.default_rng(seed)
    d = int(r.integers(2, 8))
    N = int(r.integers(n_lo, n_hi + 1))
    Q0 = random_spd(r, d, float(r.choice([0.05, 1.0, 20.0])))
    H, R = random_pool(r, N, d, m=m, pad=(m == 2))
    return Q0, whiten(H, R)


@pytest.mark.parametrize("enumerate_nodes", [True, False], ids=["enumerate", "relax-only"])
@pytest.mark.parametrize("m", [1, 2])
def test_branch_and_bound_finds_the_brute_force_optimum(
    m: int, enumerate_nodes: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On 25 random pools per case; without enumeration every node is bounded and branched."""
    if not enumerate_nodes:
        monkeypatch.setattr(fim_exact, "_ENUMERATE", 0)
    nodes = 0
    for seed in range(25):
        Q0, G = _instance(seed, m)
        K = 1 + seed % min(6, G.shape[0] - 1)
        opt = brute_force_whitened(Q0, G, K)
        got = branch_and_bound_whitened(Q0, G, K, initial=list(range(K)))
        assert got.optimal and isinstance(got, ExactSelection)
        assert got.objective == pytest.approx(opt.objective, rel=1e-10, abs=1e-12)
        assert (
            opt.objective - 1e-9 <= got.upper_bound <= got.objective + 1e-9 * max(1, opt.objective)
        )
        assert got.gap <= 1e-9
        if abs(logdet_objective(Q0, G, list(opt.indices)) - got.objective) > 1e-12:
            pytest.fail("different optima with different values")
        assert logdet_objective(Q0, G, list(got.indices)) == pytest.approx(got.objective)
        nodes += got.nodes
    if not enumerate_nodes:
        assert nodes > 2 * 25  # the relaxation path branched, not only solved roots


def _slsqp_relaxation(Q0: np.ndarray, Qk: np.ndarray, K: int):
    """scipy's SLSQP on max log det(Q0 + sum w_k Q_k), sum w = K, 0 <= w <= 1."""

    def neg_F(w: np.ndarray) -> float:
        return -float(np.linalg.slogdet(Q0 + np.tensordot(w, Qk, 1))[1])

    def neg_grad(w: np.ndarray) -> np.ndarray:
        P = np.linalg.inv(Q0 + np.tensordot(w, Qk, 1))  # the reference, not the code under test
        return -np.einsum("ij,kji->k", P, Qk)

    return minimize(
        neg_F,
        np.full(len(Qk), K / len(Qk)),
        jac=neg_grad,
        method="SLSQP",
        bounds=[(0.0, 1.0)] * len(Qk),
        constraints=[{"type": "eq", "fun": lambda w: w.sum() - K}],
        options={"ftol": 1e-14, "maxiter": 500},
    )


def test_relaxation_bound_against_scipy_and_brute_force() -> None:
    """The relaxed optimum matches SLSQP's; the certified bound sits just above it."""
    for seed in range(8):
        Q0, G = _instance(100 + seed, m=1, n_lo=6, n_hi=10)
        N, _, d = G.shape
        K = 2 + seed % 3
        sp = _slsqp_relaxation(Q0, np.einsum("kmi,kmj->kij", G, G), K)
        scipy_value = -sp.fun - float(np.linalg.slogdet(Q0)[1])
        res = relaxation_bound_whitened(Q0, G, K)
        assert res.relaxed == pytest.approx(scipy_value, abs=1e-6)
        assert res.relaxed - 1e-9 <= res.bound <= res.relaxed + 1e-6
        assert res.bound >= scipy_value - 1e-9  # a bound on the relaxation, hence on OPT
        assert res.bound >= brute_force_whitened(Q0, G, K).objective - 1e-9
        assert res.weights.sum() == pytest.approx(K) and np.all(res.weights >= 0)
        assert np.all(res.weights <= 1)


def test_relaxation_bound_is_above_every_subset_of_a_larger_pool() -> None:
    r = np.random.default_rng(7)
    Q0 = random_spd(r, 6)
    H, R = random_pool(r, 60, 6, m=2, pad=True)
    G = whiten(H, R)
    K = 6
    bound = relaxation_bound_whitened(Q0, G, K).bound
    assert bound >= swap_whitened(Q0, G, K).objective >= greedy_whitened(Q0, G, K).objective
    for _ in range(300):
        assert logdet_objective(Q0, G, r.choice(60, K, replace=False).tolist()) <= bound
    assert relaxation_bound_whitened(Q0, G, 60).bound == pytest.approx(
        logdet_objective(Q0, G, list(range(60)))
    )  # the whole pool: nothing to relax


def test_partition_budgets_against_brute_force() -> None:
    for seed in range(6):
        Q0, G = _instance(200 + seed, m=2, n_lo=9, n_hi=12)
        N = G.shape[0]
        groups = [list(range(0, N, 3)), list(range(1, N, 3)), list(range(2, N, 3))]
        budgets = [1 + seed % 2, 2, 1]
        best = -math.inf
        for combo in itertools.product(
            *(itertools.combinations(g, b) for g, b in zip(groups, budgets, strict=True))
        ):
            best = max(best, logdet_objective(Q0, G, [k for part in combo for k in part]))
        got = branch_and_bound_whitened(Q0, G, groups=groups, budgets=budgets)
        assert got.optimal and got.objective == pytest.approx(best, rel=1e-10)
        for g, b in zip(groups, budgets, strict=True):
            assert len(set(got.indices) & set(g)) == b
        assert got.objective >= partition_swap_whitened(Q0, G, groups, budgets).objective - 1e-12
        relaxed = relaxation_bound_whitened(Q0, G, groups=groups, budgets=budgets)
        assert relaxed.bound >= best - 1e-9


def test_node_limit_returns_the_incumbent_with_a_valid_certificate() -> None:
    r = np.random.default_rng(11)
    Q0 = random_spd(r, 5, 0.05)
    H, R = random_pool(r, 26, 5, m=2, pad=True)
    G = whiten(H, R)
    K = 5
    opt = brute_force_whitened(Q0, G, K).objective
    start = swap_whitened(Q0, G, K)
    for limit in (1, 3, 10):
        got = branch_and_bound_whitened(Q0, G, K, node_limit=limit)
        assert got.nodes <= limit
        assert start.objective - 1e-12 <= got.objective <= opt + 1e-9
        assert got.upper_bound >= opt - 1e-9  # certified: never below the optimum
        assert got.gap == pytest.approx((got.upper_bound - got.objective) / got.upper_bound)
        assert got.optimal == (got.upper_bound <= got.objective * (1 + 1e-9))
    full = branch_and_bound_whitened(Q0, G, K)
    assert full.optimal and full.objective == pytest.approx(opt, rel=1e-10)
    again = branch_and_bound_whitened(Q0, G, K)  # deterministic without a time limit
    assert (again.indices, again.objective, again.upper_bound, again.nodes) == (
        full.indices,
        full.objective,
        full.upper_bound,
        full.nodes,
    )


def test_bad_input_is_refused_with_the_argument_named() -> None:
    Q0, G = _instance(0, m=1)
    N = G.shape[0]
    cases: list[tuple[dict, type[Exception], str]] = [
        ({"budget": 2, "groups": [[0]], "budgets": [1]}, ValueError, "either budget"),
        ({"budget": None, "groups": [[0, 1]]}, ValueError, "together"),
        ({"budget": N + 1}, ValueError, "budget"),
        ({"budget": 2.0}, TypeError, "budget"),
        ({"budget": 2, "node_limit": 0}, ValueError, "node_limit"),
        ({"budget": 2, "node_limit": 1.5}, TypeError, "node_limit"),
        ({"budget": 2, "time_limit": 0.0}, ValueError, "time_limit"),
        ({"budget": 2, "time_limit": math.nan}, ValueError, "time_limit"),
        ({"budget": 2, "time_limit": "1"}, TypeError, "time_limit"),
        ({"budget": 2, "rtol": 1.0}, ValueError, "rtol"),
        ({"budget": 2, "initial": [0]}, ValueError, "initial"),
        ({"budget": 2, "initial": [0, 0]}, ValueError, "initial"),
        ({"budget": 2, "initial": [0, N]}, ValueError, "initial"),
        ({"budget": 2, "initial": [0.0, 1.5]}, ValueError, "initial"),
        ({"budget": 2, "objective": "trace"}, ValueError, "logdet"),
        ({"budget": 2, "interest": [0]}, ValueError, "logdet"),
    ]
    for kwargs, exc, match in cases:
        budget = kwargs.pop("budget")
        with pytest.raises(exc, match=match):
            branch_and_bound_whitened(Q0, G, budget, **kwargs)
    with pytest.raises(ValueError, match="G"):
        relaxation_bound_whitened(Q0, G[:, :, :-1], 2)


def test_optimal_agent_plays_the_brute_force_optimum() -> None:
    from selenv.bench import run_bench

    res = run_bench(
        "selenv/FIMSelection-v1",
        ["optimal", "brute_force", "swap"],
        episodes=3,
        env_kwargs={"n_candidates": 6, "budget": 4},
        progress=False,
    )
    opt, bf = res.agents["optimal"], res.agents["brute_force"]
    np.testing.assert_allclose(opt.returns, bf.returns, rtol=1e-10)
    assert np.all(np.asarray(opt.returns) >= np.asarray(res.agents["swap"].returns) - 1e-12)
    env = gym.make("selenv/FIMSelection-v1", objective="trace")
    from selenv.agents import make

    agent = make("optimal", "selenv/FIMSelection-v1")
    obs, info = env.reset(seed=0)
    agent.reset(env, seed=0)
    with pytest.raises(ValueError, match="logdet"):
        agent.act(obs, info)
