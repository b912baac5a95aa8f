"""Train an edit-ranking policy for ``selenv/ReceiverClustering-v1`` (Greiff et al. 2022).

The policy plays the env's ``action_mode="edit"`` encoding (one masked edit per filter step:
no-op, move, leave, swap) through :class:`selenv.families.clustering.view.ClusteringEditView`, which
describes every edit by the receivers' noise levels, the clusters' composition and sizes
-- without evaluating the cost ``J``. Two stages:

1. ranking pre-training (:mod:`selenv.learned.rl.ranking`, ``--rank-states`` > 0): along greedy
   trajectories, every edit of a state is costed exactly (Algorithm 1) and the policy's
   logits are fitted to that ranking (ListNet);
2. MaskablePPO on reward ``-J`` per step (``--total-timesteps``; ``gamma`` < 1, the cost is a
   running one). Default 0: the shipped policy is the ranked one. PPO from scratch did not
   learn in the 30-minute budget (1336 actions, a return dominated by the random noise
   levels: the mean episode return drifted from -54 to -57 over 24k steps), which is why
   stage 1 exists; ``--rank-states 0 --total-timesteps 40000`` reproduces that run.

The edit scorer (``--scorer``): ``factorised`` (default,
:class:`selenv.learned.families.clustering_edits.FactorisedEditScorer`) embeds the ``n``
receivers once and scores each edit by a rank-``k`` bilinear plus additive combination of its
receivers' embeddings -- per-receiver work instead of per-edit work, ~20x the PPO steps per
second of ``mlp`` (MaskablePPO, 4 envs x 128 steps, batch 256); ``mlp``
(:class:`selenv.learned.rl.candidate_policy.CandidateScorer`, the shipped checkpoint's) runs
an MLP on every one of the 1336 edit rows. ``--hidden`` are the widths of the per-receiver
(factorised) or per-edit (mlp) network.

Evaluation on held-out seeds (default assignment encoding): ``ppo`` (the policy's top edit:
no cost evaluation at all), ``ppo_top4`` / ``ppo_top8`` (its 4 / 8 best edits costed, the
best improving one played: <= 4 / 8 evaluations per step) against ``ga`` (20 per step),
``greedy`` and ``fixed_random``.

    python -m selenv.train.train_clustering_ppo   # -> runs/train_clustering_ppo/policy.zip

The shipped ``checkpoints/receiver_clustering_ppo.zip`` is this script's ranking stage with
the ``mlp`` scorer (``configs/receiver_clustering_ppo_ranking.toml``, which sets ``scorer = "mlp"``)
followed by one DAgger round (:mod:`selenv.train.train_clustering_dagger`,
``configs/receiver_clustering_ppo.toml``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym

from selenv.exits import check_size
from selenv.learned.config import arg
from selenv.learned.families.clustering import collect_clustering_ranking
from selenv.learned.families.clustering_edits import SCORERS, scorer_policy_kwargs
from selenv.learned.rl.ranking import fit_ranking
from selenv.learned.rl.training import (
    PPOConfig,
    output_paths,
    ppo_run,
    train,
)
from selenv.learned.rl.views import CandidateViewWrapper, view_for
from selenv.learned.trainer import Script
from selenv.parallel.executors import max_pool_workers

ENV_ID = "selenv/ReceiverClustering-v1"
SCRIPT = "selenv.train.train_clustering_ppo"


@dataclass
class Config(PPOConfig):
    """Defaults: the env the bench plays, the shipped ranking stage's settings; under ``runs/``."""

    env_kwargs: str = arg(
        "{}",
        "JSON object of gymnasium.make keyword arguments ({}: ReceiverClustering-v1's defaults, "
        "the env the bench plays; the shipped checkpoint's ranking stage used "
        '{"preset": "paper", "n_agents": 30, "horizon": 200}, see '
        "configs/receiver_clustering_ppo_ranking.toml)",
    )
    eval_horizon: int = arg(
        500, "episode length of the evaluation episodes (the env's default length)"
    )
    total_timesteps: int = arg(
        0,
        "PPO environment steps after the ranking stage (0: keep the ranked policy; the shipped "
        "receiver_clustering_ppo took none: 6000 ranked states, then one DAgger round of 3000 "
        "with train_clustering_dagger)",
    )
    n_envs: int = 4
    vec_env: str = "native"
    n_steps: int = 256
    batch_size: int = 256
    gamma: float = 0.98
    learning_rate: float = 3e-4
    ent_coef: float = 1e-3
    gain_skip_init: float = arg(
        1.0,
        "initial weight w of the gain skip in every edit's logit (1: the policy starts "
        "at ~94 % 'keep the clustering', see ClusteringEditView)",
    )
    out: str = "runs/train_clustering_ppo/policy.zip"
    eval_episodes: int = 10
    baselines: str = "ga,greedy,fixed_random"
    # stage 1: ranking pre-training (0 states: PPO from scratch)
    hidden: str = "128,128"
    rank_states: int = arg(
        6000, "labelled states of the ranking pre-training (0: none, PPO from scratch)"
    )
    rank_epochs: int = arg(20, "epochs of the ranking fit (ListNet)")
    rank_temperature: float = arg(
        0.1, "temperature T of the ListNet targets softmax(-dJ / (T * spread of dJ))"
    )
    rank_label_every: int = arg(
        5, "the greedy expert edits (and a state is labelled) every k-th filter step"
    )
    rank_explore: float = arg(0.2, "random edit probability on the labelling trajectories")
    rank_workers: int = arg(2, "labelling worker processes")
    rank_horizon: int = arg(500, "episode length of the labelling trajectories")
    verify_top_k: str = arg("4,8", "evaluated variants ppo_topK: comma-separated K (empty: none)")
    # the edit scorer
    scorer: str = arg(
        "factorised",
        "edit scorer: factorised (per-receiver embeddings, each edit a rank-k bilinear plus "
        "additive combination of its receivers': cheap on 1336 edits) or mlp (one MLP on "
        "every edit row, the shipped checkpoint's architecture)",
    )
    edit_rank: int = arg(16, "rank k of the factorised scorer's bilinear source-target term")


RUN = Script(SCRIPT, Config, __doc__)


def make_env(kwargs: dict[str, Any]) -> gym.Env[Any, Any]:
    """One training env: edit encoding, in the edits-as-candidates view."""
    env = gym.make(ENV_ID, **{**kwargs, "action_mode": "edit"})
    return CandidateViewWrapper(env, view_for(ENV_ID, env))


#: the run's :class:`Config` from the command line (and ``--config FILE``)
parse_args = RUN.parse


#: the files the run writes: the checkpoint and its JSON
outputs = output_paths


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Train, save, evaluate; return the checkpoint's metadata."""
    cfg = parse_args(argv)
    prog = RUN.prog
    check_size("--rank-workers", cfg.rank_workers, low=1, high=max_pool_workers(),
               note=" (labelling processes on this machine)")  # fmt: skip
    with ppo_run(cfg, prog):  # options and outputs checked, one run per --out
        if cfg.scorer not in SCORERS:
            raise ValueError(f"--scorer must be one of {list(SCORERS)}, got {cfg.scorer!r}")
        if cfg.edit_rank < 1:
            raise ValueError(f"--edit-rank must be >= 1, got {cfg.edit_rank}")
        extractor, extractor_kwargs = scorer_policy_kwargs(cfg.scorer, cfg.edit_rank)
        kwargs = cfg.kwargs()
        eval_kwargs = {**kwargs, "horizon": cfg.eval_horizon}
        eval_kwargs.pop("action_mode", None)

        def pretrain(model: Any) -> dict[str, Any]:
            if cfg.rank_states <= 0:
                return {"method": None}
            data = collect_clustering_ranking(
                {**kwargs, "horizon": cfg.rank_horizon},
                cfg.rank_states,
                cfg.seed,
                label_every=cfg.rank_label_every,
                explore=cfg.rank_explore,
                workers=cfg.rank_workers,
                progress=cfg.progress,
            )
            metrics = fit_ranking(
                model.policy,
                data,
                epochs=cfg.rank_epochs,
                temperature=cfg.rank_temperature,
                seed=cfg.seed,
                progress=cfg.progress,
            )
            return {
                "method": "listnet ranking of exact edit costs (selenv.learned.rl.ranking)",
                **metrics,
            }

        ks = [int(k) for k in cfg.verify_top_k.split(",") if k.strip()]
        return train(
            cfg,
            env_id=ENV_ID,
            make_env=lambda: make_env(kwargs),
            native={
                "env_id": ENV_ID,
                "env_kwargs": {**kwargs, "action_mode": "edit"},
                "view": "clustering_edits",
            },
            make_eval_env=lambda: gym.make(ENV_ID, **eval_kwargs),
            view="clustering_edits",
            tb_name="clustering_ppo",
            extra_meta={"eval_env_kwargs": eval_kwargs},
            pretrain=pretrain,
            policy_variants={f"ppo_top{k}": {"verify_top_k": k} for k in ks},
            features_extractor=extractor,
            extractor_kwargs=extractor_kwargs,
        )


#: the console script: ``main`` with the exit codes of :func:`selenv.learned.trainer.run_cli`
#: (0; 2 usage error or busy ``--out``; 1 I/O failure; 130 / 143 / 75 stopped and saved)
cli = RUN.command(main)


if __name__ == "__main__":
    cli()
