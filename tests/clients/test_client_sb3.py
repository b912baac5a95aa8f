"""Stable-Baselines3 PPO and sb3-contrib's MaskablePPO train on every env at default kwargs.

SB3's own ``make_vec_env`` (a ``DummyVectorEnv`` of ``gym.make(id)``) and its
``MultiInputPolicy`` for the ``Dict`` observations; MaskablePPO reads each env's
``action_masks()`` through SB3's ``env_method`` (ReceiverClustering-v2: the exact mask of its
one Discrete placement). 256 steps each; the rollout buffer must hold finite numbers.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
torch = pytest.importorskip("torch")

from sb3_contrib import MaskablePPO  # noqa: E402
from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.env_util import make_vec_env  # noqa: E402

import selenv  # noqa: E402, F401  (registers the ids)
from selenv.families import FAMILIES  # noqa: E402

IDS = [f.current_id for f in FAMILIES]


@pytest.mark.parametrize("algo", [PPO, MaskablePPO], ids=["ppo", "maskable_ppo"])
@pytest.mark.parametrize("env_id", IDS)
def test_sb3_trains_at_default_kwargs(env_id: str, algo: type) -> None:
    torch.set_num_threads(1)
    venv = make_vec_env(env_id, n_envs=2, seed=0)
    model = algo("MultiInputPolicy", venv, n_steps=64, batch_size=64, n_epochs=1, seed=0,
                 policy_kwargs={"net_arch": [32]}, device="cpu")  # fmt: skip
    model.learn(total_timesteps=256)
    assert model.num_timesteps >= 256
    buf = model.rollout_buffer
    for name in ("rewards", "values", "advantages", "returns", "log_probs"):
        assert np.isfinite(getattr(buf, name)).all(), name
    for key, obs in buf.observations.items():
        assert np.isfinite(obs).all(), key
    venv.close()
