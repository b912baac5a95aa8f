"""The learned edit ranking played by the receivers of ``receiver_clustering_v1``."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from selenv.families.clustering.env import apply_edit, edit_cost_changes
from selenv.families.clustering.multiagent_agents import ClusteringGreedyPolicy
from selenv.learned.families.clustering import (
    ClusteringLearnedPolicy,
    make_clustering_marl_learned,
)
from selenv.learned.rl.agent import CHECKPOINT_DIR
from selenv.multiagent import fim_selection_v0, receiver_clustering_v1

HORIZON = 25
SEEDS = (0, 1, 2)


@pytest.fixture(scope="module")
def policy() -> ClusteringLearnedPolicy:
    """One loaded policy (default options: the shipped ranking, 8 edits costed, every step)."""
    return make_clustering_marl_learned()


def _env(**kwargs: Any) -> Any:
    return receiver_clustering_v1.parallel_env(invalid_action="raise", horizon=HORIZON, **kwargs)


def _greedy_edit(env: Any) -> int:
    """The module greedy's edit now: its best improving allowed edit, 0 if none improves."""
    bank = env.bank
    edits = ClusteringGreedyPolicy().allowed_edits(bank.labels, env.max_size)
    if edits.size == 0:
        return 0
    d = edit_cost_changes(bank, edits)
    j = int(np.argmin(d))
    return int(edits[j]) if d[j] < 0.0 else 0


def _targets(env: Any, actions: dict[str, Any]) -> np.ndarray:
    return np.array([actions[a] for a in env.possible_agents])


@pytest.mark.parametrize("n_max_states", [14, 10])
def test_joint_action_is_allowed_and_carried_out(
    policy: ClusteringLearnedPolicy, n_max_states: int
) -> None:
    """Every receiver answers a label of its mask, and the resolution accepts every answer."""
    moved = 0
    for seed in SEEDS:
        env = _env(n_max_states=n_max_states)
        obs, infos = env.reset(seed=seed)
        policy.reset(env, seed=seed)
        while env.agents:
            before = env.bank.labels.copy()
            evaluations = env.bank.n_cost_evaluations
            actions = policy.act(obs, infos)
            assert env.bank.n_cost_evaluations - evaluations <= policy.top_k
            assert set(actions) == set(env.agents)
            for a, t in actions.items():
                assert obs[a]["action_mask"][t] == 1, (seed, a, t)
            obs, _, _, _, infos = env.step(actions)
            assert all(info["accepted"] for info in infos.values())
            moved += int(np.any(_targets(env, actions) != before))
    assert moved > 0  # the policy did edit the clustering, so the checks above were exercised


def test_plays_greedy_edit_when_ranked_in_top_k(policy: ClusteringLearnedPolicy) -> None:
    """Greedy's best edit among the top k -> the same joint action as the module's greedy.

    And when greedy stays (no allowed edit lowers ``J``), so does the learned policy: its
    candidates are a subset of greedy's.
    """
    greedy = ClusteringGreedyPolicy(every=1)
    ranked, stayed = 0, 0
    for seed in SEEDS:
        env = _env()
        obs, infos = env.reset(seed=seed)
        policy.reset(env, seed=seed)
        greedy.reset(env, seed=seed)
        while env.agents:
            best = _greedy_edit(env)
            ours = policy.act(obs, infos)
            if best == 0:
                stayed += 1
                np.testing.assert_array_equal(_targets(env, ours), env.bank.labels)
            elif best in policy.ranked_edits(obs[env.agents[0]]):
                ranked += 1
                expected = greedy.act(obs, infos)
                assert ours == expected
                np.testing.assert_array_equal(
                    _targets(env, ours), apply_edit(env.bank.labels, best)
                )
            obs, _, _, _, infos = env.step(ours)
    assert ranked > 0 and stayed > 0  # both cases occurred


def test_top_k_covering_every_edit_is_greedy_every_step() -> None:
    """With top_k at least the number of allowed edits, every decision is greedy's."""
    full = make_clustering_marl_learned(top_k=10_000)
    greedy = ClusteringGreedyPolicy(every=1)
    env = _env()
    obs, infos = env.reset(seed=3)
    full.reset(env, seed=3)
    greedy.reset(env, seed=3)
    while env.agents:
        ours = full.act(obs, infos)
        assert ours == greedy.act(obs, infos)
        obs, _, _, _, infos = env.step(ours)


def test_every_keeps_the_clustering_between_decisions(policy: ClusteringLearnedPolicy) -> None:
    """``every=5``: at steps k % 5 != 0 everyone answers its own label and nothing is costed."""
    sparse = make_clustering_marl_learned(every=5, top_k=4)
    env = _env()
    obs, infos = env.reset(seed=4)
    sparse.reset(env, seed=4)
    while env.agents:
        k, evaluations = env.bank.k, env.bank.n_cost_evaluations
        actions = sparse.act(obs, infos)
        if k % 5:
            np.testing.assert_array_equal(_targets(env, actions), env.bank.labels)
            assert env.bank.n_cost_evaluations == evaluations
        obs, _, _, _, infos = env.step(actions)


def test_greedy_every_plays_greedy_search_at_its_steps() -> None:
    """``greedy_every=3``: at k % 3 == 0 greedy's full search (the same joint action as the
    module's greedy, so the step's myopic cost change is greedy's: never worse than greedy's
    edit); at the other steps at most ``top_k`` evaluations, as without the option.
    """
    mixed = make_clustering_marl_learned(top_k=2, greedy_every=3)
    greedy = ClusteringGreedyPolicy(every=1)
    searched, moved = 0, 0
    for seed in SEEDS:
        env = _env()
        obs, infos = env.reset(seed=seed)
        mixed.reset(env, seed=seed)
        greedy.reset(env, seed=seed)
        while env.agents:
            k, evaluations = env.bank.k, env.bank.n_cost_evaluations
            allowed = greedy.allowed_edits(env.bank.labels, env.max_size).size
            best = _greedy_edit(env)  # costs every allowed edit itself
            greedy_cost = env.bank.n_cost_evaluations - evaluations
            evaluations = env.bank.n_cost_evaluations
            ours = mixed.act(obs, infos)
            spent = env.bank.n_cost_evaluations - evaluations
            if k % 3 == 0:
                searched += 1
                assert spent == greedy_cost == allowed
                np.testing.assert_array_equal(
                    _targets(env, ours), apply_edit(env.bank.labels, best)
                )
                moved += best != 0
            else:
                assert spent <= mixed.top_k
            obs, _, _, _, infos = env.step(ours)
    assert searched > 0 and moved > 0  # greedy's search did run and did edit


@pytest.mark.parametrize(
    ("options", "named"),
    [
        ({"topk": 8}, "topk"),
        ({"top_k": 0}, "top_k"),
        ({"top_k": 2.0}, "top_k"),
        ({"every": 0}, "every"),
        ({"every": "5"}, "every"),
        ({"swaps": 1}, "swaps"),
        ({"greedy_every": -1}, "greedy_every"),
        ({"greedy_every": 5.0}, "greedy_every"),
        ({"greedy_every": True}, "greedy_every"),
        ({"checkpoint": 3}, "checkpoint"),
        ({"checkpoint": "/nonexistent/ranking.zip"}, "ranking.zip"),
        ({"checkpoint": str(CHECKPOINT_DIR / "fim_selection_ppo.zip")}, "FIMSelection"),
    ],
)
def test_bad_options_are_value_errors_naming_them(options: dict[str, Any], named: str) -> None:
    """Unknown options, bad values and checkpoints of another env: ValueError naming them."""
    with pytest.raises(ValueError, match=named):
        make_clustering_marl_learned(**options)


def test_refuses_another_env_and_acting_before_reset() -> None:
    """Another module's env is a ValueError naming the module; so is ranking before reset."""
    fresh = make_clustering_marl_learned(top_k=2)
    env = _env()
    obs, _ = env.reset(seed=0)
    with pytest.raises(ValueError, match="reset"):
        fresh.ranked_edits(obs["receiver_0"])
    other = fim_selection_v0.parallel_env()
    other.reset(seed=0)
    with pytest.raises(ValueError, match="receiver_clustering_v1"):
        fresh.reset(other, seed=0)
