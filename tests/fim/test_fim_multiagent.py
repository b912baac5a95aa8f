"""selenv.multiagent.fim_selection_v0: PettingZoo API/seed tests, modes, rewards, errors."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test

from selenv.agents.fim_solvers import cooperative_greedy, greedy_whitened
from selenv.core.information import logdet_objective
from selenv.families.fim.agents import CooperativeGreedyPolicy
from selenv.multiagent import fim_selection_v0

KW = {"n_candidates": 10, "budgets": 3}


@pytest.mark.parametrize("mode", ["independent", "cooperative"])
def test_parallel_api_and_seed(mode):
    parallel_api_test(fim_selection_v0.parallel_env(mode=mode, **KW), num_cycles=50)
    parallel_seed_test(lambda: fim_selection_v0.parallel_env(mode=mode, **KW))


def test_aec_api():
    api_test(fim_selection_v0.env(**KW), num_cycles=20)


def _play(env, seed):
    obs, infos = env.reset(seed=seed)
    pol = CooperativeGreedyPolicy()
    total = 0.0
    while env.agents:
        obs, rew, _terms, _truncs, infos = env.step(pol.act(obs, env.agents))
        total += next(iter(rew.values()))
        assert len(set(rew.values())) == 1  # shared reward
    return total, next(iter(infos.values()))["objective"]


def test_independent_mode_is_per_agent_greedy_and_reward_is_centre_gain():
    env = fim_selection_v0.parallel_env(mode="independent", **KW)
    total, objective = _play(env, 4)
    P = env.problem
    picks = []
    for i in range(2):
        pool = P.pool(i)
        sel = greedy_whitened(P.Q0, P.G[pool], 3)
        picks += [int(pool[k]) for k in sel.indices]
    assert objective == pytest.approx(logdet_objective(P.Q0, P.G, picks), rel=1e-9)
    assert total == pytest.approx(objective, rel=1e-9)


def test_cooperative_mode_is_the_papers_sequential_scheme():
    env = fim_selection_v0.parallel_env(mode="cooperative", **KW)
    obs, infos = env.reset(seed=7)
    seen = []
    pol = CooperativeGreedyPolicy()
    while env.agents:
        assert env.agents == ["agent_0", "agent_1"]  # everyone present; the waiting one passes
        acting = tuple(a for a in env.agents if infos[a]["on_turn"])
        assert all(obs[a]["on_turn"][0] == (a in acting) for a in env.agents)
        for a in env.agents:
            if a not in acting:  # a waiting agent may only pass (action 0)
                mask = obs[a]["action_mask"]
                assert "action_mask" not in infos[a]  # observed only (TorchRL reads one place)
                assert mask[0] and not mask[1:].any()
        seen.append(acting)
        obs, *_, infos = env.step(pol.act(obs, env.agents))
    assert seen == [("agent_0",)] * 3 + [("agent_1",)] * 3
    P = env.problem
    pools = [(P.H[P.pool(i)], P.R[P.pool(i)]) for i in range(2)]
    ref = cooperative_greedy(P.Q0, pools, [3, 3], mode="cooperative")
    assert infos["agent_1"]["objective"] == pytest.approx(ref.objective, rel=1e-9)


def test_cooperative_beats_independent_on_average():
    diffs = []
    for seed in range(6):
        ind = _play(fim_selection_v0.parallel_env(mode="independent", **KW), seed)[1]
        coop = _play(fim_selection_v0.parallel_env(mode="cooperative", **KW), seed)[1]
        diffs.append(coop - ind)
    assert np.mean(diffs) > 0


def test_unequal_budgets_and_errors():
    env = fim_selection_v0.parallel_env(
        n_candidates=10, budgets=[1, 3], mode="independent", invalid_action="raise"
    )
    obs, _ = env.reset(seed=0)
    _obs, _rew, terms, _truncs, infos = env.step({"agent_0": 0, "agent_1": 0})
    assert env.agents == ["agent_0", "agent_1"] and not any(terms.values())
    assert not infos["agent_0"]["on_turn"] and infos["agent_1"]["on_turn"]
    with pytest.raises(ValueError, match="missing"):
        env.step({})
    with pytest.raises(ValueError, match="action 0 of agent_1 is invalid: masked"):
        env.step({"agent_0": 0, "agent_1": 0})
    before = env.state().copy()
    env.step({"agent_0": 5, "agent_1": 1})  # agent_0 waits: its 5 is ignored
    after = env.state()
    n = len(after) // 2 - 2  # state = gains (N), selected (N), budgets left (2), turns (2)
    assert after[n : 2 * n].sum() == before[n : 2 * n].sum() + 1  # one more pick: agent_1's
    with pytest.raises(ValueError, match="budget"):
        fim_selection_v0.parallel_env(n_candidates=2, budgets=[1, 99])
    with pytest.raises(ValueError, match="mode"):
        fim_selection_v0.parallel_env(mode="joint")
