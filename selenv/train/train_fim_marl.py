"""Train one shared MaskablePPO policy for every agent of ``selenv.multiagent.fim_selection_v0``.

Multi-agent FIM selection (Kirchner et al. 2020, Example 3: two agents with camera + Doppler
pools). The PettingZoo -> SB3 path is :class:`selenv.learned.rl.marl.SharedPolicyEnv`: the parallel
env is played turn by turn, each Gymnasium step being one agent's pick, so a single
candidate-scoring policy acts for all agents (parameter sharing) and the return is the team's
log-det gain. Trained in ``mode="cooperative"`` (agents take turns and see the shared FIM);
evaluated against cooperative greedy and independent greedy (Algorithm 1 per agent, no
communication) on held-out seeds, in both modes.

    python -m selenv.train.train_fim_marl   # -> runs/train_fim_marl/policy.zip (+ .json)
    python -m selenv.train.train_fim_marl --config configs/fim_marl_ppo.toml \
        --out checkpoints/fim_marl_ppo.zip --force        # the shipped checkpoint, again

``--eval-only --out FILE --force`` re-evaluates the checkpoint ``FILE`` and rewrites the
metrics in its JSON (``--force``: the JSON is an existing output).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from selenv.atomic import write_json
from selenv.families.fim.agents import CooperativeGreedyPolicy
from selenv.learned.config import arg, check_outputs, usage_error
from selenv.learned.rl.marl import SharedPolicyEnv
from selenv.learned.rl.safe_load import load_policy
from selenv.learned.rl.training import (
    PPOConfig,
    output_lock,
    output_paths,
    ppo_run,
    read_checkpoint_metadata,
    train,
    verify_pair,
)
from selenv.learned.trainer import Script
from selenv.multiagent import fim_selection_v0

ENV_ID = "selenv.multiagent.fim_selection_v0"
SCRIPT = "selenv.train.train_fim_marl"


@dataclass
class Config(PPOConfig):
    """Defaults of the shipped run, written under ``runs/``."""

    env_kwargs: str = json.dumps({"preset": "example3_moving", "n_candidates": 50, "budgets": 5})
    mode: str = arg(
        "cooperative",
        "mode the shared policy is trained in: cooperative (turns, shared FIM) or independent",
        choices=("cooperative", "independent"),
    )
    total_timesteps: int = arg(
        100_000,
        "PPO environment steps in total (the shipped fim_marl_ppo: 100,352 steps, ~3 min on 2 "
        "cores; fim_marl_ppo_independent, --mode independent: 300,032 steps, ~9 min)",
    )
    vec_env: str = arg(
        "dummy",
        "dummy or subproc (the shared-policy PettingZoo wrapper has no native vector env)",
    )
    out: str = "runs/train_fim_marl/policy.zip"
    eval_episodes: int = arg(
        50, "held-out episodes of the policy and the greedy schemes, in both modes (0: none)"
    )
    eval_only: bool = arg(
        False,
        "skip training: re-evaluate the checkpoint at --out and rewrite the metrics "
        "in its JSON (needs --force)",
    )


RUN = Script(SCRIPT, Config, __doc__)


def play(policy: Any, kwargs: dict[str, Any], mode: str, seed: int) -> float:
    """Final fusion-centre objective of one episode; ``policy`` is a model or greedy."""
    penv = fim_selection_v0.parallel_env(mode=mode, **kwargs)
    if isinstance(policy, CooperativeGreedyPolicy):
        obs, infos = penv.reset(seed=seed)
        while penv.agents:
            obs, _, _, _, infos = penv.step(policy.act(obs, penv.agents))
        return float(next(iter(infos.values()))["objective"])
    env = SharedPolicyEnv(penv)
    o, info = env.reset(seed=seed)
    done = False
    while not done:
        action, _ = policy.predict(o, action_masks=env.action_masks(), deterministic=True)
        o, _, terminated, truncated, info = env.step(int(action))
        done = terminated or truncated
    return float(info["objective"])


#: the run's :class:`Config` from the command line (and ``--config FILE``)
parse_args = RUN.parse


def outputs(cfg: Config) -> list[Path]:
    """The files the run writes (``--eval-only``: the checkpoint's JSON only)."""
    return output_paths(cfg)[1:] if cfg.eval_only else output_paths(cfg)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Train the shared policy, save it, compare it with the greedy schemes; return metadata."""
    cfg = parse_args(argv)
    prog = RUN.prog
    if cfg.eval_only:  # re-evaluate the checkpoint at --out, rewrite its metrics
        if not Path(cfg.out).is_file():
            usage_error(prog, f"--eval-only: no checkpoint {cfg.out}")
        check_outputs(prog, outputs(cfg), force=cfg.force)
        with output_lock(cfg.out, prog):
            try:
                meta = read_checkpoint_metadata(cfg.out)
            except ValueError as exc:
                usage_error(prog, exc)
            kwargs = meta["env_kwargs"]  # what the checkpoint was trained on
            return _evaluate(cfg, kwargs, meta)
    with ppo_run(cfg, prog):  # options and outputs checked, one run per --out
        kwargs = cfg.kwargs()
        meta = train(
            dataclasses.replace(cfg, eval_episodes=0),
            env_id=ENV_ID,
            make_env=lambda: SharedPolicyEnv(
                fim_selection_v0.parallel_env(mode=cfg.mode, **kwargs)
            ),
            make_eval_env=lambda: SharedPolicyEnv(fim_selection_v0.parallel_env(**kwargs)),
            view="shared_policy_turns",
            tb_name="fim_marl_ppo",
            extra_meta={
                "marl": {"path": "selenv.learned.rl.marl.SharedPolicyEnv", "mode": cfg.mode}
            },
        )
        meta["training"]["eval_episodes"] = cfg.eval_episodes  # train() ran none: _evaluate does
        return _evaluate(cfg, kwargs, meta)


def _evaluate(cfg: Config, kwargs: dict[str, Any], meta: dict[str, Any]) -> dict[str, Any]:
    """Final objectives of the shared policy and the greedy schemes on held-out seeds."""
    if cfg.eval_episodes:
        verify_pair(cfg.out, meta)  # the zip is the one this JSON describes
        model = load_policy(cfg.out, meta)  # weights only: never unpickles the zip
        seeds = [cfg.eval_seed + e for e in range(cfg.eval_episodes)]
        greedy = CooperativeGreedyPolicy()
        runs = {
            "shared_ppo_cooperative": (model, "cooperative"),
            "shared_ppo_independent": (model, "independent"),
            "cooperative_greedy": (greedy, "cooperative"),
            "independent_greedy": (greedy, "independent"),
        }
        finals = {k: [play(p, kwargs, m, s) for s in seeds] for k, (p, m) in runs.items()}
        meta["metrics"] = {
            "episodes": len(seeds),
            "eval_seeds": [seeds[0], seeds[-1]],
            "mean_final_objective": {k: round(float(np.mean(v)), 4) for k, v in finals.items()},
            "final_objectives": {k: [round(x, 4) for x in v] for k, v in finals.items()},
        }
        write_json(Path(cfg.out).with_suffix(".json"), meta)
        print(json.dumps(meta["metrics"]["mean_final_objective"], indent=2))
    return meta


#: the console script: ``main`` with the exit codes of :func:`selenv.learned.trainer.run_cli`
#: (0; 2 usage error or busy ``--out``; 1 I/O failure; 130 / 143 / 75 stopped and saved)
cli = RUN.command(main)


if __name__ == "__main__":
    cli()
