"""The sequential ReceiverClustering env: one ``Discrete`` action per receiver, an exact mask.

Checked against independent truth: the clusterings its allowed action sequences build are
enumerated on small instances and compared with every set partition that meets the state
limit (brute force); an assignment agent played through ``SequentialAgent`` reproduces its own
episode on the assignment env (same clusterings, objectives and return).
"""

from __future__ import annotations

import itertools

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import selenv  # noqa: F401  (registers the agents)
from selenv.agents import make
from selenv.envs.actions import MASKED
from selenv.families.clustering.env import ReceiverClusteringEnv
from selenv.families.clustering.labels import canonicalize
from selenv.families.clustering.sequential import (
    ReceiverClusteringSequentialEnv,
    SequentialAgent,
    placement_actions,
)

SMALL = {"n_agents": 6, "horizon": 4}


def _partitions(n: int, max_size: int) -> set[tuple[int, ...]]:
    """Every set partition of ``range(n)`` with blocks of at most ``max_size`` (canonical)."""
    out = set()
    for labels in itertools.product(range(n), repeat=n):
        if np.bincount(labels).max() <= max_size:
            out.add(tuple(canonicalize(np.array(labels)).tolist()))
    return out


def _reachable(env: ReceiverClusteringSequentialEnv) -> set[tuple[int, ...]]:
    """Every clustering that allowed action sequences build (depth-first over the masks)."""
    n, found = env.n, set()

    def walk(prefix: list[int]) -> None:
        env._open()
        for a in prefix:  # replay the placements (state of the partial clustering only)
            i = env.receiver
            lead = i if a == i else int(env._new[a])
            env._new[i], env._sizes[lead] = lead, env._sizes[lead] + 1
            env._receiver = i + 1
        if len(prefix) == n:
            found.add(tuple(canonicalize(env._new.copy()).tolist()))
            return
        for a in np.flatnonzero(env.action_masks()).tolist():
            walk([*prefix, a])

    walk([])
    return found


@pytest.mark.parametrize(("n", "n_max_states"), [(4, 10), (5, 10), (5, 14), (5, None)])
def test_allowed_sequences_build_exactly_the_feasible_clusterings(n, n_max_states) -> None:
    env = ReceiverClusteringSequentialEnv(n_agents=n, n_max_states=n_max_states, horizon=2)
    env.reset(seed=0)
    assert _reachable(env) == _partitions(n, env.max_size)
    assert env.max_size < n or n_max_states is None  # the limit binds where it is set


def test_gymnasium_check_env_and_spaces() -> None:
    env = ReceiverClusteringSequentialEnv(**SMALL)
    check_env(env, skip_render_check=True)
    obs, info = env.reset(seed=1)
    assert env.observation_space.contains(obs) and env.action_space.n == 6
    assert obs["receiver"].tolist() == [1, 0, 0, 0, 0, 0] and info["placing"] == 0
    assert env.action_masks().tolist() == [True] + [False] * 5  # receiver 0 opens a cluster


@pytest.mark.parametrize("agent_name", ["greedy", "ga", "singletons", "fixed_random", "rollout"])
def test_an_assignment_agent_replays_its_episode(agent_name: str) -> None:
    seq = ReceiverClusteringSequentialEnv(**SMALL)
    ref = gym.make("selenv/ReceiverClustering-v1", **SMALL).unwrapped
    env_id = "selenv/ReceiverClustering-v1"
    agent, ref_agent = SequentialAgent(make(agent_name, env_id)), make(agent_name, env_id)
    obs, info = seq.reset(seed=7)
    ref_obs, ref_info = ref.reset(seed=7)
    agent.reset(seq, seed=7)
    ref_agent.reset(ref, seed=7)
    ret, ref_ret, objectives, ref_objectives, steps = 0.0, 0.0, [], [], 0
    done = ref_done = False
    while not done:
        obs, r, done, trunc, info = seq.step(agent.act(obs, info))
        assert not info["invalid_action"]  # the canonical placements are always allowed
        ret += r
        steps += 1
        if info["placing"] == 0:  # a filter step ran
            objectives.append(info["objective"])
    while not ref_done:
        ref_obs, r, ref_done, _, ref_info = ref.step(ref_agent.act(ref_obs, ref_info))
        ref_ret += r
        ref_objectives.append(ref_info["objective"])
    assert steps == SMALL["horizon"] * 6 == seq.max_episode_steps
    np.testing.assert_array_equal(seq.bank.labels, ref.bank.labels)
    np.testing.assert_allclose(objectives, ref_objectives, rtol=1e-12)
    np.testing.assert_allclose(ret, ref_ret, rtol=1e-12)


def test_placement_actions_are_canonical() -> None:
    assert placement_actions(np.array([2, 0, 2, 1, 0])).tolist() == [0, 1, 0, 3, 1]
    assert placement_actions(np.array([0, 0, 0])).tolist() == [0, 0, 0]


def test_noop_voids_the_filter_steps_clustering() -> None:
    env = ReceiverClusteringSequentialEnv(invalid_action_penalty=-2.0, **SMALL)
    ref = ReceiverClusteringEnv(**SMALL)
    env.reset(seed=3)
    ref.reset(seed=3)
    before = env.bank.labels.copy()
    _, r0, *_, info = env.step(3)  # receiver 0 cannot join receiver 3 (not placed yet)
    assert info["invalid_action"] and info["invalid_code"] == MASKED and r0 == -2.0
    rewards = [env.step(i)[1] for i in range(1, 5)]  # receivers 1..4 open clusters: allowed
    _, r_last, *_ = env.step(5)
    _, r_ref, *_ = ref.step(before)  # the assignment env keeping the clustering
    np.testing.assert_array_equal(env.bank.labels, before)
    assert rewards == [0.0] * 4 and r_last == pytest.approx(r_ref, rel=1e-12)


def test_terminate_and_raise_modes_and_out_of_space_actions() -> None:
    env = ReceiverClusteringSequentialEnv(invalid_action="terminate", **SMALL)
    env.reset(seed=0)
    _, r, terminated, _, info = env.step(2)
    assert terminated and info["invalid_action"] and r == 0.0
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)
    env = ReceiverClusteringSequentialEnv(invalid_action="raise", **SMALL)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="receiver 4 is not placed yet"):
        env.step(4)
    with pytest.raises(ValueError, match="out of range"):
        env.step(6)
    with pytest.raises(TypeError, match="integer"):
        env.step(1.0)
    with pytest.raises(TypeError, match="action_mode"):
        ReceiverClusteringSequentialEnv(action_mode="edit")


def test_info_schema_is_fixed_over_an_episode() -> None:
    env = ReceiverClusteringSequentialEnv(**SMALL)
    _, info = env.reset(seed=2)
    want = {k: (np.asarray(v).dtype.kind, np.asarray(v).shape) for k, v in info.items()}
    rng, done = np.random.default_rng(0), False
    while not done:
        mask = env.action_masks()
        _, _, done, _, info = env.step(int(np.argmax(rng.random(mask.shape) + mask)))
        got = {k: (np.asarray(v).dtype.kind, np.asarray(v).shape) for k, v in info.items()}
        assert got == want and all(kind in "biuf" for kind, _ in got.values())


V1, V2 = "selenv/ReceiverClustering-v1", "selenv/ReceiverClustering-v2"


def test_the_registry_plays_every_v1_agent_on_v2_through_the_adapter() -> None:
    from selenv.agents import AGENTS, agents_for
    from selenv.agents.learned import learned_target, list_note

    assert agents_for(V2) == agents_for(V1)
    for name in agents_for(V1):
        a1, a2 = AGENTS[name][V1], AGENTS[name][V2]
        assert (a2.learned, a2.default, a2.deprecated) == (a1.learned, a1.default, a1.deprecated)
        assert a2.description == a1.description
    assert isinstance(make("greedy", V2), SequentialAgent)
    assert not isinstance(make("greedy", V1), SequentialAgent)
    assert learned_target(V2) == learned_target(V1) is not None
    assert list_note("learned", V2) == f"{list_note('learned', V1)} (on {V1}: the same episodes)"
    with pytest.raises(ValueError, match="no option"):
        make("greedy", V2, no_such_option=1)  # the wrapped agent's options are checked


@pytest.mark.parametrize("agent_name", ["greedy", "learned"])
def test_an_agent_made_for_v2_plays_v1s_episode(agent_name: str) -> None:
    kw = {"horizon": 6}
    env, ref = gym.make(V2, **kw), gym.make(V1, **kw)
    returns = []
    for e, env_id in ((env, V2), (ref, V1)):
        agent = make(agent_name, env_id)
        obs, info = e.reset(seed=4)
        agent.reset(e, seed=4)
        total, done = 0.0, False
        while not done:
            obs, r, done, trunc, info = e.step(agent.act(obs, info))
            total += r
        returns.append((total, info["objective"], info["cost_evaluations"]))
    np.testing.assert_allclose(returns[0][:2], returns[1][:2], rtol=1e-12)
    assert returns[0][2] == returns[1][2]  # the same searches ran
