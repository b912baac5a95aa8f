"""The native vector env of ReceiverClustering-v2 against its single env, sub-env by sub-env.

Sub-env ``b`` of ``gymnasium.make_vec("selenv/ReceiverClustering-v2", num_envs=B)`` must
replay ``gymnasium.make(...)`` reset with ``seed + b`` and driven by the same actions: the
same observations, rewards, episode ends and infos, in every invalid-action mode and with
sub-envs out of step with one another (a ``terminate`` ends one early).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401
from selenv.envs.actions import MASKED
from selenv.families.clustering.sequential_vector import ReceiverClusteringSequentialVectorEnv

ID = "selenv/ReceiverClustering-v2"
SMALL = {"n_agents": 6, "n_max_states": 10, "horizon": 3}


def _draw(masks: np.ndarray, rng: np.random.Generator, p_invalid: float) -> np.ndarray:
    """A masked-uniform placement per sub-env; with probability ``p_invalid`` a masked one."""
    out = np.argmax(rng.random(masks.shape) + masks, axis=1)
    for b in np.flatnonzero(rng.random(len(masks)) < p_invalid):
        bad = np.flatnonzero(~masks[b])
        if bad.size:
            out[b] = rng.choice(bad)
    return out


@pytest.mark.parametrize("invalid_action", ["noop", "terminate"])
def test_sub_envs_replay_the_single_env(invalid_action: str) -> None:
    B, seed, rng = 3, 11, np.random.default_rng(0)
    kw = {**SMALL, "invalid_action": invalid_action, "invalid_action_penalty": -1.5}
    venv = gym.make_vec(ID, num_envs=B, **kw)
    assert isinstance(venv, ReceiverClusteringSequentialVectorEnv)
    singles = [gym.make(ID, **kw) for _ in range(B)]
    obs, infos = venv.reset(seed=seed)
    s_obs = [env.reset(seed=seed + b)[0] for b, env in enumerate(singles)]
    pending = np.zeros(B, bool)  # NEXT_STEP: the single env resets where the vector env does
    counts = {"invalid": 0, "ends": 0, "filter_steps": 0}
    for t in range(120):
        for b, env in enumerate(singles):
            for key, value in s_obs[b].items():
                np.testing.assert_array_equal(obs[key][b], value, err_msg=f"{t} {b} {key}")
            np.testing.assert_array_equal(
                venv.action_masks()[b], env.unwrapped.action_masks(), err_msg=f"{t} {b}"
            )
        acts = _draw(venv.action_masks(), rng, p_invalid=0.05)
        obs, rew, term, trunc, infos = venv.step(acts)
        for b, env in enumerate(singles):
            if pending[b]:
                s_obs[b], _ = env.reset()
                assert rew[b] == 0 and not term[b] and not trunc[b]
                continue
            o, r, te, tr, info = env.step(acts[b])
            s_obs[b] = o
            np.testing.assert_allclose(rew[b], r, rtol=1e-12, atol=0, err_msg=f"{t} {b}")
            assert (term[b], trunc[b]) == (te, tr), (t, b)
            for key, value in info.items():
                np.testing.assert_allclose(infos[key][b], value, rtol=1e-12, err_msg=key)
            counts["invalid"] += int(info["invalid_code"] == MASKED)
            counts["filter_steps"] += int(info["placing"] == 0)
        counts["ends"] += int((term | trunc).sum())
        pending = term | trunc
    assert counts["invalid"] >= 5 and counts["ends"] >= 2 and counts["filter_steps"] >= 10


def test_an_invalid_placement_raises_before_any_sub_env_changes() -> None:
    venv = gym.make_vec(ID, num_envs=2, **SMALL, invalid_action="raise")
    obs, _ = venv.reset(seed=0)
    with pytest.raises(ValueError, match="sub-env 1"):
        venv.step(np.array([0, 3]))  # receiver 3 is not placed yet in sub-env 1
    np.testing.assert_array_equal(venv.unwrapped.receivers, [0, 0])
    obs, *_ = venv.step(np.array([0, 0]))
    assert obs["receiver"][:, 1].tolist() == [1, 1]


@pytest.mark.parametrize(
    ("actions", "error", "match"),
    [
        (np.zeros(3, np.int64), ValueError, "shape"),
        (np.zeros(2), TypeError, "integers"),
        (np.array([0, 6]), ValueError, r"actions\[1\]"),
        (np.array([True, False]), TypeError, "integers"),
    ],
)
def test_bad_actions_are_refused_naming_them(actions, error, match) -> None:
    venv = gym.make_vec(ID, num_envs=2, **SMALL)
    venv.reset(seed=0)
    with pytest.raises(error, match=match):
        venv.step(actions)


def test_fixed_keywords_are_refused() -> None:
    with pytest.raises(TypeError, match="action_mode"):
        gym.make_vec(ID, num_envs=2, action_mode="edit")


def test_get_attr_receiver_and_render() -> None:
    venv = gym.make_vec(ID, num_envs=2, **SMALL, render_mode="rgb_array")
    venv.reset(seed=0)
    venv.step(np.array([0, 0]))
    assert venv.get_attr("receiver") == (1, 1)
    frames = venv.render()
    assert len(frames) == 2 and frames[0].ndim == 3 and frames[0].dtype == np.uint8
    venv.close()
