"""Every registered env and PettingZoo module works with the mainstream RL stacks, default kwargs.

What a new user does first — the checkers, vectorisation, plain PPO, MaskablePPO, the PettingZoo
tests and SuperSuit -> SB3 — run here on each id exactly as registered (no keyword arguments
except ``render_mode`` where rendering is what is checked). Training budgets are the
algorithms' arguments (a few hundred steps), never env keywords.
"""

from __future__ import annotations

import warnings
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import supersuit as ss
from gymnasium.utils.env_checker import check_env as gym_check_env
from pettingzoo.test import (
    api_test,
    max_cycles_test,
    parallel_api_test,
    parallel_seed_test,
    state_test,
)
from sb3_contrib import MaskablePPO
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.utils import set_random_seed

import selenv  # noqa: F401  (registers the ids)
from selenv.envs import ENV_IDS
from selenv.multiagent import fim_selection_v0, receiver_clustering_v0, receiver_clustering_v1

MODULES = [fim_selection_v0, receiver_clustering_v1]
PPO_ARGS: dict[str, Any] = {"n_steps": 64, "batch_size": 64, "n_epochs": 1, "seed": 0}


class InfoRecorder(BaseCallback):
    """Collects every step's ``infos`` during ``learn``."""

    def __init__(self) -> None:
        super().__init__()
        self.infos: list[dict[str, Any]] = []

    def _on_step(self) -> bool:
        self.infos.extend(self.locals["infos"])
        return True


# -- Gymnasium ----------------------------------------------------------------------------------
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_gymnasium_check_env_with_render_check(env_id: str) -> None:
    env = gym.make(env_id, render_mode="rgb_array")
    gym_check_env(env.unwrapped, skip_render_check=False)
    env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_sb3_check_env(env_id: str) -> None:
    sb3_check_env(gym.make(env_id).unwrapped, warn=False)


@pytest.mark.parametrize("mode", ["sync", "async"])
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_gymnasium_make_vec(env_id: str, mode: str) -> None:
    venv = gym.make_vec(env_id, num_envs=2, vectorization_mode=mode)
    try:
        obs, _ = venv.reset(seed=0)
        assert venv.observation_space.contains(obs)
        venv.action_space.seed(0)
        for _ in range(4):  # sampled actions: masked ones included
            obs, rew, _term, _trunc, _info = venv.step(venv.action_space.sample())
            assert venv.observation_space.contains(obs) and np.all(np.isfinite(rew))
    finally:
        venv.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_sb3_make_vec_env_renders(env_id: str) -> None:
    venv = make_vec_env(env_id, n_envs=2, seed=0)  # passes render_mode="rgb_array"
    try:
        assert venv.get_attr("render_mode") == ["rgb_array", "rgb_array"]
        venv.reset()
        frames = venv.get_images()
        assert len(frames) == 2 and all(f.ndim == 3 and f.dtype == np.uint8 for f in frames)
        acts = np.stack([venv.action_space.sample() for _ in range(2)])
        venv.step(acts)
    finally:
        venv.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_plain_ppo_trains_on_defaults(env_id: str) -> None:
    rec = InfoRecorder()
    model = PPO("MultiInputPolicy", gym.make(env_id), **PPO_ARGS)
    model.learn(192, callback=rec)  # plain PPO samples masked / infeasible actions: no crash
    assert len(rec.infos) == 192
    assert all(isinstance(i["invalid_action"], bool) for i in rec.infos)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_maskable_ppo_trains_on_defaults(env_id: str) -> None:
    rec = InfoRecorder()
    model = MaskablePPO("MultiInputPolicy", gym.make(env_id), **PPO_ARGS)
    model.learn(192, callback=rec)
    assert len(rec.infos) == 192
    if env_id != "selenv/ReceiverClustering-v1":  # exact masks: never an invalid action
        assert not any(i["invalid_action"] for i in rec.infos)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_unknown_keyword_is_a_type_error_and_bad_render_mode_a_value_error(env_id: str) -> None:
    with pytest.raises(TypeError, match="not_a_keyword"):
        gym.make(env_id, not_a_keyword=1)
    with pytest.raises(ValueError, match="render_mode"):
        gym.make(env_id, render_mode="ansi")
    with pytest.raises(ValueError, match="invalid_action"):
        gym.make(env_id, invalid_action="ignore")
    with pytest.raises(ValueError, match="invalid_action_penalty"):
        gym.make(env_id, invalid_action_penalty=float("nan"))


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_spec_max_episode_steps_is_set(env_id: str) -> None:
    env = gym.make(env_id)
    steps = env.spec.max_episode_steps
    assert isinstance(steps, int) and steps == env.unwrapped.max_episode_steps > 0
    assert gym.make(env_id, max_episode_steps=3).spec.max_episode_steps == 3  # user's wins


# -- PettingZoo and SuperSuit -------------------------------------------------------------------
@pytest.mark.parametrize("module", MODULES, ids=lambda m: m.__name__.rsplit(".", 1)[-1])
def test_pettingzoo_tests_on_defaults(module: Any) -> None:
    parallel_api_test(module.parallel_env(), num_cycles=100)
    parallel_seed_test(module.parallel_env)
    api_test(module.env(), num_cycles=20)
    state_test(module.env(), module.parallel_env(), num_cycles=5)


@pytest.mark.parametrize(
    "module",
    [fim_selection_v0, receiver_clustering_v0, receiver_clustering_v1],
    ids=lambda m: m.__name__.rsplit(".", 1)[-1],
)
def test_pettingzoo_max_cycles(module: Any) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # receiver_clustering_v0
        max_cycles_test(module)
        assert module.parallel_env().metadata["name"] == module.__name__.rsplit(".", 1)[-1]
        assert module.env().metadata["name"] == module.__name__.rsplit(".", 1)[-1]
    for bad, err in ((0, ValueError), (2.0, TypeError), (True, TypeError)):
        with pytest.raises(err, match="max_cycles"):
            module.parallel_env(max_cycles=bad)


@pytest.mark.parametrize("module", MODULES, ids=lambda m: m.__name__.rsplit(".", 1)[-1])
def test_max_cycles_beyond_the_episode_changes_nothing(module: Any) -> None:
    """A cap longer than the episode: the same steps, rewards and ends as no cap."""
    runs = []
    for cap in (None, 10**6):
        env = module.parallel_env(max_cycles=cap)
        obs, _ = env.reset(seed=3)
        rng, trace = np.random.default_rng(0), []
        while env.agents:
            masks = {a: obs[a]["action_mask"] for a in env.agents}
            acts = {a: int(np.argmax(rng.random(m.shape) + m)) for a, m in masks.items()}
            obs, rew, term, trunc, _ = env.step(acts)
            trace.append((sorted(rew.items()), sorted(term.items()), sorted(trunc.items())))
        runs.append(trace)
    assert runs[0] == runs[1] and not any(t for _, _, tr in runs[0] for _, t in tr)


@pytest.mark.parametrize("module", MODULES, ids=lambda m: m.__name__.rsplit(".", 1)[-1])
def test_pettingzoo_module_conventions(module: Any) -> None:
    from pettingzoo import AECEnv, ParallelEnv
    from pettingzoo.utils.wrappers import OrderEnforcingWrapper

    assert isinstance(module.parallel_env(), ParallelEnv)
    assert isinstance(module.raw_env(), AECEnv)
    assert isinstance(module.env(), OrderEnforcingWrapper)
    penv = module.parallel_env(render_mode="rgb_array")
    penv.reset(seed=0)
    assert penv.state_space.contains(penv.state())
    frame = penv.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3
    with pytest.raises(TypeError, match="not_a_keyword"):
        module.parallel_env(not_a_keyword=1)


@pytest.mark.parametrize("module", MODULES, ids=lambda m: m.__name__.rsplit(".", 1)[-1])
def test_supersuit_pipeline_trains_sb3_ppo(module: Any) -> None:
    penv = module.parallel_env()
    venv = ss.pettingzoo_env_to_vec_env_v1(penv)
    venv = ss.concat_vec_envs_v1(venv, 2, num_cpus=0, base_class="stable_baselines3")
    rec = InfoRecorder()
    set_random_seed(0)  # SuperSuit's SB3 wrapper has no seed(): PPO(seed=...) would fail
    model = PPO("MultiInputPolicy", venv, n_steps=16, batch_size=64, n_epochs=1)
    model.learn(16 * venv.num_envs, callback=rec)  # one rollout and one update
    assert model.num_timesteps == 16 * venv.num_envs
    assert len(rec.infos) == 16 * venv.num_envs  # one info per agent slot per step
    venv.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_human_render_mode_runs_headless(env_id: str) -> None:
    env = gym.make(env_id, render_mode="human")  # matplotlib window; Agg here: draws only
    env.reset(seed=0)
    assert env.render() is None
    env.close()
    env.close()  # idempotent
