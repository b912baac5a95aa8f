"""Train MaskablePPO on ``selenv/FIMSelection-v1`` and compare it with greedy and random.

CleanRL-style: :class:`Config` (the command line, with this env's defaults) then
:func:`selenv.learned.rl.training.train` (envs, model, tqdm + TensorBoard, checkpoint + JSON,
evaluation of the saved checkpoint against ``greedy`` and ``random`` on held-out seeds).

    python -m selenv.train.train_fim_ppo          # -> runs/train_fim_ppo/policy.zip (+ .json)
    python -m selenv.train.train_fim_ppo --config configs/fim_selection_ppo.toml \
        --out checkpoints/fim_selection_ppo.zip --force    # the shipped checkpoint, again
    tensorboard --logdir runs
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym

from selenv.learned.config import parse_config
from selenv.learned.rl.training import (
    PPOConfig,
    check_run_outputs,
    output_lock,
    output_paths,
    run_cli,
    train,
)

ENV_ID = "selenv/FIMSelection-v1"
SCRIPT = "selenv.train.train_fim_ppo"


@dataclass
class Config(PPOConfig):
    """Defaults of the shipped run (140k steps, ~6 min on 2 cores), written under ``runs/``."""

    env_kwargs: str = json.dumps({"preset": "example2_moving", "n_candidates": 100, "budget": 10})
    total_timesteps: int = 140_000
    out: str = "runs/train_fim_ppo/policy.zip"
    eval_episodes: int = 100


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
        probe = gym.make(ENV_ID, **kwargs).unwrapped
        m, d, n = int(probe.m), int(probe.d), int(probe.n)  # type: ignore[attr-defined]
        return train(
            cfg,
            env_id=ENV_ID,
            make_env=lambda: gym.make(ENV_ID, **kwargs),
            make_eval_env=lambda: gym.make(ENV_ID, **kwargs),
            view="identity",
            tb_name="fim_ppo",
            native={"env_id": ENV_ID, "env_kwargs": kwargs, "view": None},
            extra_meta={
                "obs_layout": {
                    "m": m,
                    "d": d,
                    "whitened_dim": m * d,
                    "n_features": 4,
                    "n_candidates_trained": n,
                }
            },
        )


def cli() -> None:
    """Console-script entry point (same options as ``main``).

    Exit code 0 after a run, 2 on a usage error or a busy ``--out``, 1 on an I/O failure,
    130 / 143 after SIGINT / SIGTERM (the last completed iteration saved, see ``--resume``).
    """
    raise SystemExit(run_cli(main, f"python -m {SCRIPT}"))


if __name__ == "__main__":
    cli()
