"""Train MaskablePPO on ``selenv/LandmarkSelection-v1`` (Soubaras & Chahbazian 2023).

The env already observes candidates (per-landmark gain, whitened Jacobian rows, features), so
the candidate-scoring policy reads it as is. The return is the sum over the flight of
``-cost`` (eq. 11): a non-myopic policy could beat the paper's per-step brute force, which
solves only the first term of the Bellman equation (13). Evaluation: the saved checkpoint
against ``brute_force``, ``vns``, ``greedy`` and ``random`` on held-out seeds.

    python -m selenv.train.train_landmark_ppo   # -> runs/train_landmark_ppo/policy.zip (+ .json)

The shipped ``checkpoints/landmark_selection_ppo_v01.zip`` is this script's run
(``configs/landmark_selection_ppo_v01.toml``); ``landmark_selection_ppo.zip`` is that policy
after expert iteration (:mod:`selenv.train.train_landmark_expert`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym

from selenv.learned.config import arg
from selenv.learned.rl.training import (
    PPOConfig,
    output_paths,
    ppo_run,
    train,
)
from selenv.learned.trainer import Script

ENV_ID = "selenv/LandmarkSelection-v1"
SCRIPT = "selenv.train.train_landmark_ppo"


@dataclass
class Config(PPOConfig):
    """Defaults: the env the bench plays, the v0.1 run's PPO settings; under ``runs/``."""

    env_kwargs: str = arg(
        "{}",
        "JSON object of gymnasium.make keyword arguments ({}: LandmarkSelection-v1's defaults, "
        'the env the bench plays; the v0.1 policy was trained on {"n_landmarks": 30, "k": 2, '
        '"horizon": 100}, see configs/landmark_selection_ppo_v01.toml)',
    )
    total_timesteps: int = arg(
        100_000,
        "PPO environment steps in total (the v0.1 policy: 100,352 steps, ~5 min on 2 cores; "
        "the shipped landmark_selection_ppo then took 3 expert-iteration rounds, "
        "train_landmark_expert)",
    )
    n_envs: int = 4
    vec_env: str = "native"
    n_steps: int = 256
    batch_size: int = 256
    gain_skip_init: float = 1.0
    out: str = "runs/train_landmark_ppo/policy.zip"
    eval_episodes: int = 20
    baselines: str = "brute_force,vns,greedy,random"


RUN = Script(SCRIPT, Config, __doc__)


#: the run's :class:`Config` from the command line (and ``--config FILE``)
parse_args = RUN.parse


#: the files the run writes: the checkpoint and its JSON
outputs = output_paths


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Train, save, evaluate; return the checkpoint's metadata."""
    cfg = parse_args(argv)
    with ppo_run(cfg, RUN.prog):  # options and outputs checked, one run per --out
        kwargs = cfg.kwargs()
        return train(
            cfg,
            env_id=ENV_ID,
            make_env=lambda: gym.make(ENV_ID, **kwargs),
            make_eval_env=lambda: gym.make(ENV_ID, **kwargs),
            view="identity",
            tb_name="landmark_ppo",
            native={"env_id": ENV_ID, "env_kwargs": kwargs, "view": None},
        )


#: the console script: ``main`` with the exit codes of :func:`selenv.learned.trainer.run_cli`
#: (0; 2 usage error or busy ``--out``; 1 I/O failure; 130 / 143 / 75 stopped and saved)
cli = RUN.command(main)


if __name__ == "__main__":
    cli()
