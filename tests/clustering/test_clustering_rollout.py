"""``rollout`` for ReceiverClustering-v1: options, L = 0 is greedy, no peeking, env untouched."""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401
from selenv.agents import agents_for, make
from selenv.families.clustering.rollout import ClusteringRolloutAgent

ENV_ID = "selenv/ReceiverClustering-v1"
#: small and fast-switching, so that the regimes change within the rollout horizon
ENV_KW: dict[str, Any] = {"n_agents": 9, "horizon": 30, "tau": 6, "p_enter": 0.1, "p_leave": 0.2}


def _play(env: gym.Env[Any, Any], agent: Any, seed: int) -> list[np.ndarray]:
    obs, info = env.reset(seed=seed)
    agent.reset(env, seed=seed)
    out, done = [], False
    while not done:
        obs, _r, term, trunc, info = env.step(agent.act(obs, info))
        out.append(obs["assignment"].copy())
        done = term or trunc
    return out


def test_registered_and_options_validated() -> None:
    assert "rollout" in agents_for(ENV_ID)
    assert isinstance(make("rollout", ENV_ID), ClusteringRolloutAgent)
    for kwargs, name in (
        ({"top_k": 0}, "top_k"),
        ({"horizon": -1}, "horizon"),
        ({"every": 0}, "every"),
        ({"top_k": 2.5}, "top_k"),
        ({"horizon": True}, "horizon"),
        ({"forecast": "oracle"}, "forecast"),
        ({"samples": 0}, "samples"),
    ):
        with pytest.raises(ValueError, match=name):
            make("rollout", ENV_ID, **kwargs)


@pytest.mark.parametrize("mode", ["assignment", "edit"])
def test_horizon_zero_is_the_myopic_greedy(mode: str) -> None:
    env = gym.make(ENV_ID, **ENV_KW, action_mode=mode)
    greedy = _play(env, make("greedy", ENV_ID, every=3), seed=1)
    rollout = _play(env, make("rollout", ENV_ID, horizon=0, top_k=2, every=3), seed=1)
    assert len(greedy) == 30 and any(not np.array_equal(greedy[0], g) for g in greedy)
    for a, b in zip(greedy, rollout, strict=True):
        np.testing.assert_array_equal(a, b)


def _env_at(k: int, seed: int, future: str | None = None) -> Any:
    """The env after ``k`` keep-steps; ``future="flip"`` first flips the regimes after ``k``."""
    env = gym.make(ENV_ID, **ENV_KW)
    obs, _ = env.reset(seed=seed)
    base = env.unwrapped
    if future == "flip":
        regimes = base.problem.regimes.copy()
        regimes[k + 1 :] = 1.0 - regimes[k + 1 :]
        base.problem = dataclasses.replace(base.problem, regimes=regimes)
        base.bank.problem = base.problem
    for _ in range(k):
        obs, *_ = env.step(obs["assignment"])
    return env


@pytest.mark.parametrize("forecast", ["mean", "sample"])
def test_rollout_never_looks_at_the_future_regime_path(forecast: str) -> None:
    k, seed = 10, 2
    choices = []
    for future in (None, "flip"):
        env = _env_at(k, seed, future)
        agent = make("rollout", ENV_ID, top_k=3, horizon=8, forecast=forecast, samples=2)
        agent.reset(env, seed=7)
        obs = {"assignment": env.unwrapped.bank.labels.copy()}
        choices.append((agent.act(obs, {}), agent.last_scores))
    np.testing.assert_array_equal(choices[0][0], choices[1][0])
    assert choices[0][1] == choices[1][1]  # the same scores, bit for bit
    assert len(choices[0][1]) == 4  # the no-op and the top 3 edits
    # the altered future does change what happens next (the test can see a peek)
    a, b = _env_at(k, seed), _env_at(k, seed, "flip")
    a.step(choices[0][0])
    b.step(choices[0][0])
    assert a.unwrapped.bank.cost().J != b.unwrapped.bank.cost().J


def test_act_leaves_the_env_state_unchanged() -> None:
    env = _env_at(10, 3)
    bank = env.unwrapped.bank
    labels, k, J = bank.labels.copy(), bank.k, bank.cost().J
    hist = {key: bank.history(key).copy() for key in bank.clusters}
    problem = env.unwrapped.problem
    agent = make("rollout", ENV_ID, top_k=3, horizon=6)
    agent.reset(env, seed=0)
    agent.act({}, {})
    assert bank.k == k and bank.cost().J == J and env.unwrapped.problem is problem
    np.testing.assert_array_equal(bank.labels, labels)
    assert bank.clusters == list(hist)
    for key, h in hist.items():
        np.testing.assert_array_equal(bank.history(key), h)
    assert bank.n_cost_evaluations > 0  # the decision's effort is counted


def test_rollout_plays_feasible_clusterings_and_is_seeded() -> None:
    env = gym.make(ENV_ID, **ENV_KW)
    a = _play(env, make("rollout", ENV_ID, top_k=2, horizon=4, forecast="sample"), seed=4)
    b = _play(env, make("rollout", ENV_ID, top_k=2, horizon=4, forecast="sample"), seed=4)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
        assert np.bincount(x).max() <= 3
