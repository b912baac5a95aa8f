"""The learned CL scorer ``cem``: its features, its limits (zero weights), its checkpoint."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401
from selenv.agents import make
from selenv.families.cooperative.features import FEATURE_NAMES, FusionMemory, pair_features
from selenv.learned.families.cooperative import CHECKPOINT_FORMAT, CLLearnedScorerAgent, read_scorer

CL = "selenv/CLScheduling-v1"
SHORT = {"horizon": 16}
ZERO = np.zeros(len(FEATURE_NAMES))


def _spd(rng: np.random.Generator, n: int = 9) -> np.ndarray:
    M = rng.normal(size=(n, n))
    return M @ M.T + n * np.eye(n)


def test_features_match_a_per_pair_loop_with_determinants() -> None:
    """A second formulation: plain loops, ``log det`` from ``det``, traces as sums."""
    rng = np.random.default_rng(0)
    A = 4
    P = np.stack([_spd(rng) for _ in range(A)])
    pairs = np.array([[0, 1], [2, 3], [3, 0]])
    P_new = np.stack([_spd(rng) for _ in pairs])
    gains = np.array([0.3, -0.1, 0.05])
    memory = FusionMemory(A)
    memory.record(2, 4)
    memory.record(0, 7)
    k, horizon = 12, 60
    got = pair_features(P, P_new, pairs, gains, k, horizon, memory)
    assert got.shape == (3, len(FEATURE_NAMES))

    def tr(M: np.ndarray, a: int, b: int) -> float:
        return sum(M[t, t] for t in range(a, b))

    pos_mean = sum(tr(P[a], 0, 2) for a in range(A)) / A
    for row, ((i, j), Pn, g) in enumerate(zip(pairs, P_new, gains, strict=True)):
        left = (horizon - k) / horizon
        expected = [
            math.log(tr(Pn, 3, 6) / tr(P[i], 3, 6)),
            math.log(tr(Pn, 6, 9) / tr(P[i], 6, 9)),
            math.log(np.linalg.det(Pn) / np.linalg.det(P[i])),
            g / tr(P[i], 0, 2),
            1.0,
            left,
            g * left,
            math.log(tr(P[i], 0, 2) / tr(P[j], 0, 2)),
            math.log(tr(P[i], 3, 6) / tr(P[j], 3, 6)),
            math.log(tr(P[i], 0, 2) / pos_mean),
            min((k - memory.last[i]) / 10.0, 1.0),
            min((k - 7) / 10.0, 1.0),
        ]
        np.testing.assert_allclose(got[row], expected, rtol=1e-9, atol=1e-12)
    assert got[0, 10] == 0.5 and got[1, 10] == pytest.approx(0.8) and got[2, 10] == 1.0


def _episode_actions(agent: Any, seed: int, **env_kw: Any) -> list[int]:
    env = gym.make(CL, **{**SHORT, **env_kw})
    obs, info = env.reset(seed=seed)
    agent.reset(env, seed=seed)
    actions, done = [], False
    while not done:
        a = agent.act(obs, info)
        actions.append(a)
        obs, _, terminated, truncated, info = env.step(a)
        done = terminated or truncated
    return actions


@pytest.mark.parametrize("seed", [0, 5])
def test_zero_weights_at_horizon_zero_play_greedy(seed: int) -> None:
    ours = _episode_actions(CLLearnedScorerAgent(ZERO, horizon=0), seed)
    assert ours == _episode_actions(make("greedy", CL), seed)
    assert any(a != 30 for a in ours) and 30 in ours  # both fusions and stops were played


@pytest.mark.parametrize("horizon", [1, 3])
def test_zero_weights_with_a_lookahead_play_fast_rollout(horizon: int) -> None:
    env = gym.make(CL, **SHORT)
    env.reset(seed=2)
    ours, ref = (
        CLLearnedScorerAgent(ZERO, horizon=horizon),
        make("fast_rollout", CL, horizon=horizon),
    )
    for agent in (ours, ref):
        agent.reset(env, seed=2)
    for _ in range(8):
        choice, scores = ours.scores()
        ref_choice, ref_scores = ref.scores()
        assert choice == ref_choice and list(scores) == list(ref_scores)
        np.testing.assert_allclose(list(scores.values()), list(ref_scores.values()), rtol=1e-12)
        env.step(choice)


def test_the_correction_changes_decisions() -> None:
    """Teeth: a large negative bias never fuses; a large positive one fuses at every step."""
    bias = FEATURE_NAMES.index("bias")
    never, always = ZERO.copy(), ZERO.copy()
    never[bias], always[bias] = -1.0, 1.0
    stop = 30
    assert set(_episode_actions(CLLearnedScorerAgent(never, horizon=0), 1)) == {stop}
    assert stop not in _episode_actions(CLLearnedScorerAgent(always, horizon=0), 1)


def test_memory_records_the_agents_fusions() -> None:
    env = gym.make(CL, **SHORT)
    obs, info = env.reset(seed=3)
    always = ZERO.copy()
    always[FEATURE_NAMES.index("bias")] = 1.0
    agent = CLLearnedScorerAgent(always, horizon=0)
    agent.reset(env, seed=3)
    k = env.unwrapped.sim.k
    a = agent.act(obs, info)
    i = env.unwrapped.pairs[a][0]
    assert agent.memory.last[i] == k and agent.memory.any == k
    assert agent.last_scores[a] == max(agent.last_scores.values())


# -- the checkpoint -------------------------------------------------------------------------
def _checkpoint(tmp_path: Path, **changes: Any) -> Path:
    data: dict[str, Any] = {
        "format": CHECKPOINT_FORMAT,
        "env_id": CL,
        "features": list(FEATURE_NAMES),
        "theta": [1e-3] * len(FEATURE_NAMES),
        "lookahead": {"horizon": 1, "top_k": 3},
        "env_config": {
            "n_agents": 6,
            "model": "ins",
            "objective": "trace",
            "fusion": "dmv",
            "budget": 1,
        },
    }
    data.update(changes)
    path = tmp_path / "scorer.json"
    path.write_text(json.dumps(data))
    return path


def test_the_shipped_checkpoint_loads_and_plays_the_bench_env() -> None:
    agent = make("cem", CL)
    assert agent.horizon >= 0 and np.all(np.isfinite(agent.theta)) and np.any(agent.theta != 0)
    assert len(_episode_actions(agent, 0)) >= SHORT["horizon"]


def test_a_checkpoint_file_round_trips(tmp_path: Path) -> None:
    agent = make("cem", CL, checkpoint=str(_checkpoint(tmp_path)))
    np.testing.assert_array_equal(agent.theta, 1e-3)
    assert (agent.horizon, agent.top_k) == (1, 3)


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"format": "other"}, "format"),
        ({"features": list(FEATURE_NAMES[:-1])}, "features"),
        ({"theta": [1e-3] * 11}, "theta"),
        ({"theta": [1e-3] * 11 + ["x"]}, "theta"),
        ({"theta": [1e-3] * 11 + [True]}, "theta"),
        ({"lookahead": {"horizon": -1, "top_k": 3}}, "lookahead"),
        ({"lookahead": {"horizon": 1}}, "lookahead"),
        ({"env_config": {"n_agents": 6}}, "env_config"),
    ],
)
def test_bad_checkpoints_are_refused_naming_the_field(
    tmp_path: Path, changes: dict[str, Any], field: str
) -> None:
    with pytest.raises(ValueError, match=field):
        read_scorer(_checkpoint(tmp_path, **changes))


def test_non_finite_weights_and_non_json_are_refused(tmp_path: Path) -> None:
    path = _checkpoint(tmp_path)
    path.write_text(path.read_text().replace("0.001", "NaN", 1))
    with pytest.raises(ValueError, match="theta"):
        read_scorer(path)
    path.write_text("import os")
    with pytest.raises(ValueError, match="JSON"):
        read_scorer(path)
    with pytest.raises(FileNotFoundError):
        read_scorer(tmp_path / "missing.json")


def test_another_env_configuration_is_refused_at_reset(tmp_path: Path) -> None:
    agent = make("cem", CL, checkpoint=str(_checkpoint(tmp_path)))
    with pytest.raises(ValueError, match="n_agents=6"):
        agent.reset(gym.make(CL, n_agents=4), seed=0)
    with pytest.raises(ValueError, match="ins model"):
        agent.reset(gym.make(CL, model="unicycle", n_agents=6), seed=0)
    with pytest.raises(ValueError, match="CLScheduling"):
        agent.reset(gym.make("CartPole-v1"), seed=0)
    with pytest.raises(ValueError, match="theta"):
        CLLearnedScorerAgent(np.zeros(3))
