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
from pathlib import Path
from typing import Any

import gymnasium as gym

from selenv.learned.config import arg, parse_config
from selenv.learned.rl.training import (
    PPOConfig,
    check_run_outputs,
    output_lock,
    output_paths,
    run_cli,
    train,
)

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


def parse_args(argv: list[str] | None = None) -> Config:
    """The run's :class:`Config` from the command line (and ``--config FILE``)."""
    return parse_config(Config, argv, (__doc__ or "").split("\n")[0], script=SCRIPT)


def outputs(cfg: Config) -> list[Path]:
    """The files the run writes."""
    return output_paths(cfg)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Train, save, evaluate; return the checkpoint's metadata."""
    cfg = parse_args(argv)
    prog = f"python -m {SCRIPT}"
    check_run_outputs(cfg, prog)
    with output_lock(cfg.out, prog):  # one run per --out
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


def cli() -> None:
    """Console-script entry point (same options as ``main``).

    Exit code 0 after a run, 2 on a usage error or a busy ``--out``, 1 on an I/O failure,
    130 / 143 after SIGINT / SIGTERM (the last completed iteration saved, see ``--resume``).
    """
    raise SystemExit(run_cli(main, f"python -m {SCRIPT}"))


if __name__ == "__main__":
    cli()
