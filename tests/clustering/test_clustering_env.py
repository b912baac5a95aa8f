"""selenv/ReceiverClustering-v1: Gymnasium/SB3 checks, encodings, determinism, bad input."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from hypothesis import given, settings
from hypothesis import strategies as st
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import selenv  # noqa: F401
from selenv.families.clustering.env import (
    apply_edit,
    edit_action_count,
    edit_cost_changes,
    edit_mask,
)
from selenv.families.clustering.labels import random_feasible_clustering
from selenv.families.clustering.scenario import canonical_labels

ENV_ID = "selenv/ReceiverClustering-v1"


def test_gymnasium_and_sb3_check_env_assignment_mode() -> None:
    # unconstrained: every sampled assignment is feasible, so the checkers' random steps are valid
    env = gym.make(ENV_ID, n_agents=6, n_max_states=None, horizon=8)
    gym_check_env(env.unwrapped, skip_render_check=True)
    sb3_check_env(gym.make(ENV_ID, n_agents=6, n_max_states=None, horizon=8).unwrapped)


def _rollout(env, seed, policy):
    obs, info = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    traj = []
    done = False
    while not done:
        action = policy(obs, info, rng)
        obs, reward, term, trunc, info = env.step(action)
        assert env.observation_space.contains(obs)
        assert reward == pytest.approx(-info["objective"])
        traj.append((obs["assignment"].copy(), reward))
        done = term or trunc
    return traj


def _masked_edit(obs, info, rng):
    return int(rng.choice(np.flatnonzero(info["action_mask"])))


def test_edit_mode_rollout_is_feasible_deterministic_and_masks_agree() -> None:
    env = gym.make(ENV_ID, n_agents=9, horizon=12, action_mode="edit")
    a = _rollout(env, 3, _masked_edit)
    b = _rollout(env, 3, _masked_edit)
    assert len(a) == 12
    for (la, ra), (lb, rb) in zip(a, b, strict=True):
        np.testing.assert_array_equal(la, lb)
        assert ra == rb
        assert np.bincount(la).max() <= 3  # N_max = 14 -> at most 3 receivers per cluster
    obs, info = env.reset(seed=0)
    np.testing.assert_array_equal(obs["action_mask"], env.unwrapped.action_masks())
    np.testing.assert_array_equal(info["action_mask"], obs["action_mask"])
    assert obs["action_mask"].shape == (edit_action_count(9),) and obs["action_mask"][0] == 1


def test_assignment_mode_same_seed_same_trajectory_and_sigma() -> None:
    env = gym.make(ENV_ID, horizon=6)
    obs1, _ = env.reset(seed=5)
    sigma1 = env.unwrapped.problem.sigma.copy()
    keep = lambda obs, info, rng: obs["assignment"]  # noqa: E731
    t1 = _rollout(env, 5, keep)
    t2 = _rollout(env, 5, keep)
    np.testing.assert_array_equal(env.unwrapped.problem.sigma, sigma1)
    assert [r for _, r in t1] == [r for _, r in t2]
    env.reset(seed=6)
    assert not np.array_equal(env.unwrapped.problem.sigma, sigma1)
    sizes = np.bincount(obs1["assignment"])
    assert np.all(sizes == 3)  # the random start fills 10 clusters of 3


def test_relabelled_action_is_no_change_and_reward_is_minus_cost() -> None:
    env = gym.make(ENV_ID, n_agents=6, horizon=5)
    obs, info = env.reset(seed=0, options={"clustering": [0, 0, 1, 1, 2, 2]})
    bank = env.unwrapped.bank
    obs, r, *_, info = env.step(np.array([5, 5, 3, 3, 4, 4]))
    assert not info["changed"] and info["k"] == 1
    assert r == pytest.approx(-bank.cost().J) and info["objective"] == pytest.approx(bank.cost().J)
    target = np.array([0, 1, 0, 2, 1, 2])
    expected = bank.evaluate(target)[0]  # Algorithm 1 cost at k = 1, before the step
    obs, r, *_, info = env.step(target)
    assert info["changed"]
    np.testing.assert_array_equal(obs["assignment"], canonical_labels(target))
    assert bank.k == 2 and info["objective"] != pytest.approx(expected)  # one more step since


def test_episode_ends_at_horizon() -> None:
    env = gym.make(ENV_ID, n_agents=4, horizon=3)
    obs, _ = env.reset(seed=0)
    flags = [env.step(obs["assignment"])[2] for _ in range(3)]
    assert flags == [False, False, True]
    with pytest.raises(RuntimeError, match="reset"):
        env.unwrapped.step(obs["assignment"])


def test_infeasible_or_bad_actions_are_clear_errors() -> None:
    env = gym.make(ENV_ID, n_agents=6, horizon=5, invalid_action="raise")
    env.reset(seed=0)
    with pytest.raises(
        ValueError, match=r"infeasible: cluster 0 \(receivers \[0, 1, 2, 3\]\).*n_max_states = 14"
    ):
        env.step(np.array([0, 0, 0, 0, 1, 1]))
    with pytest.raises(ValueError, match=r"shape \(6,\)"):
        env.step(np.array([0, 1, 2]))
    with pytest.raises(ValueError, match="integer labels"):
        env.step(np.array([0.5, 1, 2, 3, 4, 5]))
    edit = gym.make(ENV_ID, n_agents=6, horizon=5, action_mode="edit", invalid_action="raise")
    edit.reset(seed=0, options={"clustering": [0, 0, 0, 1, 1, 1]})
    with pytest.raises(
        ValueError, match=r"action 2 is invalid: masked: receiver 0 -> cluster of 1"
    ):
        edit.step(2)  # 0 joins 1's cluster: already together
    with pytest.raises(ValueError, match="out of range"):
        edit.step(edit_action_count(6))
    with pytest.raises(TypeError, match="integer"):
        edit.step(1.0)
    with pytest.raises(ValueError, match=r"options\['clustering'\]: cluster"):
        edit.reset(seed=0, options={"clustering": [0, 0, 0, 0, 1, 1]})
    with pytest.raises(ValueError, match="unknown reset options"):
        edit.reset(seed=0, options={"foo": 1})


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"sigma": -np.ones((30, 2))}, "sigma must be finite and > 0"),
        ({"noise_correlation": 1.0}, r"\[0, 1\)"),
        ({"n_max_states": 4}, "below one receiver's state count"),
        ({"horizon": 0}, "horizon"),
        ({"action_mode": "moves"}, "action_mode"),
        ({"initial": "best"}, "initial"),
    ],
)
def test_bad_kwargs(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        gym.make(ENV_ID, **kwargs)


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(2, 9),
    cap=st.integers(1, 4),
    seed=st.integers(0, 2**31 - 1),
)
def test_edit_mask_allows_exactly_the_feasible_changes(n: int, cap: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    labels = canonical_labels(random_feasible_clustering(n, cap, rng))
    mask = edit_mask(labels, cap)
    assert mask[0]
    for a in range(1, edit_action_count(n)):
        new = canonical_labels(apply_edit(labels, a))
        feasible = np.bincount(new).max() <= cap
        changed = not np.array_equal(new, labels)
        assert bool(mask[a]) == (feasible and changed), (labels, a)


def test_maskable_ppo_learns_on_edit_mode_smoke() -> None:
    from sb3_contrib import MaskablePPO

    env = gym.make(ENV_ID, n_agents=6, horizon=6, action_mode="edit")
    model = MaskablePPO("MultiInputPolicy", env, n_steps=32, batch_size=32, n_epochs=1, seed=0)
    model.learn(64)
    obs, info = env.reset(seed=1)
    action, _ = model.predict(obs, action_masks=env.unwrapped.action_masks())
    assert info["action_mask"][int(action)]


@pytest.mark.parametrize("preset", ["paper", "multipath"])
def test_edit_cost_changes_equal_full_evaluations_of_every_allowed_edit(preset: str) -> None:
    env = gym.make(ENV_ID, n_agents=8, horizon=30, tau=5, preset=preset)
    env.reset(seed=2, options={"clustering": [0, 0, 0, 1, 1, 2, 3, 3]})  # full, room, singleton
    base = env.unwrapped
    for _ in range(9):
        env.step(base.bank.labels)
    bank = base.bank
    actions = np.flatnonzero(edit_mask(bank.labels, base.max_size))
    d = edit_cost_changes(bank, actions)
    assert d[0] == 0.0 and actions.size > 30
    full = bank.evaluate(np.stack([apply_edit(bank.labels, int(a)) for a in actions[1:]]))
    np.testing.assert_allclose(d[1:], full - bank.cost().J, rtol=1e-9, atol=1e-13)


def test_assignment_mode_observes_its_mask_and_v0_does_not() -> None:
    env = gym.make("selenv/ReceiverClustering-v1", n_agents=8, horizon=5)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    np.testing.assert_array_equal(obs["action_mask"], env.unwrapped.action_masks())
    np.testing.assert_array_equal(obs["action_mask"], info["action_mask"])
    obs, *_ = env.step(obs["assignment"])
    np.testing.assert_array_equal(obs["action_mask"], env.unwrapped.action_masks())
    with pytest.warns(DeprecationWarning):
        old = gym.make("selenv/ReceiverClustering-v0", n_agents=8, horizon=5)
    obs0, _ = old.reset(seed=0)
    assert "action_mask" not in obs0 and "action_mask" not in old.observation_space.spaces
    with pytest.raises(TypeError, match="obs_mask"):
        gym.make("selenv/ReceiverClustering-v1", obs_mask=1)
