"""The ``ppo`` agent's lean inference path chooses exactly SB3 ``predict``'s actions."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, SB3PolicyAgent
from selenv.learned.rl.candidate_policy import make_ppo
from selenv.learned.rl.lean import LeanScorer

MAX_STEPS = 40


@pytest.mark.parametrize("env_id", sorted(DEFAULT_CHECKPOINTS))
def test_lean_agent_equals_predict_on_shipped_checkpoints(env_id: str) -> None:
    """Every step of two episodes: the lean agent and the ``predict`` agent pick the same."""
    env = gym.make(env_id)
    lean = SB3PolicyAgent(env_id=env_id)
    slow = SB3PolicyAgent(env_id=env_id, lean=False)
    steps = 0
    for seed in (0, 1):
        obs, info = env.reset(seed=seed)
        lean.reset(env, seed=seed)
        slow.reset(env, seed=seed)
        done = False
        while not done and steps < MAX_STEPS * (seed + 1):
            a_lean, a_slow = lean.act(obs, info), slow.act(obs, info)
            np.testing.assert_array_equal(np.asarray(a_lean), np.asarray(a_slow))
            obs, _, term, trunc, info = env.step(a_lean)
            done = term or trunc
            steps += 1
    assert steps >= 10  # the comparison really ran


@pytest.mark.parametrize("algo", ["maskable_ppo", "ppo"])
def test_lean_mode_equals_predict_on_random_weights_and_masks(algo: str) -> None:
    """Random (untrained, scaled-up) weights, random observations and masks, incl. ties."""
    env = gym.make("selenv/FIMSelection-v1", n_candidates=30, budget=5)
    model = make_ppo(env, algo, seed=0, device="cpu")
    policy = model.policy
    with th.no_grad():
        for p in policy.pi_features_extractor.parameters():
            p.mul_(20.0)  # sharpen the scores so that the argmax is not the gain skip alone
    scorer = LeanScorer(policy)
    rng = np.random.default_rng(0)
    space = env.observation_space
    space.seed(0)
    n = space["action_mask"].shape[0]
    n_diff_from_gain = 0
    for k in range(200):
        obs = space.sample()
        mask = rng.random(n) < 0.6
        mask[rng.integers(n)] = True
        if k % 10 == 0:  # exact ties in the gains
            obs["gain"][:] = obs["gain"][0]
        obs["action_mask"] = mask.astype(obs["action_mask"].dtype)
        if algo == "maskable_ppo":
            expected, _ = policy.predict(obs, action_masks=mask, deterministic=True)
        else:
            expected, _ = policy.predict(obs, deterministic=True)
        got = scorer.action(obs, mask)
        assert got == int(expected)
        assert mask[got]
        n_diff_from_gain += got != int(np.argmax(np.where(mask, obs["gain"], -np.inf)))
    assert n_diff_from_gain > 20  # the network, not a gain argmax, decided


def test_lean_scorer_rejects_other_policies_and_empty_masks() -> None:
    with pytest.raises(TypeError, match="candidate-scoring policy"):
        LeanScorer(object())
    env = gym.make("selenv/FIMSelection-v1", n_candidates=10, budget=3)
    scorer = LeanScorer(make_ppo(env, seed=0, device="cpu").policy)
    obs, _ = env.reset(seed=0)
    with pytest.raises(ValueError, match="empty action mask"):
        scorer.action(obs, np.zeros(obs["action_mask"].shape, dtype=bool))
    with pytest.raises(TypeError, match="lean must be a bool"):
        SB3PolicyAgent(lean="yes")  # type: ignore[arg-type]


def test_top_m_scorer_matches_the_network_on_the_whole_pool_and_picks_from_the_top_m() -> None:
    from selenv.learned.rl.lean import TopMScorer

    env = gym.make("selenv/FIMSelection-v1", n_candidates=30, budget=5)
    policy = make_ppo(env, seed=1, device="cpu").policy
    with th.no_grad():
        for p in policy.pi_features_extractor.parameters():
            p.mul_(5.0)
    lean, space = LeanScorer(policy), env.observation_space
    space.seed(1)
    rng = np.random.default_rng(1)
    n = space["action_mask"].shape[0]
    for _ in range(50):
        obs = space.sample()
        mask = rng.random(n) < 0.7
        mask[0] = True
        obs["action_mask"] = mask.astype(obs["action_mask"].dtype)
        full = TopMScorer(policy, n)
        idx = np.flatnonzero(mask)
        np.testing.assert_allclose(
            full.scores(obs, idx), lean.scores(obs, mask)[idx], rtol=1e-4, atol=1e-4
        )
        top4 = TopMScorer(policy, 4).action(obs, mask)
        best4 = idx[np.argsort(-np.maximum(obs["gain"][idx], 0), kind="stable")[:4]]
        assert mask[top4] and obs["gain"][top4] >= np.sort(obs["gain"][idx])[-4]
        assert top4 in set(best4) or obs["gain"][top4] == obs["gain"][best4[-1]]
    with pytest.raises(ValueError, match="top_m"):
        TopMScorer(policy, 0)
    with pytest.raises(ValueError, match="top_m"):
        SB3PolicyAgent(top_m=-1)
