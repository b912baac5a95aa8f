"""One DAgger round for a ranking-trained ``ReceiverClustering-v1`` policy (Ross et al. 2011).

The ranking stage of :mod:`selenv.train.train_clustering_ppo` labels states that the greedy expert
visits; the policy then meets states of its own. Here the policy (acting as
``SB3PolicyAgent(checkpoint, verify_top_k=behaviour_top_k)``) drives the labelling
trajectories, the exact Algorithm 1 cost change of every edit labels them
(:func:`selenv.learned.families.clustering.collect_clustering_ranking` with ``behaviour``), and
the policy's logits are fitted to those labels (ListNet,
:func:`selenv.learned.rl.ranking.fit_ranking`), starting from the checkpoint's weights. The
result is saved with the source metadata plus a ``dagger`` block, and evaluated like the
training scripts do.

    python -m selenv.train.train_clustering_dagger   # -> runs/train_clustering_dagger/policy.zip

``--scorer checkpoint`` (default) fits the checkpoint's own architecture from its weights
(``mlp`` or ``factorised``, whichever it has: :mod:`selenv.learned.families.clustering_edits`);
``--scorer factorised`` / ``mlp`` fits a *fresh* policy of that scorer (the checkpoint's
``hidden``, ``activation`` and ``gain_skip_init``) to the labels the checkpoint's behaviour
collected, e.g. to distil the shipped ``mlp`` policy into the cheaper factorised one.

Stopping and resuming: once the labels are collected they are saved with the run's state
``<out stem>.last.zip`` (+ ``.json``, ``.labels.npz``, and ``.fit.pt`` mid-fit), rewritten every
``--checkpoint-every`` fit epochs and removed when the run completes. SIGINT / SIGTERM while
labelling abandons the labels (the workers stop; nothing is kept); during the fit the current
epoch completes and the state is saved (``"complete": false``, ``"interrupted"``); the command
exits 130 / 143 with one line naming ``--resume <out stem>.last.zip``, which continues with the
same options to the weights of an uninterrupted run (other options are refused, exit 2).
``--max-minutes M`` stops the same way after the labels are collected or after a fit epoch
(``"interrupted": "max-minutes"``, exit 75). The collection and the fit are the DAgger loop's
(:mod:`selenv.learned.rl.distill`), one round of it.

The shipped ``checkpoints/receiver_clustering_ppo.zip`` is one such round on the ranking-trained
policy: ``configs/receiver_clustering_ppo.toml`` (its header gives both commands).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, cast

import gymnasium as gym
from gymnasium import spaces

from selenv.atomic import write_json
from selenv.exits import Terminated, UsageError
from selenv.learned.config import arg, check_outputs, usage_error
from selenv.learned.families.clustering import collect_clustering_ranking
from selenv.learned.families.clustering_edits import (
    SCORERS,
    edit_model_from_checkpoint,
    is_edit_architecture,
    scorer_policy_kwargs,
)
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, load_metadata
from selenv.learned.rl.candidate_policy import make_ppo
from selenv.learned.rl.distill import (
    FREE_OPTIONS,
    FitOptions,
    Progress,
    collected,
    fit_round,
    read_run_inputs,
    save_state,
)
from selenv.learned.rl.ranking import (
    FitState,
    check_ranking_sizes,
    fit_state_path,
    load_labels,
    read_fit_state,
)
from selenv.learned.rl.safe_load import model_from_checkpoint, read_weights
from selenv.learned.rl.training import evaluate_checkpoint
from selenv.learned.rl.views import CandidateViewWrapper, view_for
from selenv.learned.trainer import (
    RunStop,
    Script,
    check_run_options,
    evaluation_stops,
    last_paths,
    output_lock,
    run_arg,
    save_final,
    set_rng_state,
    stop_exception,
)

ENV_ID = "selenv/ReceiverClustering-v1"
SCRIPT = "selenv.train.train_clustering_dagger"


@dataclass
class Config(FitOptions):
    """The fit options of :class:`~selenv.learned.rl.distill.FitOptions`, and the round's."""

    checkpoint: str = arg(
        str(DEFAULT_CHECKPOINTS[ENV_ID]), "the policy to improve (a ReceiverClustering-v1 .zip)"
    )
    out: str = arg(
        "runs/train_clustering_dagger/policy.zip",
        "the improved checkpoint (.zip); its metadata goes next to it as .json",
    )
    force: bool = run_arg("force", False)
    env_kwargs: str = arg(
        "{}",
        "JSON object of gymnasium.make keyword arguments of the labelling episodes ({}: "
        "ReceiverClustering-v1's defaults, the env the bench plays; the shipped checkpoint: "
        '{"preset": "paper", "n_agents": 30, "horizon": 500}, see '
        "configs/receiver_clustering_ppo.toml)",
    )
    states: int = arg(3000, "labelled states (visited by the policy)")
    behaviour_top_k: int = arg(
        4, "the behaviour plays as ppo_topK: its K best edits costed, the best played"
    )
    explore: float = arg(0.05, "random edit probability on the labelling trajectories")
    label_every: int = arg(5, "a state is labelled every k-th filter step")
    epochs: int = arg(10, "epochs of the ranking fit (ListNet)")
    seed: int = arg(1, "seed of the labelling episodes and the fit")
    eval_episodes: int = run_arg("eval_episodes", 10, note="the saved checkpoint, reloaded")
    eval_seed: int = run_arg("eval_seed", 10_000)
    verify_top_k: str = arg("4,8", "evaluated variants ppo_topK: comma-separated K (empty: none)")
    baselines: str = arg("ga", "comma-separated registered agents evaluated next to the policy")
    scorer: str = arg(
        "checkpoint",
        "the policy fitted: checkpoint (the checkpoint's architecture, from its weights), or "
        "factorised / mlp (a fresh policy of that edit scorer, fitted to the labels of the "
        "checkpoint's behaviour)",
    )
    edit_rank: int = arg(16, "rank k of a fresh factorised scorer (with --scorer factorised)")
    checkpoint_every: int = run_arg(
        "checkpoint_every",
        1,
        unit="fit epochs",
        note="<out stem>.last.zip (+ .json, .labels.npz, .fit.pt) is also written once the "
        "labels are collected",
    )
    resume: str = run_arg(
        "resume",
        "",
        unit="<out stem>.last.zip",
        note="the labels collected, the weights, the fit epoch and its optimizer",
    )
    max_minutes: float | None = run_arg(
        "max_minutes", None, unit="the labels collected or a fit epoch"
    )


RUN = Script(SCRIPT, Config, __doc__)


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


#: the run's :class:`Config` from the command line (and ``--config FILE``)
parse_args = RUN.parse


def outputs(cfg: Config) -> list[Path]:
    """The files the run writes: the checkpoint and its ``.json`` metadata."""
    out = Path(cfg.out)
    return [out, out.with_suffix(".json")]


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Collect, fit, save, evaluate; return the new checkpoint's metadata."""
    cfg = parse_args(argv)
    check_ranking_sizes(cfg)  # every size in range and under its ceiling, before any work
    prog = RUN.prog
    check_run_options(cfg, prog)
    last = last_paths(cfg.out)[0]
    if cfg.resume:
        if not Path(cfg.resume).is_file():
            usage_error(prog, f"--resume {cfg.resume}: no such checkpoint")
    elif last.exists() and not cfg.force:
        usage_error(
            prog,
            f"{last} exists (an unfinished run of this --out): continue it with --resume "
            f"{last}, or pass --force to start over",
        )
    check_outputs(prog, outputs(cfg), force=cfg.force)
    with output_lock(cfg.out, prog):  # one run per --out
        return _run(cfg)


def state_files(out: str | Path) -> list[Path]:
    """The resume state of ``--out``, removed when the run completes.

    ``<stem>.last.zip`` / ``.json`` / ``.labels.npz`` / ``.fit.pt``.
    """
    last = last_paths(out)
    return [*last, last[0].with_suffix(".labels.npz"), fit_state_path(last[0])]


#: options that may differ between an interrupted run and its --resume
_FREE = (*FREE_OPTIONS, "verify_top_k", "baselines")


def _run(cfg: Config) -> dict[str, Any]:
    """The round itself (``main`` after the output checks, holding the lock)."""
    out = Path(cfg.out)
    if out.suffix != ".zip":
        raise UsageError(f"--out must end in .zip, got {cfg.out!r}")
    if cfg.scorer not in ("checkpoint", *SCORERS):
        raise UsageError(f"--scorer must be one of {['checkpoint', *SCORERS]}, got {cfg.scorer!r}")
    if cfg.edit_rank < 1:
        raise UsageError(f"--edit-rank must be >= 1, got {cfg.edit_rank}")
    kwargs, resumed, meta = read_run_inputs(cfg, ENV_ID, "dagger", _FREE, load=load_metadata)
    flag = RunStop(cfg.max_minutes)  # signals and the budget, checked at the safe points
    started = time.perf_counter()
    last = last_paths(out)[0]
    labels_file = state_files(out)[2]
    data = None
    if resumed is None:
        try:
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
        except (KeyboardInterrupt, Terminated) as exc:
            name = "SIGINT" if isinstance(exc, KeyboardInterrupt) else "SIGTERM"
            raise stop_exception(
                name, "while collecting the labels: nothing complete to keep; run it again"
            ) from None
    # weights read safely (never SB3's load(), which unpickles the zip), onto a fresh model
    env = gym.make(ENV_ID, **{**kwargs, "action_mode": "edit"})
    env = CandidateViewWrapper(env, view_for(ENV_ID, env, meta.get("view")))
    if cfg.scorer == "checkpoint":
        loader = edit_model_from_checkpoint if is_edit_architecture(meta) else model_from_checkpoint
        model = loader(cfg.checkpoint, meta, env)
    else:
        model, architecture = fresh_model(meta, env, cfg.scorer, cfg.edit_rank, cfg.seed)
        meta = {**meta, "architecture": architecture}
    meta = {**meta, "dagger": asdict(cfg), "metrics": None}
    meta.pop("checkpoint_sha256", None)  # the source's: replaced by the new zip's
    run = Progress(fit=FitState(0, {}))
    if resumed is not None:
        space = cast(spaces.Dict, env.observation_space)
        rows = {k: tuple(sp.shape or ()) for k, sp in space.spaces.items()}
        run = _restore(cfg, resumed, model, rows, labels_file)
    run.start = started  # the wall time counts the collection

    def save(interrupted: str | None, fit: FitState | None) -> None:
        save_state(model, meta, run, last, interrupted, fit)

    def stop(name: str) -> BaseException:
        return stop_exception(
            name,
            f"saved the labels and the fit after {run.epochs_done} of {cfg.epochs} epochs as "
            f"{last} (+ .json); continue with the same command and --resume {last}",
        )

    if data is not None:  # labels collected: a resume fits them
        stopped = collected(data, labels_file, 0, run, flag, save)
        if stopped is not None:
            raise stop(stopped)
    with flag:
        fit = fit_round(
            cfg, model, run.parts[0], run, seed=cfg.seed, flag=flag, save=save, stop=stop
        )
    meta["dagger"] = {**asdict(cfg), **fit, "wall_seconds": run.wall()}
    meta["complete"] = True
    json_path = out.with_suffix(".json")
    save_final(model, meta, out, state_files(out), flag)  # zip + JSON as an atomic pair
    if cfg.eval_episodes:
        eval_kwargs = meta.get("eval_env_kwargs", kwargs)
        ks = [int(k) for k in cfg.verify_top_k.split(",") if k.strip()]
        with evaluation_stops(out):
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


def _restore(
    cfg: Config,
    meta: dict[str, Any],
    model: Any,
    rows: dict[str, tuple[int, ...]],
    labels_file: Path,
) -> Progress:
    """Labels, weights, fit state and generators of ``cfg.resume`` (``UsageError`` if bad)."""
    path = Path(cfg.resume)
    state = meta["resume_state"]
    labels = state.get("labels")
    if not isinstance(labels, list) or len(labels) != 1 or not isinstance(labels[0], dict):
        raise UsageError(f"--resume {path}: malformed resume state (no labels recorded)")
    try:
        data = load_labels(
            labels_file,
            sha256=str(labels[0].get("sha256")),
            rows=cfg.states,
            row_shapes=rows,
            n_actions=rows["action_mask"][0],
        )
        fit = read_fit_state(path, state.get("fit"))
        model.policy.load_state_dict(read_weights(path), strict=True)
        set_rng_state(state["rng"])
    except (ValueError, RuntimeError, KeyError, TypeError) as exc:
        raise UsageError(f"--resume {path}: {exc}") from None
    wall = state.get("wall_seconds")
    return Progress(
        labels=labels,
        parts=[data],
        fit=fit,
        epochs_done=fit.epochs_done if fit is not None else 0,
        wall_before=float(wall) if isinstance(wall, int | float) else 0.0,
    )


#: the console script: ``main`` with the exit codes of :func:`selenv.learned.trainer.run_cli`
#: (0; 2 usage error or busy ``--out``; 1 I/O failure; 130 / 143 / 75 stopped and saved)
cli = RUN.command(main)


if __name__ == "__main__":
    cli()
