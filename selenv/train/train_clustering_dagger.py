"""One DAgger round for a ranking-trained ``ReceiverClustering-v1`` policy (Ross et al. 2011).

The ranking stage of :mod:`selenv.train.train_clustering_ppo` labels states that the greedy expert
visits; the policy then meets states of its own. Here the policy (acting as
``SB3PolicyAgent(checkpoint, verify_top_k=behaviour_top_k)``) drives the labelling
trajectories, the exact Algorithm 1 cost change of every edit labels them
(:func:`selenv.learned.rl.ranking.collect_clustering_ranking` with ``behaviour``), and the policy's
logits are fitted to those labels (ListNet, :func:`selenv.learned.rl.ranking.fit_ranking`),
starting from the checkpoint's weights. The result is saved with the source metadata plus a
``dagger`` block, and evaluated like the training scripts do.

    python -m selenv.train.train_clustering_dagger   # -> runs/train_clustering_dagger/policy.zip

``--scorer checkpoint`` (default) fits the checkpoint's own architecture from its weights
(``mlp`` or ``factorised``, whichever it has: :mod:`selenv.learned.rl.edit_policy`);
``--scorer factorised`` / ``mlp`` fits a *fresh* policy of that scorer (the checkpoint's
``hidden``, ``activation`` and ``gain_skip_init``) to the labels the checkpoint's behaviour
collected, e.g. to distil the shipped ``mlp`` policy into the cheaper factorised one.

The shipped ``checkpoints/receiver_clustering_ppo.zip`` is one such round on the ranking-trained
policy: ``configs/receiver_clustering_ppo.toml`` (its header gives both commands).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import torch

from selenv.atomic import write_json
from selenv.learned.config import arg, check_outputs, parse_config
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, load_metadata
from selenv.learned.rl.candidate_policy import make_ppo
from selenv.learned.rl.edit_policy import (
    SCORERS,
    edit_model_from_checkpoint,
    is_edit_architecture,
    scorer_policy_kwargs,
)
from selenv.learned.rl.ranking import collect_clustering_ranking, fit_ranking
from selenv.learned.rl.safe_load import model_from_checkpoint
from selenv.learned.rl.training import (
    evaluate_checkpoint,
    output_lock,
    read_checkpoint_metadata,
    run_cli,
    save_checkpoint,
    verify_pair,
)
from selenv.learned.rl.views import CandidateViewWrapper, view_for

ENV_ID = "selenv/ReceiverClustering-v1"
SCRIPT = "selenv.train.train_clustering_dagger"


@dataclass
class Config:
    """Every field is a ``--kebab-case`` option."""

    checkpoint: str = arg(
        str(DEFAULT_CHECKPOINTS[ENV_ID]), "the policy to improve (a ReceiverClustering-v1 .zip)"
    )
    out: str = arg(
        "runs/train_clustering_dagger/policy.zip",
        "the improved checkpoint (.zip); its metadata goes next to it as .json",
    )
    force: bool = arg(False, "overwrite an existing --out (.zip or .json)")
    env_kwargs: str = arg(
        json.dumps({"preset": "paper", "n_agents": 30, "horizon": 500}),
        "JSON object of gymnasium.make keyword arguments of the labelling episodes",
    )
    states: int = arg(3000, "labelled states (visited by the policy)")
    behaviour_top_k: int = arg(
        4, "the behaviour plays as ppo_topK: its K best edits costed, the best played"
    )
    explore: float = arg(0.05, "random edit probability on the labelling trajectories")
    label_every: int = arg(5, "a state is labelled every k-th filter step")
    epochs: int = arg(10, "epochs of the ranking fit (ListNet)")
    learning_rate: float = arg(5e-4, "Adam learning rate of the ranking fit")
    temperature: float = arg(
        0.1, "temperature T of the ListNet targets softmax(-dJ / (T * spread of dJ))"
    )
    workers: int = arg(2, "labelling worker processes")
    seed: int = arg(1, "seed of the labelling episodes and the fit")
    progress: bool = arg(True, "show tqdm bars")
    eval_episodes: int = arg(
        10, "held-out episodes on which the saved checkpoint is evaluated (0: none)"
    )
    eval_seed: int = arg(10_000, "seed of the first held-out episode (then +1, +2, ...)")
    verify_top_k: str = arg("4,8", "evaluated variants ppo_topK: comma-separated K (empty: none)")
    baselines: str = arg("ga", "comma-separated registered agents evaluated next to the policy")
    scorer: str = arg(
        "checkpoint",
        "the policy fitted: checkpoint (the checkpoint's architecture, from its weights), or "
        "factorised / mlp (a fresh policy of that edit scorer, fitted to the labels of the "
        "checkpoint's behaviour)",
    )
    edit_rank: int = arg(16, "rank k of a fresh factorised scorer (with --scorer factorised)")


def fresh_model(
    meta: dict[str, Any], env: gym.Env[Any, Any], scorer: str, rank: int, seed: int
) -> tuple[Any, dict[str, Any]]:
    """An untrained model of edit scorer ``scorer`` on ``env``, and its ``architecture`` block.

    The widths, activation and gain skip are the source checkpoint's (``meta``); its algorithm
    (``training.algorithm``) too; ``seed`` initialises the weights.

    Raises:
        ValueError: an unknown ``scorer`` or an incomplete ``meta["architecture"]``.
    """
    extractor, extra = scorer_policy_kwargs(scorer, rank)
    src = meta.get("architecture")
    if not isinstance(src, dict):
        raise ValueError(f"--checkpoint metadata lacks an 'architecture' object: {src!r}")
    try:
        kw = {
            "hidden": [int(h) for h in src["hidden"]],
            "activation": str(src["activation"]),
            "gain_skip_init": float(src.get("gain_skip_init", 0.0)),
            **extra,
        }
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"--checkpoint metadata: incomplete architecture: {exc!r}") from exc
    training = meta.get("training")
    is_ppo = isinstance(training, dict) and training.get("algorithm") == "PPO"
    net_arch: dict[str, list[int]] = {"pi": [], "vf": [64]}
    model = make_ppo(
        env,
        "ppo" if is_ppo else "maskable_ppo",
        seed=seed,
        policy_kwargs={
            "net_arch": net_arch,
            "features_extractor_class": extractor,
            "features_extractor_kwargs": kw,
        },
    )
    architecture = {
        "policy": f"selenv.learned.rl.candidate_policy.{type(model.policy).__name__}",
        "features_extractor": f"{extractor.__module__}.{extractor.__name__}",
        **kw,
        "net_arch": net_arch,
        "n_parameters": int(sum(p.numel() for p in model.policy.parameters())),
        "pool_size_independent": True,
    }
    return model, architecture


def parse_args(argv: list[str] | None = None) -> Config:
    """The run's :class:`Config` from the command line (and ``--config FILE``)."""
    return parse_config(Config, argv, (__doc__ or "").split("\n")[0], script=SCRIPT)


def outputs(cfg: Config) -> list[Path]:
    """The files the run writes: the checkpoint and its ``.json`` metadata."""
    out = Path(cfg.out)
    return [out, out.with_suffix(".json")]


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Collect, fit, save, evaluate; return the new checkpoint's metadata."""
    cfg = parse_args(argv)
    check_outputs(f"python -m {SCRIPT}", outputs(cfg), force=cfg.force)
    with output_lock(cfg.out, f"python -m {SCRIPT}"):  # one run per --out
        return _run(cfg)


def _run(cfg: Config) -> dict[str, Any]:
    """The round itself (``main`` after the output checks, holding the lock)."""
    out = Path(cfg.out)
    if out.suffix != ".zip":
        raise ValueError(f"--out must end in .zip, got {cfg.out!r}")
    if cfg.scorer not in ("checkpoint", *SCORERS):
        raise ValueError(f"--scorer must be one of {['checkpoint', *SCORERS]}, got {cfg.scorer!r}")
    if cfg.edit_rank < 1:
        raise ValueError(f"--edit-rank must be >= 1, got {cfg.edit_rank}")
    meta = load_metadata(cfg.checkpoint)
    if Path(cfg.checkpoint).with_suffix(".json").is_file():  # refuse a mismatched pair
        verify_pair(cfg.checkpoint, read_checkpoint_metadata(cfg.checkpoint))
    if meta.get("env_id") != ENV_ID:
        raise ValueError(f"--checkpoint {cfg.checkpoint} was trained on {meta.get('env_id')!r}")
    kwargs = json.loads(cfg.env_kwargs)
    torch.set_num_threads(1)
    start = time.perf_counter()
    data = collect_clustering_ranking(
        kwargs,
        cfg.states,
        cfg.seed,
        label_every=cfg.label_every,
        explore=cfg.explore,
        workers=cfg.workers,
        progress=cfg.progress,
        behaviour=cfg.checkpoint,
        behaviour_top_k=cfg.behaviour_top_k,
    )
    # weights read safely (never SB3's load(), which unpickles the zip), onto a fresh model
    env = gym.make(ENV_ID, **{**kwargs, "action_mode": "edit"})
    env = CandidateViewWrapper(env, view_for(ENV_ID, env, meta.get("view")))
    if cfg.scorer == "checkpoint":
        loader = edit_model_from_checkpoint if is_edit_architecture(meta) else model_from_checkpoint
        model = loader(cfg.checkpoint, meta, env)
    else:
        model, architecture = fresh_model(meta, env, cfg.scorer, cfg.edit_rank, cfg.seed)
        meta = {**meta, "architecture": architecture}
    fit = fit_ranking(
        model.policy,
        data,
        epochs=cfg.epochs,
        learning_rate=cfg.learning_rate,
        temperature=cfg.temperature,
        seed=cfg.seed,
        progress=cfg.progress,
    )
    meta = {
        **meta,
        "dagger": {**asdict(cfg), **fit, "wall_seconds": round(time.perf_counter() - start, 1)},
        "metrics": None,
    }
    meta.pop("checkpoint_sha256", None)  # the source's: replaced by the new zip's
    json_path = out.with_suffix(".json")
    save_checkpoint(model, meta, out)  # zip + JSON as an atomic pair
    if cfg.eval_episodes:
        eval_kwargs = meta.get("eval_env_kwargs", kwargs)
        ks = [int(k) for k in cfg.verify_top_k.split(",") if k.strip()]
        meta["metrics"] = evaluate_checkpoint(
            out,
            env_id=ENV_ID,
            make_eval_env=lambda: gym.make(ENV_ID, **eval_kwargs),
            seeds=[cfg.eval_seed + e for e in range(cfg.eval_episodes)],
            baselines=cfg.baselines,
            policy_variants={f"ppo_top{k}": {"verify_top_k": k} for k in ks},
        )
        write_json(json_path, meta)
        summary = {k: v["mean_final_objective"] for k, v in meta["metrics"]["agents"].items()}
        print(json.dumps({"mean_final_objective": summary}, indent=2))
    return meta


def cli() -> None:
    """Console-script entry point (same options as ``main``).

    Exit code 0 after a run, 2 on a usage error or a busy ``--out``, 1 on an I/O failure,
    130 / 143 after SIGINT / SIGTERM.
    """
    raise SystemExit(run_cli(main, f"python -m {SCRIPT}"))


if __name__ == "__main__":
    cli()
