"""Tianshou 2 trains DQN and PPO on every env with Gymnasium's ``FlattenObservation`` only.

Tianshou stacks every step's ``info`` into its replay buffer: a key present on some steps only,
or a ``str``, leaves holes that it reports as ``MalformedBufferError: Encountered NaNs``. The
envs' fixed info schema is what makes this work. Each run: Tianshou's ``DummyVectorEnv`` of 4
envs, 1,000 env steps through its own trainer, then the buffer is checked for finite numbers.
Needs the ``clients`` extra.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("tianshou")
torch = pytest.importorskip("torch")

from gymnasium.wrappers import FlattenObservation  # noqa: E402
from tianshou.algorithm import DQN, PPO  # noqa: E402
from tianshou.algorithm.modelfree.dqn import DiscreteQLearningPolicy  # noqa: E402
from tianshou.algorithm.modelfree.reinforce import DiscreteActorPolicy  # noqa: E402
from tianshou.algorithm.optim import AdamOptimizerFactory  # noqa: E402
from tianshou.data import Collector, CollectStats, VectorReplayBuffer  # noqa: E402
from tianshou.env import DummyVectorEnv  # noqa: E402
from tianshou.trainer import OffPolicyTrainerParams, OnPolicyTrainerParams  # noqa: E402
from tianshou.utils.net.common import Net  # noqa: E402
from tianshou.utils.net.discrete import DiscreteActor, DiscreteCritic  # noqa: E402

import selenv  # noqa: E402, F401  (registers the ids)
from selenv.families import FAMILIES  # noqa: E402

#: every current id at its default keywords (one Discrete action each)
IDS = [f.current_id for f in FAMILIES]
STEPS = 1000


def _envs(env_id: str, n: int) -> DummyVectorEnv:
    envs = DummyVectorEnv([lambda: FlattenObservation(gym.make(env_id)) for _ in range(n)])
    envs.seed(0)
    return envs


def _dqn(envs: DummyVectorEnv, obs_dim: int, space: gym.spaces.Discrete) -> tuple[Any, Any]:
    net = Net(state_shape=obs_dim, action_shape=int(space.n), hidden_sizes=[64, 64])
    policy = DiscreteQLearningPolicy(model=net, action_space=space, eps_training=0.1)
    algorithm = DQN(policy=policy, optim=AdamOptimizerFactory(lr=1e-3), gamma=0.9,
                    n_step_return_horizon=3, target_update_freq=100)  # fmt: skip
    buffer = VectorReplayBuffer(4 * STEPS, len(envs))
    collector = Collector[CollectStats](algorithm, envs, buffer, exploration_noise=True)
    collector.reset()
    collector.collect(n_step=64)
    params = OffPolicyTrainerParams(
        training_collector=collector, max_epochs=1, epoch_num_steps=STEPS,
        collection_step_num_env_steps=16, batch_size=64,
        update_step_num_gradient_steps_per_sample=0.1, show_progress=False, verbose=False,
    )  # fmt: skip
    return algorithm, params


def _ppo(envs: DummyVectorEnv, obs_dim: int, space: gym.spaces.Discrete) -> tuple[Any, Any]:
    actor = DiscreteActor(preprocess_net=Net(state_shape=obs_dim, hidden_sizes=[64, 64]),
                          action_shape=int(space.n))  # fmt: skip
    critic = DiscreteCritic(preprocess_net=Net(state_shape=obs_dim, hidden_sizes=[64, 64]))
    policy = DiscreteActorPolicy(actor=actor, action_space=space)
    algorithm = PPO(policy=policy, critic=critic, optim=AdamOptimizerFactory(lr=3e-4))
    buffer = VectorReplayBuffer(STEPS, len(envs))
    collector = Collector[CollectStats](algorithm, envs, buffer)
    params = OnPolicyTrainerParams(
        training_collector=collector, max_epochs=1, epoch_num_steps=STEPS,
        collection_step_num_env_steps=256, batch_size=128, update_step_num_repetitions=2,
        show_progress=False, verbose=False,
    )  # fmt: skip
    return algorithm, params


@pytest.mark.parametrize("algo", ["dqn", "ppo"])
@pytest.mark.parametrize("env_id", IDS)
def test_tianshou_trains_with_flatten_observation_only(env_id: str, algo: str) -> None:
    torch.manual_seed(0)
    torch.set_num_threads(1)
    envs = _envs(env_id, 4)
    probe = FlattenObservation(gym.make(env_id))
    obs_dim, space = probe.observation_space.shape[0], probe.action_space
    algorithm, params = (_dqn if algo == "dqn" else _ppo)(envs, obs_dim, space)
    result = algorithm.run_training(params)
    assert result.timing.total_time > 0 and params.training_collector.collect_step >= STEPS
    collector = params.training_collector
    if algo == "ppo":  # on-policy: the buffer was emptied after the last update
        collector.collect(n_step=64)
    batch, _ = collector.buffer.sample(0)  # everything stored
    assert len(batch) > 0
    for key in ("obs", "obs_next", "rew"):
        assert np.isfinite(np.asarray(batch[key], dtype=np.float64)).all(), key
    for key, value in batch.info.items():  # the envs' info, stacked without holes
        assert np.isfinite(np.asarray(value, dtype=np.float64)).all(), f"info[{key!r}]"
    envs.close()
