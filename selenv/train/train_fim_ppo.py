"""Train MaskablePPO on ``selenv/FIMSelection-v1`` and compare it with greedy and random.

CleanRL-style: :class:`Config` (the command line, with this env's defaults) then
:func:`selenv.learned.rl.training.train` (envs, model, tqdm + TensorBoard, checkpoint + JSON,
evaluation of the saved checkpoint against ``greedy`` and ``random`` on held-out seeds).

    python -m selenv.train.train_fim_ppo          # -> runs/train_fim_ppo/policy.zip (+ .json)
    python -m selenv.train.train_fim_ppo --config configs/fim_selection_ppo.toml \
        --out checkpoints/fim_selection_ppo.zip --force    # the shipped checkpoint, again
    tensorboard --logdir runs

One checkpoint for every preset and budget: ``--view invariant`` (``d``-independent statistics
of the whitened rows, :class:`selenv.families.fim.view.FIMInvariantView`) with
``--mixture kirchner_presets`` (each training episode one of the six presets at 200 candidates
and budget 5, 10, 15 or 20, :class:`selenv.learned.rl.mixture.EnvMixture`)::

    python -m selenv.train.train_fim_ppo --config configs/fim_selection_ppo_general.toml \
        --out checkpoints/fim_selection_ppo_general.zip --force
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import gymnasium as gym

from selenv.exits import UsageError
from selenv.families.fim.view import WIDTH as INVARIANT_WIDTH
from selenv.learned.config import arg
from selenv.learned.rl.mixture import MIXTURES, EnvMixture, parse_mixture
from selenv.learned.rl.training import (
    PPOConfig,
    check_run_outputs,
    output_lock,
    output_paths,
    train,
)
from selenv.learned.rl.views import CandidateViewWrapper, view_for
from selenv.learned.trainer import Script

ENV_ID = "selenv/FIMSelection-v1"
#: the candidate views this script trains with
VIEW_NAMES = ("identity", "invariant")
SCRIPT = "selenv.train.train_fim_ppo"


@dataclass
class Config(PPOConfig):
    """Defaults of the shipped run (140k steps, ~6 min on 2 cores), written under ``runs/``."""

    env_kwargs: str = json.dumps({"preset": "example2_moving", "n_candidates": 100, "budget": 10})
    total_timesteps: int = arg(
        140_000,
        "PPO environment steps in total (the shipped fim_selection_ppo: 140,288 steps, ~6 min "
        "on 2 cores; fim_selection_ppo_general: 400,384 steps, ~29 min)",
    )
    out: str = "runs/train_fim_ppo/policy.zip"
    eval_episodes: int = 100
    view: str = arg(
        "identity",
        "candidate view: identity (the whitened rows, tied to the preset's parameter "
        "dimension d; the shipped fim_selection_ppo) or invariant (d-independent statistics: "
        "one checkpoint for every preset and budget; fim_selection_ppo_general)",
    )
    mixture: str = arg(
        "",
        "train on several configurations, one drawn per episode: "
        f"{' or '.join(sorted(MIXTURES))} (the six presets at 200 candidates x budgets "
        "5/10/15/20) or a JSON list of env keyword objects; needs --view invariant and "
        "--vec-env dummy or subproc; --env-kwargs stays the evaluation env",
    )


RUN = Script(SCRIPT, Config, __doc__)


#: the run's :class:`Config` from the command line (and ``--config FILE``)
parse_args = RUN.parse


#: the files the run writes: the checkpoint and its JSON
outputs = output_paths


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Train, save, evaluate; return the checkpoint's metadata."""
    cfg = parse_args(argv)
    prog = RUN.prog
    check_run_outputs(cfg, prog)
    if cfg.view not in VIEW_NAMES:
        raise UsageError(f"--view must be one of {list(VIEW_NAMES)}, got {cfg.view!r}")
    mixture = None
    if cfg.mixture:
        try:
            mixture = parse_mixture(cfg.mixture)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        if cfg.view != "invariant":
            raise UsageError(
                f"--mixture needs --view invariant (the {cfg.view!r} view's width depends on "
                "the preset)"
            )
        if cfg.vec_env == "native":
            raise UsageError(
                "--mixture: one native vector env holds one configuration; add --vec-env dummy "
                "(or subproc)"
            )
    with output_lock(cfg.out, prog):  # one run per --out
        kwargs = cfg.kwargs()
        probe = gym.make(ENV_ID, **kwargs).unwrapped
        m, d, n = int(probe.m), int(probe.d), int(probe.n)  # type: ignore[attr-defined]
        if cfg.view == "identity":
            layout = {"m": m, "d": d, "whitened_dim": m * d}
            view_key: str | None = None
        else:
            layout = {"whitened_dim": INVARIANT_WIDTH}
            view_key = cfg.view
        extra: dict[str, Any] = {
            "obs_layout": {**layout, "n_features": 4, "n_candidates_trained": n}
        }
        if mixture is not None:
            extra["mixture"] = mixture

        def make_env() -> gym.Env[Any, Any]:
            if mixture is not None:
                return EnvMixture(ENV_ID, mixture, cfg.view)
            env = gym.make(ENV_ID, **kwargs)
            if view_key is None:
                return env
            return CandidateViewWrapper(env, view_for(ENV_ID, env, view_key))

        return train(
            cfg,
            env_id=ENV_ID,
            make_env=make_env,
            make_eval_env=lambda: gym.make(ENV_ID, **kwargs),
            view=cfg.view,
            tb_name="fim_ppo" if cfg.view == "identity" else f"fim_ppo_{cfg.view}",
            native={"env_id": ENV_ID, "env_kwargs": kwargs, "view": view_key},
            extra_meta=extra,
        )


#: the console script: ``main`` with the exit codes of :func:`selenv.learned.trainer.run_cli`
#: (0; 2 usage error or busy ``--out``; 1 I/O failure; 130 / 143 / 75 stopped and saved)
cli = RUN.command(main)


if __name__ == "__main__":
    cli()
