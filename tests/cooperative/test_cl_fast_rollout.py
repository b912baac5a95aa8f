"""CLScheduling's ``fast_rollout``: ``rollout``'s lookahead batched, checked against it.

``rollout`` (one candidate and one previewed pair at a time, the forecast's own per-agent
filter calls) is the second formulation: same candidates, same scores to rounding, same choice,
on configurations that exercise every branch (budget > 1 and the gain-cache refresh, bearing
rows, naive fusion, the unicycle model, sparse relative links, the ``all`` base, the episode's
last steps).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401
from selenv.agents import make

CL = "selenv/CLScheduling-v1"
CONFIGS: dict[str, dict[str, Any]] = {
    "benchmark": {"horizon": 14},
    "budget2_logdet": {"n_agents": 3, "budget": 2, "horizon": 14, "objective": "logdet"},
    "bearing_sparse": {
        "n_agents": 3,
        "budget": 3,
        "horizon": 14,
        "bearing_sigma_deg": 2.0,
        "relative_every": 2,
    },
    "naive_budget2": {"n_agents": 3, "budget": 2, "horizon": 14, "fusion": "naive"},
    "unicycle": {"model": "unicycle", "n_agents": 3, "budget": 2, "horizon": 14},
}


def _bound(name: str, env: gym.Env[Any, Any], **kw: Any) -> Any:
    agent = make(name, CL, **kw)
    agent.reset(env, seed=0)
    return agent


@pytest.mark.parametrize("config", sorted(CONFIGS))
@pytest.mark.parametrize(
    ("horizon", "base"), [(0, "greedy"), (2, "greedy"), (5, "greedy"), (3, "all")]
)
def test_fast_rollout_gives_rollouts_scores_and_choices_over_an_episode(
    config: str, horizon: int, base: str
) -> None:
    """Every decision of a whole episode (rollout plays it): candidates, scores, choice.

    Two candidates can tie exactly in the math (two fusions into different agents with the same
    partner commute), and then rounding picks one; such a choice must be a tied maximum of
    ``rollout``'s own scores, and it must stay rare.
    """
    env = gym.make(CL, **CONFIGS[config])
    obs, info = env.reset(seed=3)
    fast = _bound("fast_rollout", env, horizon=horizon, base=base)
    ref = _bound("rollout", env, horizon=horizon, base=base)
    done, decisions, simulated, ties = False, 0, 0, 0
    while not done:
        choice, scores = fast.scores()
        ref_choice, ref_scores = ref.scores()
        assert list(scores) == list(ref_scores)  # the same candidates in the same order
        np.testing.assert_allclose(
            list(scores.values()), list(ref_scores.values()), rtol=1e-9, atol=1e-12
        )
        if choice != ref_choice:  # only an exact tie in the math, broken by rounding
            top = max(ref_scores.values())
            assert abs(ref_scores[choice] - top) <= 1e-9 * max(1.0, abs(top)), (choice, ref_scores)
            ties += 1
        decisions += 1
        simulated += len(scores) > 1
        obs, _, terminated, truncated, info = env.step(ref_choice)
        done = terminated or truncated
    assert decisions >= CONFIGS[config]["horizon"] and simulated > 0
    assert ties <= 1


def test_fast_rollout_acts_with_its_scores_and_keeps_them() -> None:
    env = gym.make(CL, **CONFIGS["budget2_logdet"])
    obs, info = env.reset(seed=1)
    agent = _bound("fast_rollout", env, top_k=2, horizon=2)
    for _ in range(6):
        a = agent.act(obs, info)
        assert agent.last_scores and a == max(agent.last_scores, key=agent.last_scores.get)
        assert info["action_mask"][a]
        obs, _, terminated, _, info = env.step(a)
        assert not terminated


def test_the_stack_pieces_agree_with_the_scores() -> None:
    """``candidates`` + ``simulate`` + ``advance`` + ``objective`` are ``scores``'s parts."""
    env = gym.make(CL, **CONFIGS["benchmark"])
    env.reset(seed=2)
    for _ in range(5):
        env.step(env.unwrapped.n_pairs)
    agent = _bound("fast_rollout", env, horizon=3)
    decision = agent.candidates()
    stack = agent.simulate(decision, 3)
    assert stack.P.shape[0] == len(decision.actions) and stack.k == decision.root.k + 3
    np.testing.assert_array_equal(stack.x, np.repeat(stack.x[:1], stack.x.shape[0], axis=0))
    agent.advance(stack, decision.root.u_hold)
    expected = decision.root.objective_value() - agent.objective(stack)
    np.testing.assert_allclose(list(agent.scores()[1].values()), expected, rtol=1e-12)
    assert np.all(np.isinf(decision.pair_gains[~env.unwrapped.action_masks()[:-1]]))
