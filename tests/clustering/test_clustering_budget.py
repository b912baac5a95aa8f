"""Clustering greedy under an evaluation budget (``greedy:max_evaluations=K``)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from selenv.agents import make
from selenv.families.clustering.agents import GreedyMoveAgent, best_edit
from selenv.families.clustering.env import edit_cost_changes, edit_mask

ENV = "selenv/ReceiverClustering-v1"


def _env() -> gym.Env:
    return gym.make(ENV, n_agents=12, horizon=20)


def test_budgeted_greedy_costs_k_edits_and_takes_the_best_of_them() -> None:
    env = _env()
    env.reset(seed=0)
    bank = env.unwrapped.bank
    before = bank.n_cost_evaluations
    rng = np.random.default_rng(5)
    action, delta = best_edit(bank, env.unwrapped.max_size, True, 8, rng)
    assert bank.n_cost_evaluations - before == 8
    # the same draw, costed independently: the choice is the best improving one of those 8
    allowed = np.flatnonzero(edit_mask(bank.labels, env.unwrapped.max_size)[1:]) + 1
    sample = np.sort(np.random.default_rng(5).choice(allowed, size=8, replace=False))
    d = edit_cost_changes(bank, sample)
    if d.min() < 0:
        assert action == sample[np.argmin(d)] and delta == d.min()
    else:
        assert (action, delta) == (0, 0.0)
    full_action, full_delta = best_edit(bank, env.unwrapped.max_size)
    assert full_delta <= delta  # the unrestricted search is at least as good


def test_budgeted_greedy_is_seeded_and_counts_its_evaluations() -> None:
    returns, evals = [], []
    for _ in range(2):
        env = _env()
        agent = make("greedy:every=1:max_evaluations=8", env_id=ENV)
        obs, info = env.reset(seed=3)
        agent.reset(env, seed=3)
        ret, done, steps = 0.0, False, 0
        while not done:
            obs, r, term, trunc, info = env.step(agent.act(obs, info))
            ret += r
            steps += 1
            done = term or trunc
        returns.append(ret)
        evals.append(info["cost_evaluations"] / steps)
    assert returns[0] == returns[1]
    assert evals[0] <= 8.0 and evals[0] > 4.0


@pytest.mark.parametrize("bad", [0, -1, 2.5, True, "8"])
def test_budgeted_greedy_rejects_bad_budgets(bad: object) -> None:
    with pytest.raises((TypeError, ValueError), match="max_evaluations"):
        GreedyMoveAgent(max_evaluations=bad)  # type: ignore[arg-type]
