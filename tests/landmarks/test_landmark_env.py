"""selenv/LandmarkSelection-v1 and its agents: checks, optimality, VNS, determinism, errors."""

from __future__ import annotations

import itertools

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import selenv  # noqa: F401
from selenv.agents import agents_for, make
from selenv.agents.fim_solvers import brute_force
from selenv.agents.vns import vns, vns_whitened
from selenv.core.kalman import kf_update
from selenv.core.linalg import logdet_spd

ENV_ID = "selenv/LandmarkSelection-v1"


def test_gymnasium_and_sb3_check_env() -> None:
    # k = 1: every pick ends a filter step, so the checkers' unmasked random actions are valid
    gym_check_env(gym.make(ENV_ID, n_landmarks=8, k=1, horizon=6).unwrapped)
    sb3_check_env(gym.make(ENV_ID, n_landmarks=8, k=1, horizon=6).unwrapped)


def _play(env, agent, seed):
    obs, info = env.reset(seed=seed)
    agent.reset(env, seed=seed)
    rewards, sels, costs = [], [], []
    done = False
    while not done:
        a = agent.act(obs, info)
        assert info["action_mask"][a]
        obs, r, done, trunc, info = env.step(a)
        assert env.observation_space.contains(obs)
        rewards.append(r)
        if info["picks"][0] < 0 or done:  # no pick open: an update just happened
            sels.append(tuple(j for j in info["last_selection"].tolist() if j >= 0))
            costs.append(info["objective"])
    return np.array(rewards), sels, np.array(costs), info


def test_reward_is_minus_cost_at_each_update_and_zero_between_picks() -> None:
    env = gym.make(ENV_ID, n_landmarks=12, k=3, horizon=8)
    rewards, sels, costs, info = _play(env, make("greedy", ENV_ID), seed=0)
    assert rewards.size == 24 and len(sels) == 8
    np.testing.assert_array_equal(rewards.reshape(8, 3)[:, :2], 0.0)
    np.testing.assert_allclose(rewards.reshape(8, 3)[:, 2], -costs)
    ekf = env.unwrapped.ekf
    assert costs[-1] == pytest.approx(logdet_spd(ekf.P))
    assert info["position_error"] == pytest.approx(
        np.linalg.norm(ekf.x[:3] - env.unwrapped.problem.states[8][:3])
    )
    det_env = gym.make(ENV_ID, n_landmarks=12, k=3, horizon=8, objective="det")
    _, sels_det, costs_det, _ = _play(det_env, make("greedy", ENV_ID), seed=0)
    assert sels_det == sels  # det and log det give the same selections
    np.testing.assert_allclose(costs_det, np.exp(costs), rtol=1e-9)


def test_same_seed_same_trajectory() -> None:
    env = gym.make(ENV_ID, n_landmarks=10, k=2, horizon=10)
    a = _play(env, make("vns", ENV_ID), seed=3)
    b = _play(env, make("vns", ENV_ID), seed=3)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[1] == b[1]
    c = _play(env, make("vns", ENV_ID), seed=4)
    assert not np.array_equal(a[0], c[0])


def test_brute_force_is_optimal_every_step_against_an_independent_enumeration() -> None:
    env = gym.make(ENV_ID, n_landmarks=9, k=2, horizon=6).unwrapped
    obs, info = env.reset(seed=1)
    agent = make("brute_force", ENV_ID)
    agent.reset(env, seed=1)
    R = env.problem.R_landmark
    for _ in range(6):
        P, x = env.ekf.P.copy(), env.ekf.x.copy()
        H, _ = env.ekf.candidates()
        costs = {}
        for pair in itertools.combinations(range(9), 2):
            Hs = H[list(pair)].reshape(-1, 9)
            post = kf_update(x, P, Hs @ x, Hs, np.kron(np.eye(2), R)).P
            costs[pair] = float(logdet_spd(post))
        best = min(costs, key=costs.get)
        picks = []
        for _ in range(2):
            a = agent.act(obs, info)
            picks.append(a)
            obs, r, done, _, info = env.step(a)
        assert tuple(sorted(picks)) == best
        assert info["objective"] == pytest.approx(costs[best], abs=1e-9)


def test_vns_equals_brute_force_when_k_is_one() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        A = rng.normal(size=(9, 9))
        Q0 = A @ A.T + 0.1 * np.eye(9)
        H = rng.normal(size=(30, 2, 9))
        R = np.diag([0.01, 0.02])
        v = vns(Q0, H, R, 1, rng=int(rng.integers(1 << 30)))
        b = brute_force(Q0, H, R, 1)
        assert v.indices == b.indices and v.objective == pytest.approx(b.objective)
    # in the env too: every step's pick is the single best landmark
    env = gym.make(ENV_ID, n_landmarks=12, k=1, horizon=10)
    _, sel_v, cost_v, _ = _play(env, make("vns", ENV_ID), seed=2)
    _, sel_b, cost_b, _ = _play(env, make("brute_force", ENV_ID), seed=2)
    assert sel_v == sel_b
    np.testing.assert_allclose(cost_v, cost_b)


def test_vns_warm_start_improves_and_respects_its_input() -> None:
    rng = np.random.default_rng(1)
    A = rng.normal(size=(9, 9))
    Q0 = A @ A.T + np.eye(9)
    G = 0.5 * rng.normal(size=(30, 2, 9))
    start = (0, 1)
    v = vns_whitened(Q0, G, 2, initial=start, rng=0)
    from selenv.core.information import logdet_objective

    assert v.objective >= logdet_objective(Q0, G, list(start)) - 1e-12
    b = brute_force(Q0, G, np.eye(2), 2)  # G already whitened: R = I
    assert v.objective <= b.objective + 1e-12
    with pytest.raises(ValueError, match="initial"):
        vns_whitened(Q0, G, 2, initial=(0, 0))
    with pytest.raises(ValueError, match="l_max"):
        vns_whitened(Q0, G, 2, l_max=0)


def test_all_landmarks_is_the_lower_bound_and_refuses_small_k() -> None:
    env_all = gym.make(ENV_ID, n_landmarks=8, k=8, horizon=6)
    _, _, cost_all, _ = _play(env_all, make("all", ENV_ID), seed=5)
    env = gym.make(ENV_ID, n_landmarks=8, k=2, horizon=6)
    _, _, cost_bf, _ = _play(env, make("brute_force", ENV_ID), seed=5)
    assert np.all(cost_all < cost_bf)
    with pytest.raises(ValueError, match="needs k = n_landmarks = 8"):
        make("all", ENV_ID).reset(env, seed=0)


def test_registered_agents_and_myopic_ordering() -> None:
    assert {"brute_force", "vns", "greedy", "swap", "random", "all"} <= set(agents_for(ENV_ID))
    env = gym.make(ENV_ID, n_landmarks=15, k=2, horizon=15)
    bf = _play(env, make("brute_force", ENV_ID), seed=7)[0].sum()
    rnd = _play(env, make("random", ENV_ID), seed=7)[0].sum()
    assert bf > rnd


def test_bad_input_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match=r"k must lie in \[1, n_landmarks=5\]"):
        gym.make(ENV_ID, n_landmarks=5, k=6)
    with pytest.raises(ValueError, match=r"k must lie in \[1"):
        gym.make(ENV_ID, k=0)
    with pytest.raises(TypeError, match="k must be an int"):
        gym.make(ENV_ID, k=2.0)
    bad = np.zeros((3, 3))
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match="landmarks"):
        gym.make(ENV_ID, n_landmarks=3, k=1, landmarks=bad)
    with pytest.raises(ValueError, match="objective"):
        gym.make(ENV_ID, objective="min_eig")
    with pytest.raises(TypeError, match=r"got an unexpected keyword argument 'colour'"):
        gym.make(ENV_ID, colour="red")
    env = gym.make(ENV_ID, n_landmarks=6, k=2, horizon=3, invalid_action="raise")
    env.reset(seed=0)
    env.step(1)
    with pytest.raises(ValueError, match="masked"):
        env.step(1)
    with pytest.raises(ValueError, match="out of range"):
        env.step(6)


def test_maskable_ppo_smoke() -> None:
    from sb3_contrib import MaskablePPO

    env = gym.make(ENV_ID, n_landmarks=8, k=2, horizon=5)
    model = MaskablePPO("MultiInputPolicy", env, n_steps=32, batch_size=32, n_epochs=1, seed=0)
    model.learn(64)
    obs, info = env.reset(seed=1)
    action, _ = model.predict(obs, action_masks=env.unwrapped.action_masks())
    assert info["action_mask"][int(action)]
