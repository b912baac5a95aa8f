"""Train MaskablePPO on ``selenv/CLScheduling-v1`` (which relative measurements to fuse).

The env's observation is rewritten by :class:`selenv.families.cooperative.view.CLView`: the
directed pairs (and the stop action) become candidates with the pair's gain and the two agents'
uncertainties, so the policy does not depend on the number of pairs. The gain is, by default
(``--view cl_pairs_fused``), the exact previewed decrease of the objective by the pair's fused
update -- the quantity the greedy agent maximises, so with the gain skip the untrained policy
is a softened greedy -- or (``--view cl_pairs``) the env's cheap naive-EKF proxy, which
needs no preview (the shipped ``checkpoints/cl_scheduling_ppo_proxy.zip``). Evaluation: the
saved checkpoint against ``greedy`` (previews every pair's fused update), ``round_robin`` and
``random`` with the same fusion, on held-out seeds.

    python -m selenv.train.train_cl_ppo   # -> runs/train_cl_ppo/policy.zip (+ .json)

The shipped checkpoints' runs: ``configs/cl_scheduling_ppo.toml`` and
``configs/cl_scheduling_ppo_proxy.toml`` (``--config FILE``).
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
from selenv.learned.rl.views import CandidateViewWrapper, view_for
from selenv.learned.trainer import Script

ENV_ID = "selenv/CLScheduling-v1"
SCRIPT = "selenv.train.train_cl_ppo"


@dataclass
class Config(PPOConfig):
    """Defaults: the env the bench plays, the shipped run's PPO settings; under ``runs/``."""

    env_kwargs: str = arg(
        "{}",
        "JSON object of gymnasium.make keyword arguments ({}: CLScheduling-v1's defaults, the "
        "env the bench plays; the shipped checkpoints were trained on "
        '{"preset": "dense", "n_agents": 4, "budget": 2, "fusion": "dmv", "horizon": 100}, '
        "see configs/cl_scheduling_ppo.toml)",
    )
    total_timesteps: int = arg(
        60_000,
        "PPO environment steps in total (the shipped cl_scheduling_ppo: 60,416 steps, ~4 min "
        "on 2 cores)",
    )
    n_envs: int = 4
    vec_env: str = "native"
    n_steps: int = 256
    batch_size: int = 256
    gain_skip_init: float = 2.0
    out: str = "runs/train_cl_ppo/policy.zip"
    eval_episodes: int = 20
    baselines: str = "greedy,round_robin,random"
    view: str = arg(
        "cl_pairs_fused",
        "candidate view (selenv.learned.rl.views): cl_pairs_fused (each pair's previewed "
        "fused gain, the shipped run), cl_pairs (the naive-EKF proxy, no previews: "
        "cl_scheduling_ppo_proxy, trained with --view cl_pairs --gain-skip-init 1) or "
        "cl_pairs_fused_top3 (stop and the 3 pairs of largest previewed gain)",
    )


RUN = Script(SCRIPT, Config, __doc__)


def make_env(kwargs: dict[str, Any], view: str = "cl_pairs") -> gym.Env[Any, Any]:
    """One training env: the CL env in its pairs-as-candidates view (``cl_pairs[_fused]``)."""
    env = gym.make(ENV_ID, **kwargs)
    return CandidateViewWrapper(env, view_for(ENV_ID, env, view))


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
            make_env=lambda: make_env(kwargs, cfg.view),
            native={"env_id": ENV_ID, "env_kwargs": kwargs, "view": cfg.view},
            make_eval_env=lambda: gym.make(ENV_ID, **kwargs),
            view=cfg.view,
            tb_name="cl_ppo",
        )


#: the console script: ``main`` with the exit codes of :func:`selenv.learned.trainer.run_cli`
#: (0; 2 usage error or busy ``--out``; 1 I/O failure; 130 / 143 / 75 stopped and saved)
cli = RUN.command(main)


if __name__ == "__main__":
    cli()
