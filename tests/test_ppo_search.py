"""``ppo_search``: fast_rollout's lookahead on the shortlist the learned policy ranks first."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401
from selenv.agents import agents_for, make
from selenv.learned.rl.agent import SB3PolicyAgent
from selenv.learned.rl.candidate_policy import MASKED_LOGIT

LM = "selenv/LandmarkSelection-v1"
LM_KW: dict[str, Any] = {"n_landmarks": 12, "k": 2, "horizon": 25}


def _warm(seed: int, steps: int, **kw: Any) -> tuple[gym.Env[Any, Any], Any, Any]:
    """An env after ``steps`` brute-force picks (mid filter step when ``steps`` is odd)."""
    env = gym.make(LM, **dict(LM_KW, **kw))
    obs, info = env.reset(seed=seed)
    bf = make("brute_force", LM)
    bf.reset(env, seed=seed)
    for _ in range(steps):
        obs, _, terminated, _, info = env.step(bf.act(obs, info))
        assert not terminated
    return env, obs, info


def _bound(name: str, env: gym.Env[Any, Any], **kw: Any) -> Any:
    agent = make(name, LM, **kw)
    agent.reset(env, seed=0)
    return agent


def test_registered_for_the_current_version_only() -> None:
    assert "ppo_search" in agents_for(LM)
    assert "ppo_search" not in agents_for("selenv/LandmarkSelection-v0")


@pytest.mark.parametrize(("seed", "warm"), [(3, 4), (5, 11), (2, 40)])
@pytest.mark.parametrize("horizon", [0, 3])
def test_with_every_landmark_it_is_fast_rollout(seed: int, warm: int, horizon: int) -> None:
    """The shortlist is the only thing the policy changes: with all landmarks, same scores."""
    env, obs, info = _warm(seed, warm, horizon=50)
    n = LM_KW["n_landmarks"]
    search = _bound("ppo_search", env, horizon=horizon, shortlist=n)
    fast = _bound("fast_rollout", env, horizon=horizon, shortlist=n)
    choice, scores = search.scores(obs, info)
    ref_choice, ref_scores = fast.scores(obs, info)
    assert choice == ref_choice
    assert set(scores) == set(ref_scores)
    np.testing.assert_allclose(
        [scores[s] for s in ref_scores], list(ref_scores.values()), rtol=1e-9, atol=1e-12
    )


@pytest.mark.parametrize(("seed", "warm"), [(4, 2), (7, 9), (9, 30)])
def test_the_shortlist_is_the_policys_best_scored_open_landmarks(seed: int, warm: int) -> None:
    env, obs, info = _warm(seed, warm)
    search = _bound("ppo_search", env, shortlist=4, top_k=6)
    # the policy's scores through SB3's own feature extraction (not the lean forward)
    ref = SB3PolicyAgent(env_id=LM)
    ref.reset(env, seed=0)
    logits = ref.scores(ref.view(obs))
    open_ = np.isfinite(env.unwrapped.state.masked_gains())
    top = np.argsort(-np.where(open_, logits, -np.inf), kind="stable")[:4]
    for backend in ("torch", "numpy"):
        ours = search.policy.logits(obs, info, backend=backend)
        np.testing.assert_allclose(ours[open_], logits[open_], rtol=1e-5, atol=1e-5)
        assert (ours[~open_] == MASKED_LOGIT).all()
    assert set(search.select_shortlist(obs, info, env.unwrapped.state.masked_gains(), 4)) == set(
        top.tolist()
    )
    choice, scores = search.scores(obs, info)
    assert len(scores) == math.comb(4, env.unwrapped.budget_left)  # every subset of the shortlist
    assert all(set(s) <= set(top.tolist()) for s in scores)
    assert choice in scores


def test_masked_landmarks_never_enter_the_shortlist() -> None:
    env, obs, info = _warm(6, 7)  # mid step: one landmark already picked
    search = _bound("ppo_search", env, shortlist=LM_KW["n_landmarks"])
    gains = env.unwrapped.state.masked_gains()
    assert not np.isfinite(gains).all()
    logits = search.policy.logits(obs, info)
    assert (logits[~np.isfinite(gains)] == MASKED_LOGIT).all()
    shortlist = search.select_shortlist(obs, info, gains, int(np.isfinite(gains).sum()))
    assert np.isfinite(gains[shortlist]).all()
    assert len(set(shortlist.tolist())) == len(shortlist)


def test_leaves_the_env_alone() -> None:
    """Scoring reads the env (no peeking: tests/test_rollout.py) and changes none of it."""
    env, obs, info = _warm(6, 14)
    base = env.unwrapped
    before = (base.ekf.x.copy(), base.ekf.P.copy(), base.ekf.k, tuple(base.picks))
    search = _bound("ppo_search", env)
    first = search.scores(obs, info)
    assert search.act(obs, info) in first[0]
    np.testing.assert_array_equal(base.ekf.x, before[0])
    np.testing.assert_array_equal(base.ekf.P, before[1])
    assert (base.ekf.k, tuple(base.picks)) == before[2:]
    assert search.scores(obs, info) == first


def test_plays_whole_episodes_deterministically() -> None:
    def episode() -> tuple[float, list[int]]:
        env = gym.make(LM, **dict(LM_KW, horizon=10))
        obs, info = env.reset(seed=12)
        agent = make("ppo_search", LM, horizon=4)
        agent.reset(env, seed=12)
        total, actions, done = 0.0, [], False
        while not done:
            actions.append(int(agent.act(obs, info)))
            obs, r, terminated, truncated, info = env.step(actions[-1])
            total += float(r)
            done = terminated or truncated
        return total, actions

    first, second = episode(), episode()
    assert first == second
    assert len(first[1]) == 10 * LM_KW["k"]


def test_needs_the_observation_and_a_bound_policy() -> None:
    env, _, _ = _warm(1, 2)
    with pytest.raises(ValueError, match="obs"):
        _bound("ppo_search", env).scores()
    with pytest.raises(ValueError, match="reset"):
        SB3PolicyAgent(env_id=LM).logits({}, {})
    with pytest.raises(ValueError, match="backend"):
        _bound("ppo_search", env).policy.logits({}, {}, backend="jax")


@pytest.mark.parametrize("options", [{"top_k": 0}, {"horizon": -1}, {"shortlist": 0}])
def test_bad_options_raise(options: dict[str, Any]) -> None:
    with pytest.raises((TypeError, ValueError), match=next(iter(options))):
        make("ppo_search", LM, **options)


def test_refuses_a_checkpoint_of_another_env() -> None:
    with pytest.raises(ValueError, match=r"FIMSelection|LandmarkSelection"):
        make("ppo_search", LM, checkpoint="checkpoints/fim_selection_ppo.zip")
