"""receiver_clustering_v1 (PettingZoo): API/seed tests, resolution rule, rewards, errors."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import data_equivalence
from hypothesis import given, settings
from hypothesis import strategies as st
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test, state_test

import selenv  # noqa: F401  (registers the Gymnasium ids)
from selenv.families.clustering.labels import random_feasible_clustering
from selenv.families.clustering.scenario import canonical_labels
from selenv.multiagent import receiver_clustering_v1 as rc

SMALL: dict[str, Any] = {"n_agents": 7, "n_max_states": 14, "horizon": 10, "tau": 5}  # max_size 3
FREE: dict[str, Any] = {
    "n_agents": 6,
    "n_max_states": None,
    "horizon": 8,
    "tau": 5,
}  # every action valid


def _names(n: int) -> list[str]:
    return [f"receiver_{i}" for i in range(n)]


def _masked_actions(
    env: rc.ReceiverClusteringParallelEnv, obs: dict[str, Any], rng: np.random.Generator
) -> dict[str, int]:
    return {a: int(rng.choice(np.flatnonzero(obs[a]["action_mask"]))) for a in env.agents}


def _order(env: rc.ReceiverClusteringParallelEnv) -> np.ndarray:
    assert env.last_order is not None
    return env.last_order


def _stay(env: rc.ReceiverClusteringParallelEnv) -> dict[str, int]:
    return {a: int(env.bank.labels[i]) for i, a in enumerate(env.possible_agents)}


# -- PettingZoo conformance ----------------------------------------------------------------------
@pytest.mark.parametrize("kw", [SMALL, FREE])
def test_parallel_api(kw: dict[str, Any]) -> None:
    parallel_api_test(rc.parallel_env(**kw), num_cycles=20)


def test_parallel_seed_test_with_unmasked_sampling() -> None:
    # parallel_seed_test samples *unmasked* actions: with n_max_states=None every label is valid
    parallel_seed_test(lambda: rc.parallel_env(**FREE))


def test_aec_api_and_state() -> None:
    api_test(rc.env(**SMALL), num_cycles=15)
    # state_test also samples unmasked actions
    state_test(rc.env(**FREE), rc.parallel_env(**FREE), num_cycles=5)


def _trajectory(seed: int, kw: dict[str, Any] = SMALL, steps: int = 6) -> list[Any]:
    env = rc.parallel_env(**kw)
    obs, infos = env.reset(seed=seed)
    rng = np.random.default_rng(0)  # same agent policy for both runs
    out: list[Any] = [(obs, infos)]
    for _ in range(steps):
        obs, rew, terms, truncs, infos = env.step(_masked_actions(env, obs, rng))
        out.append((obs, rew, infos, _order(env).copy(), env.state()))
    return out


def test_same_seed_same_trajectory_with_masked_actions() -> None:
    a, b, c = _trajectory(3), _trajectory(3), _trajectory(4)
    assert data_equivalence(a, b)
    assert not data_equivalence(a, c)


def test_observations_masks_state_and_termination() -> None:
    env = rc.parallel_env(**SMALL)
    n = SMALL["n_agents"]
    assert env.possible_agents == _names(n)
    obs, infos = env.reset(seed=1, options={"clustering": [0, 0, 0, 1, 1, 2, 2]})
    assert all(info["accepted"] for info in infos.values())  # reset: nothing refused
    for t in range(SMALL["horizon"]):
        for i, a in enumerate(env.agents):
            o = obs[a]
            assert env.observation_space(a).contains(o)
            assert np.array_equal(o["self"], np.eye(n, dtype=np.int8)[i])
            assert np.array_equal(o["assignment"], env.bank.labels)
            assert o["action_mask"].dtype == np.int8 and o["action_mask"].any()
            assert np.array_equal(o["action_mask"].astype(bool), env.action_mask(a))
            assert "action_mask" not in infos[a]  # observed only (TorchRL reads one place)
        mask = env.action_mask("receiver_3")
        sizes = np.bincount(env.bank.labels, minlength=n)
        own = env.bank.labels[3]
        assert np.array_equal(mask, (sizes < 3) | (np.arange(n) == own))
        state = env.state()
        assert env.state_space.contains(state)
        assert np.array_equal(state[:n], env.bank.labels)
        np.testing.assert_allclose(state[n:], env.bank.receiver_position_variance(), rtol=1e-6)
        obs, rew, terms, truncs, infos = env.step(_stay(env))
        done = t == SMALL["horizon"] - 1
        assert set(rew) == set(terms) == set(_names(n))
        assert all(v is done for v in terms.values()) and not any(truncs.values())
    assert env.agents == []
    assert obs["receiver_0"]["time"][0] == 1.0
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})


# -- the resolution rule ---------------------------------------------------------------------------
def test_three_receivers_compete_for_one_free_place() -> None:
    # max_size 3; cluster 0 = {0, 1} has room for one; receivers 2, 4, 6 all choose label 0
    labels = [0, 0, 1, 1, 2, 2, 3]
    winners = []
    for seed in range(12):
        env = rc.parallel_env(**SMALL)
        env.reset(seed=seed, options={"clustering": labels})
        actions = _stay(env) | {f"receiver_{i}": 0 for i in (2, 4, 6)}
        _obs, _rew, _terms, _truncs, infos = env.step(actions)
        acc = {i for i in range(7) if infos[f"receiver_{i}"]["accepted"]}
        movers = [i for i in (2, 4, 6) if i in acc]
        assert len(movers) == 1
        assert acc == {0, 1, 3, 5} | set(movers)  # staying is always accepted
        first = next(int(i) for i in _order(env) if i in (2, 4, 6))
        assert movers == [first]  # the seeded order decides
        new = env.bank.labels
        assert np.flatnonzero(new == new[0]).tolist() == sorted([0, 1, first])
        assert np.bincount(new).max() <= 3
        winners.append(first)
        # same seed, same winner
        env.reset(seed=seed, options={"clustering": labels})
        *_, infos2 = env.step(actions)
        assert data_equivalence(infos2, infos)
    assert len(set(winners)) > 1


def test_receivers_choosing_one_unused_label_form_a_new_cluster() -> None:
    env = rc.parallel_env(n_agents=6, n_max_states=10, horizon=5)  # max_size 2
    env.reset(seed=0, options={"clustering": [0, 0, 1, 1, 2, 2]})
    actions = _stay(env) | {f"receiver_{i}": 5 for i in (0, 2, 4)}
    *_, infos = env.step(actions)
    movers = [i for i in (0, 2, 4) if infos[f"receiver_{i}"]["accepted"]]
    first_two = [int(i) for i in _order(env) if i in (0, 2, 4)][:2]
    assert sorted(movers) == sorted(first_two)  # only max_size fit, in the seeded order
    new = env.bank.labels
    assert new[first_two[0]] == new[first_two[1]]
    assert sorted(np.bincount(new).tolist()) == [1, 1, 2, 2]
    assert infos["receiver_1"]["n_clusters"] == 4


def test_leaving_frees_room_only_for_receivers_visited_later() -> None:
    labels = np.array([0, 0, 1, 1, 2, 2, 3])  # max_size 3: cluster 0 has one free place
    targets = np.array([6, 0, 0, 1, 2, 0, 3])  # 0 leaves to a new cluster; 2 and 5 join 0
    new, acc = rc.resolve_moves(labels, targets, 3, np.array([0, 1, 2, 3, 4, 5, 6]))
    assert acc.all() and new.tolist() == [6, 0, 0, 1, 2, 0, 3]
    new, acc = rc.resolve_moves(labels, targets, 3, np.array([2, 5, 0, 1, 3, 4, 6]))
    assert acc.tolist() == [True, True, True, True, True, False, True]
    assert new.tolist() == [6, 0, 0, 1, 2, 2, 3]


@st.composite
def _instance(draw: Any) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    n = draw(st.integers(2, 9))
    max_size = draw(st.integers(1, n))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    labels = canonical_labels(random_feasible_clustering(n, max_size, rng))
    targets = np.array(draw(st.lists(st.integers(0, n - 1), min_size=n, max_size=n)))
    return labels, targets, max_size, rng.permutation(n)


@settings(max_examples=200, deadline=None)
@given(_instance())
def test_resolution_is_always_feasible(
    inst: tuple[np.ndarray, np.ndarray, int, np.ndarray],
) -> None:
    labels, targets, max_size, order = inst
    new, acc = rc.resolve_moves(labels, targets, max_size, order)
    assert np.bincount(new).max() <= max_size
    stay = targets == labels
    assert acc[stay].all()
    assert np.array_equal(new[acc], targets[acc])
    assert np.array_equal(new[~acc], labels[~acc])


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(0, 2**31 - 1))
def test_env_steps_stay_feasible_and_follow_the_rule(seed: int, policy_seed: int) -> None:
    env = rc.parallel_env(n_agents=8, n_max_states=14, horizon=4, tau=3)  # max_size 3
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(policy_seed)
    while env.agents:
        before = env.bank.labels.copy()
        actions = _masked_actions(env, obs, rng)
        obs, rew, _terms, _truncs, infos = env.step(actions)
        targets = np.array([actions[a] for a in env.possible_agents])
        ref, acc = rc.resolve_moves(before, targets, 3, _order(env))
        assert np.array_equal(env.bank.labels, canonical_labels(ref))
        assert [infos[a]["accepted"] for a in env.possible_agents] == acc.tolist()
        assert acc[targets == before].all()
        assert np.bincount(env.bank.labels).max() <= 3
        J = env.bank.cost().J
        assert set(rew.values()) == {-J}
        assert all(info["objective"] == J for info in infos.values())


# -- consistency with the single-agent env -------------------------------------------------------
def _actions_for(current: np.ndarray, target: np.ndarray, max_size: int) -> dict[str, int]:
    """Labels that turn ``current`` into ``target`` whatever the visiting order (asserted)."""
    m = int(current.max()) + 1
    fresh = iter(range(m, current.size))
    chosen: dict[int, int] = {}
    for c in range(int(target.max()) + 1):
        members = np.flatnonzero(target == c)
        olds, counts = np.unique(current[members], return_counts=True)
        free = [
            int(o) for o in olds[np.argsort(-counts, kind="stable")] if o not in chosen.values()
        ]
        chosen[c] = free[0] if free else next(fresh)
        joiners = int(np.sum(current[members] != chosen[c]))
        assert np.sum(current == chosen[c]) + joiners <= max_size  # order-independent
    return {f"receiver_{i}": chosen[int(target[i])] for i in range(current.size)}


@pytest.mark.parametrize(
    ("kw", "options"),
    [
        ({"n_agents": 6, "n_max_states": 10}, {"clustering": np.arange(6)}),  # max_size 2
        ({"n_agents": 8, "n_max_states": 14}, None),  # max_size 3, same random initial clustering
        ({"n_agents": 6, "n_max_states": None}, None),
    ],
)
def test_shared_reward_matches_single_agent_env(
    kw: dict[str, Any], options: dict[str, Any] | None
) -> None:
    horizon = 12
    kw = kw | {"horizon": horizon, "tau": 4}
    n = kw["n_agents"]
    ma = rc.parallel_env(**kw)
    sa = gym.make("selenv/ReceiverClustering-v1", **kw)
    ma.reset(seed=11, options=options)
    sa.reset(seed=11, options=options)
    sa_raw: Any = sa.unwrapped
    bank_sa = sa_raw.bank
    assert ma.problem is not None
    assert np.array_equal(ma.bank.labels, bank_sa.labels)
    np.testing.assert_array_equal(ma.problem.sigma, sa_raw.problem.sigma)
    rng = np.random.default_rng(5)
    max_size = ma.max_size
    for t in range(horizon):
        if kw["n_max_states"] is None:
            target = canonical_labels(rng.integers(0, n, n))
        elif t % 2 == 0:  # via singletons, so that every target is reachable in one step
            target = np.arange(n)
        else:
            target = canonical_labels(random_feasible_clustering(n, max_size, rng))
        _obs, rew, terms, _truncs, infos = ma.step(_actions_for(ma.bank.labels, target, max_size))
        _obs_sa, r_sa, term_sa, _, info_sa = sa.step(target)
        assert all(info["accepted"] for info in infos.values())
        assert np.array_equal(ma.bank.labels, target)
        assert np.array_equal(bank_sa.labels, target)
        assert set(rew) == set(_names(n)) and len(set(rew.values())) == 1
        r = rew["receiver_0"]
        assert r == -ma.bank.cost().J == -infos["receiver_0"]["objective"]
        assert r == pytest.approx(r_sa, rel=1e-12)
        assert infos["receiver_0"]["objective"] == pytest.approx(info_sa["objective"], rel=1e-12)
        assert all(v is term_sa for v in terms.values())
    assert ma.agents == []


# -- bad input -------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"n_agents": 0}, "n_agents"),
        ({"n_max_states": 3}, "n_max_states"),
        ({"noise_correlation": 1.0}, "noise_correlation"),
        ({"weights": (0, 0, 0)}, "weights"),
        ({"sigma": np.ones((3, 2))}, "sigma"),
        ({"horizon": 0}, "horizon"),
        ({"initial": "all"}, "initial"),
        ({"render_mode": "ansi"}, "render_mode"),
    ],
)
def test_constructor_errors(kw: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        rc.parallel_env(**{"n_agents": 6} | kw)


def test_step_errors() -> None:
    env = rc.parallel_env(**SMALL, invalid_action="raise")
    with pytest.raises(RuntimeError, match="reset"):
        _ = env.bank
    with pytest.raises(RuntimeError, match="reset"):
        env.state()
    with pytest.raises(ValueError, match="options"):
        env.reset(seed=0, options={"clustering": [0] * 7})  # one cluster of 7 > 3
    env.reset(seed=0, options={"clustering": [0, 0, 0, 1, 1, 2, 2]})
    stay = _stay(env)
    with pytest.raises(ValueError, match=r"missing \['receiver_6'\]"):
        env.step({a: v for a, v in stay.items() if a != "receiver_6"})
    with pytest.raises(ValueError, match="unexpected"):
        env.step(stay | {"receiver_9": 0})
    with pytest.raises(ValueError, match=r"receiver_2.*label 7 is out of range"):
        env.step(stay | {"receiver_2": 7})
    with pytest.raises(ValueError, match=r"receiver_2.*label -1 is out of range"):
        env.step(stay | {"receiver_2": -1})
    with pytest.raises(ValueError, match=r"action 0 of receiver_4 is invalid: masked: label 0"):
        env.step(stay | {"receiver_4": 0})  # cluster 0 is full
    with pytest.raises(TypeError, match=r"receiver_1.*1\.0"):
        env.step(stay | {"receiver_1": 1.0})
    with pytest.raises(TypeError, match=r"receiver_1.*True"):
        env.step(stay | {"receiver_1": True})
    assert env.bank.k == 0  # nothing was applied
    _obs, _rew, _terms, _truncs, infos = env.step(stay | {"receiver_0": 0, "receiver_3": 6})
    assert all(info["accepted"] for info in infos.values())
    assert env.bank.k == 1 and int(env.bank.labels.max()) == 3
