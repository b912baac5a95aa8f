"""The learned ``FIMSelection-v1`` selector: policy picks and greedy's, each polished by swaps."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401
from selenv.agents import make
from selenv.agents.fim_solvers import greedy_whitened, swap_deltas, swap_whitened, whiten_in
from selenv.core.information import logdet_objective
from selenv.learned.families.fim import FIMPolicySwapAgent, make_fim_learned, polish

FIM = "selenv/FIMSelection-v1"
SEEDS = (3, 11, 29, 104)


def _play(agent: Any, seed: int, **env_kw: Any) -> tuple[list[int], float, gym.Env[Any, Any]]:
    """One episode of ``agent``; its picks in order and the final objective."""
    env = gym.make(FIM, invalid_action="raise", **env_kw)
    obs, info = env.reset(seed=seed)
    agent.reset(env, seed=seed)
    picks, done = [], False
    while not done:
        action = agent.act(obs, info)
        picks.append(int(action))
        obs, _, done, _, info = env.step(action)
    return picks, float(info["objective"]), env


def _pool(seed: int, m: int, N: int = 14, d: int = 4) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(d, d))
    return X @ X.T + d * np.eye(d), rng.normal(size=(N, m, d)) * rng.uniform(0.2, 1.5, (N, 1, 1))


@pytest.mark.parametrize("m", [1, 2, 3])
def test_swap_deltas_are_the_objective_differences(m: int) -> None:
    """Each (i, j) entry is f(S - i + j) - f(S), recomputed by direct Cholesky log dets."""
    Q0, G = _pool(m, m)
    sel = np.array([0, 5, 9, 2])
    uns = np.setdiff1d(np.arange(G.shape[0]), sel)
    delta = swap_deltas(whiten_in(Q0, G, sel), sel, uns)
    base = logdet_objective(Q0, G, sel)
    ref = np.empty((sel.size, uns.size))
    for a in range(sel.size):
        for b, j in enumerate(uns):
            swapped = sel.copy()
            swapped[a] = j
            ref[a, b] = logdet_objective(Q0, G, swapped) - base
    np.testing.assert_allclose(delta, ref, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("m", [1, 2])
def test_polish_never_lowers_the_start(seed: int, m: int) -> None:
    Q0, G = _pool(seed, m, N=20)
    start = np.random.default_rng(seed).choice(20, size=5, replace=False)
    sel, rounds = polish(Q0, G, start)
    assert sorted(set(sel.tolist())) == sorted(sel.tolist()) and sel.size == 5
    assert logdet_objective(Q0, G, sel) >= logdet_objective(Q0, G, start) - 1e-12
    assert rounds >= 1
    assert polish(Q0, G, start, max_rounds=0)[0].tolist() == list(start)


@pytest.mark.parametrize("seed", range(4))
def test_polish_from_greedy_is_swap(seed: int) -> None:
    """The same moves as swap_whitened: same picks in the same slots, same objective."""
    Q0, G = _pool(seed + 50, 2, N=24)
    start = greedy_whitened(Q0, G, 6)
    sel, _ = polish(Q0, G, start.indices)
    ref = swap_whitened(Q0, G, 6)
    assert sel.tolist() == list(ref.indices)


@pytest.mark.parametrize("seed", SEEDS)
def test_picks_are_a_valid_subset_of_the_budget(seed: int) -> None:
    picks, value, env = _play(make_fim_learned(), seed)
    base = env.unwrapped
    assert len(picks) == base.budget == len(set(picks))
    assert all(0 <= k < base.n for k in picks)
    assert value == pytest.approx(logdet_objective(base.core.Q0, base.state.G, picks), abs=1e-9)


@pytest.mark.parametrize("seed", SEEDS)
def test_policy_start_is_the_policy_playing_the_env(seed: int) -> None:
    """The scratch rollout sees exactly the observations the env would show the policy."""
    agent = make_fim_learned(starts="policy", policy_steps=0)
    env = gym.make(FIM)
    obs, info = env.reset(seed=seed)
    agent.reset(env, seed=seed)
    planned = agent.policy_picks(obs, env.unwrapped.budget_left)
    played, done = [], False
    while not done:
        action = int(np.argmax(agent.policy.logits(obs, info, backend="numpy")))
        played.append(action)
        obs, _, done, _, info = env.step(action)
    assert planned == played


@pytest.mark.parametrize("steps", [1, 2, 4])
def test_policy_steps_then_greedy(steps: int) -> None:
    """The first ``steps`` picks are the policy's own rollout's, the rest greedy's after them."""
    env = gym.make(FIM)
    obs, _ = env.reset(seed=5)
    full = make_fim_learned(starts="policy", policy_steps=0)
    full.reset(env, seed=5)
    agent = make_fim_learned(starts="policy", policy_steps=steps)
    agent.reset(env, seed=5)
    base = env.unwrapped
    picks = agent.policy_picks(obs, base.budget_left)
    assert picks[:steps] == full.policy_picks(obs, base.budget_left)[:steps]
    state = base.state
    Q = state.information + sum(state.G[k].T @ state.G[k] for k in picks[:steps])
    rest = np.setdiff1d(np.arange(base.n), picks[:steps])
    greedy = greedy_whitened(Q, np.asarray(state.G)[rest], base.budget - steps)
    assert picks[steps:] == [int(rest[k]) for k in greedy.indices]


@pytest.mark.parametrize("pool", [5, 12, 64])
def test_policy_pool_picks_among_the_best_scored(pool: int) -> None:
    agent = make_fim_learned(starts="policy", policy_pool=pool)
    env = gym.make(FIM)
    obs, info = env.reset(seed=8)
    agent.reset(env, seed=8)
    left = env.unwrapped.budget_left
    logits = agent.policy.logits(obs, info, backend="numpy")
    best = set(np.argsort(-logits, kind="stable")[: max(pool, left)].tolist())
    picks = agent.policy_picks(obs, left)
    assert len(set(picks)) == left and set(picks) <= best


@pytest.mark.parametrize("seed", SEEDS)
def test_swap_polish_never_lowers_the_policy_start(seed: int) -> None:
    agent = make_fim_learned(starts="policy")
    env = gym.make(FIM)
    obs, _ = env.reset(seed=seed)
    agent.reset(env, seed=seed)
    base = env.unwrapped
    start = agent.policy_picks(obs, base.budget_left)
    Q0, G = base.core.Q0, np.asarray(base.state.G)
    _, value, _ = _play(make_fim_learned(starts="policy"), seed)
    assert value >= logdet_objective(Q0, G, start) - 1e-9


@pytest.mark.parametrize("seed", SEEDS)
def test_greedy_start_is_swap(seed: int) -> None:
    """starts='greedy' plays exactly the swap agent's picks (the second formulation)."""
    picks, value, _ = _play(make_fim_learned(starts="greedy"), seed)
    ref_picks, ref_value, _ = _play(make("swap", FIM), seed)
    assert picks == ref_picks
    assert value == pytest.approx(ref_value, abs=1e-12)


@pytest.mark.parametrize("seed", SEEDS)
def test_both_starts_never_below_either(seed: int) -> None:
    _, both, _ = _play(make_fim_learned(), seed)
    _, greedy_start, _ = _play(make_fim_learned(starts="greedy"), seed)
    _, policy_start, _ = _play(make_fim_learned(starts="policy"), seed)
    assert both >= max(greedy_start, policy_start) - 1e-9


def test_takes_over_mid_episode() -> None:
    """Picks made before the agent's first plan stay in the prior; the rest fill the budget."""
    env = gym.make(FIM, invalid_action="raise", budget=6)
    obs, info = env.reset(seed=7)
    greedy = make("greedy", FIM)
    greedy.reset(env, seed=7)
    first = []
    for _ in range(2):
        first.append(int(greedy.act(obs, info)))
        obs, _, _, _, info = env.step(first[-1])
    agent = make_fim_learned()
    agent.reset(env, seed=7)
    rest, done = [], False
    while not done:
        rest.append(int(agent.act(obs, info)))
        obs, _, done, _, info = env.step(rest[-1])
    assert len(rest) == 4 and not set(rest) & set(first) and len(set(rest)) == 4


@pytest.mark.parametrize(
    ("options", "named"),
    [
        ({"starts": "random"}, "starts"),
        ({"max_rounds": -1}, "max_rounds"),
        ({"max_rounds": True}, "max_rounds"),
        ({"max_rounds": 2.5}, "max_rounds"),
        ({"policy_pool": -4}, "policy_pool"),
        ({"policy_steps": -1}, "policy_steps"),
        ({"policy_steps": 1.0}, "policy_steps"),
        ({"policy_pool": "all"}, "policy_pool"),
        ({"tol": math.nan}, "tol"),
        ({"tol": -1e-3}, "tol"),
        ({"tol": "small"}, "tol"),
        ({"top_k": 3}, "top_k"),
        ({"starts": "greedy", "checkpoint": "x.zip"}, "checkpoint"),
        ({"checkpoint": "/nonexistent/policy.zip"}, "policy.zip"),
    ],
)
def test_bad_options_are_value_errors_naming_them(options: dict[str, Any], named: str) -> None:
    with pytest.raises(ValueError, match=named):
        make_fim_learned(**options)


def test_refuses_another_objective() -> None:
    env = gym.make(FIM, objective="trace")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="objective='logdet' only"):
        FIMPolicySwapAgent().reset(env, seed=0)


def test_swap_warm_start_study_fixed_point_and_greedy_reference() -> None:
    """benchmarks/fim_swap_warm_starts.py: swap's result is a fixed point of the polish (one
    round, the same objective); greedy's start is the reference; replacements lower the kept
    count exactly."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "fim_swap_warm_starts.py"
    spec = importlib.util.spec_from_file_location("fim_swap_warm_starts", path)
    assert spec is not None and spec.loader is not None
    study = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(study)
    rows = {r["start"]: r for r in study.measure([3, 11], [0, 2], {"n_candidates": 40}, 0)}
    assert set(rows) == {"greedy", "swap's result, 0 replaced", "swap's result, 2 replaced"}
    fixed = rows["swap's result, 0 replaced"]
    assert fixed["rounds_mean"] == 1.0 and fixed["ties"] == 2 and fixed["picks_of_swap_kept"] == 10
    assert rows["swap's result, 2 replaced"]["picks_of_swap_kept"] == 8
    assert rows["greedy"]["ties"] == 2 and rows["greedy"]["rounds_mean"] >= 1.0


def test_swap_warm_start_study_counts_the_learned_starts_against_swaps_picks() -> None:
    """--policy-steps: the learned start's 'kept' is its overlap with swap's own selection and
    its row's outcome is the polish of ppo_swap's policy start (checked through the agent with
    starts='policy' and the solver's swap, not through the study's code)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "fim_swap_warm_starts.py"
    spec = importlib.util.spec_from_file_location("fim_swap_warm_starts", path)
    assert spec is not None and spec.loader is not None
    study = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(study)
    seed, kwargs = 5, {"n_candidates": 50}
    rows = {r["start"]: r for r in study.measure([seed], [], kwargs, 0, policy_steps=[2])}
    assert set(rows) == {
        "greedy", "policy start, 2 policy picks", "policy's K highest first scores"
    }  # fmt: skip
    env = gym.make("selenv/FIMSelection-v1", **kwargs)
    obs, info = env.reset(seed=seed)
    state = env.unwrapped.state
    prior, G = state.information, np.asarray(state.G)
    budget = int(env.unwrapped.budget_left)
    swap_sel = set(swap_whitened(prior, G, budget).indices)
    start = FIMPolicySwapAgent(starts="policy", policy_steps=2, max_rounds=0)  # no polish
    start.reset(env, seed)
    picks = start.plan(obs, info)
    row = rows["policy start, 2 policy picks"]
    assert len(picks) == budget and row["picks_of_swap_kept"] == len(swap_sel & set(picks))
    polished = FIMPolicySwapAgent(starts="policy", policy_steps=2)
    polished.reset(env, seed)
    plan = polished.plan(obs, info)
    gap = logdet_objective(prior, G, plan) - logdet_objective(prior, G, sorted(swap_sel))
    assert row["mean_diff_vs_swap"] == pytest.approx(gap, abs=1e-9)
    assert row["rounds_mean"] >= 1.0
