"""``fast_rollout`` on LandmarkSelection: checked against the reference ``rollout``.

With the shortlist covering every landmark, the batched Woodbury lookahead must give the
reference rollout's candidates and scores (a second formulation: Joseph-form EKF updates and
brute force over all subsets at every simulated step) to a stated tolerance, and the same
decision; with a short shortlist it must stay on that shortlist.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401
from selenv.agents import agents_for, make
from selenv.families.landmarks.models import propagate, propagate_steps

LM = "selenv/LandmarkSelection-v1"
LM_KW: dict[str, Any] = {"n_landmarks": 12, "k": 2, "horizon": 25}


def _play(env: gym.Env[Any, Any], agent: Any, steps: int, seed: int) -> tuple[Any, Any]:
    obs, info = env.reset(seed=seed)
    agent.reset(env, seed=seed)
    for _ in range(steps):
        obs, _, terminated, _, info = env.step(agent.act(obs, info))
        assert not terminated
    return obs, info


def _bound(name: str, env: gym.Env[Any, Any], **kw: Any) -> Any:
    agent = make(name, LM, **kw)
    agent.reset(env, seed=0)
    return agent


def test_registered_for_the_landmark_env() -> None:
    assert "fast_rollout" in agents_for(LM)


@pytest.mark.parametrize(("seed", "warm"), [(3, 4), (5, 10), (11, 16), (2, 40)])
@pytest.mark.parametrize("horizon", [0, 1, 6])
def test_full_shortlist_gives_the_reference_rollout_scores(
    seed: int, warm: int, horizon: int
) -> None:
    kw = dict(LM_KW, horizon=50)
    env = gym.make(LM, **kw)
    _play(env, make("brute_force", LM), warm, seed=seed)
    fast = _bound("fast_rollout", env, top_k=4, horizon=horizon, shortlist=kw["n_landmarks"])
    ref = _bound("rollout", env, top_k=4, horizon=horizon)
    choice, scores = fast.scores()
    ref_choice, ref_scores = ref.scores()
    assert choice == ref_choice
    assert list(scores) == list(ref_scores)  # the same candidates, best one-step gain first
    ours, theirs = np.array(list(scores.values())), np.array(list(ref_scores.values()))
    if horizon == 0:  # gain log det(I + W P W^T) vs -log det P+: the same up to log det P
        np.testing.assert_allclose(np.diff(ours), np.diff(theirs), rtol=1e-9, atol=1e-12)
        return
    np.testing.assert_allclose(ours, theirs, rtol=1e-9)


def test_short_shortlist_stays_on_it_and_horizon_zero_is_its_best_subset() -> None:
    env = gym.make(LM, **LM_KW)
    _play(env, make("brute_force", LM), 6, seed=8)
    gains = env.unwrapped.state.masked_gains()
    shortlist = set(np.argsort(-gains, kind="stable")[:4].tolist())
    agent = _bound("fast_rollout", env, top_k=6, horizon=3, shortlist=4)
    choice, scores = agent.scores()
    assert len(scores) == 6  # C(4, 2) subsets of the shortlist
    assert all(set(s) <= shortlist for s in scores)
    myopic = _bound("fast_rollout", env, horizon=0, shortlist=4)
    best, _ = myopic.scores()
    # brute force over the shortlist only: the best one-step subset within it
    full = _bound("fast_rollout", env, horizon=0, shortlist=LM_KW["n_landmarks"])
    ranked = [s for s in full.scores()[1] if set(s) <= shortlist]
    assert not ranked or best == ranked[0]
    assert choice in scores


def test_deterministic_and_leaves_the_env_alone() -> None:
    env = gym.make(LM, **LM_KW)
    obs, info = _play(env, make("brute_force", LM), 8, seed=9)
    base = env.unwrapped
    before = (base.ekf.x.copy(), base.ekf.P.copy(), base.ekf.k, tuple(base.picks))
    first, second = make("fast_rollout", LM), make("fast_rollout", LM)
    first.reset(env, seed=0)
    second.reset(env, seed=1)
    assert first.act(obs, info) == second.act(obs, info)
    assert first.last_scores == second.last_scores
    after = (base.ekf.x, base.ekf.P, base.ekf.k, tuple(base.picks))
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])
    assert before[2:] == after[2:]


def test_does_not_peek_at_the_future() -> None:
    a, b = gym.make(LM, **LM_KW), gym.make(LM, **LM_KW)
    _play(a, make("brute_force", LM), 14, seed=6)
    _play(b, make("brute_force", LM), 14, seed=6)
    base = b.unwrapped
    k, prob, rng = base.ekf.k, base.problem, np.random.default_rng(98)

    def scramble(x: np.ndarray, start: int) -> np.ndarray:
        out = np.array(x, copy=True)
        out[start:] += rng.normal(size=out[start:].shape) * (1.0 + np.abs(out[start:]))
        return out

    base.problem = base.ekf.problem = dataclasses.replace(
        prob,
        states=scramble(prob.states, k),
        imu_true=scramble(prob.imu_true, k),
        imu_measured=scramble(prob.imu_measured, k),
        measurement_noise=scramble(prob.measurement_noise, k - 1),
        measurements=scramble(prob.measurements, k - 1),
    )
    assert _bound("fast_rollout", a).scores() == _bound("fast_rollout", b).scores()


def test_plays_whole_episodes_including_the_last_steps() -> None:
    env = gym.make(LM, **dict(LM_KW, horizon=12))
    agent = make("fast_rollout", LM, horizon=4)
    obs, info = env.reset(seed=4)
    agent.reset(env, seed=4)
    done, steps = False, 0
    while not done:
        obs, _, terminated, truncated, info = env.step(agent.act(obs, info))
        done, steps = terminated or truncated, steps + 1
    assert steps == 12 * LM_KW["k"]


@pytest.mark.parametrize(
    "options",
    [{"top_k": 0}, {"horizon": -1}, {"shortlist": 0}, {"shortlist": 500}, {"top_k": 1.5}],
)
def test_bad_options_raise(options: dict[str, Any]) -> None:
    with pytest.raises((TypeError, ValueError), match=next(iter(options))):
        make("fast_rollout", LM, **options)


def test_refuses_another_objective_and_another_env() -> None:
    agent = make("fast_rollout", LM)
    with pytest.raises(ValueError, match="objective"):
        agent.reset(gym.make(LM, **LM_KW, objective="det"), seed=0)
    with pytest.raises(ValueError, match="LandmarkSelection"):
        agent.reset(gym.make("CartPole-v1"), seed=0)


def test_propagate_steps_repeats_propagate() -> None:
    rng = np.random.default_rng(0)
    x = np.r_[rng.normal(size=6) * 10.0, rng.normal(size=3) * 0.3]
    u = np.r_[rng.normal(size=2), -9.8, rng.normal(size=3) * 0.05]
    xs = propagate_steps(x, u, 0.1, 7)
    assert xs.shape == (8, 9)
    y = x
    for t in range(7):
        y = propagate(y, u, 0.1)
        np.testing.assert_array_equal(xs[t + 1], y)  # the same arithmetic, same machine
    with pytest.raises(ValueError, match="x"):
        propagate_steps(np.zeros(3), u, 0.1, 2)
