"""Train MaskablePPO on ``selenv/LandmarkSelection-v0`` (Soubaras & Chahbazian 2023).

The env already observes candidates (per-landmark gain, whitened Jacobian rows, features), so
the candidate-scoring policy reads it as is. The return is the sum over the flight of
``-cost`` (eq. 11): a non-myopic policy could beat the paper's per-step brute force, which
solves only the first term of the Bellman equation (13). Evaluation: the saved checkpoint
against ``brute_force``, ``vns``, ``greedy`` and ``random`` on held-out seeds.

    python -m selenv.train.train_landmark_ppo   # -> checkpoints/landmark_selection_ppo.zip
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import gymnasium as gym

from selenv.learned.config import parse_config
from selenv.learned.rl.training import PPOConfig, train

ENV_ID = "selenv/LandmarkSelection-v0"


@dataclass
class Config(PPOConfig):
    """Defaults of the shipped run."""

    env_kwargs: str = json.dumps({"n_landmarks": 30, "k": 2, "horizon": 100})
    total_timesteps: int = 100_000
    n_envs: int = 4
    vec_env: str = "subproc"
    n_steps: int = 256
    batch_size: int = 256
    gain_skip_init: float = 1.0
    out: str = "checkpoints/landmark_selection_ppo.zip"
    eval_episodes: int = 20
    baselines: str = "brute_force,vns,greedy,random"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Train, save, evaluate; return the checkpoint's metadata."""
    cfg = parse_config(Config, argv, (__doc__ or "").split("\n")[0])
    kwargs = cfg.kwargs()
    return train(
        cfg,
        env_id=ENV_ID,
        make_env=lambda: gym.make(ENV_ID, **kwargs),
        make_eval_env=lambda: gym.make(ENV_ID, **kwargs),
        view="identity",
        tb_name="landmark_ppo",
    )


if __name__ == "__main__":
    main()
