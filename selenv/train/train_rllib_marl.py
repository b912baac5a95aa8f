"""Train one shared candidate-scoring RLModule with RLlib's multi-agent PPO (PettingZoo envs).

RLlib new API stack: ``PPOConfig`` with the env adapter
:class:`selenv.learned.rl.rllib_env.SelenvMultiAgentEnv` (only the agents on turn observe and act,
shared team reward, per-agent candidate views), every agent mapped to the one module id
``"shared"`` (parameter sharing) whose class is
:class:`selenv.learned.rl.rllib_module.CandidateScoringRLModule` (permutation-equivariant logits
masked by ``action_mask``, value from the pooled embedding). Ray is started (or joined with
``--address``) by :func:`selenv.parallel.ray_session` and stopped at the end if started here.

Outputs, next to ``--out`` (default ``runs/rllib_<env>/policy``; refused if they exist,
unless ``--force``, before Ray starts):

* ``<out>.pth`` + ``<out>.json``: the trained module, exported without pickle
  (:func:`selenv.learned.rl.rllib_agent.export_module`), playable by ``selenv bench`` as
  ``rllib:path=<out>.json``; RLlib's own (pickled) checkpoints are not written;
* ``<out>.metrics.json``: one record per iteration (RLlib's sampled returns, summed over
  agents, the learner's losses, steps, wall time), plus TensorBoard scalars with
  ``--tensorboard-dir``.

The outputs are written atomically (:mod:`selenv.atomic`): the ``.pth`` and ``.json`` as one
pair, so a failed or killed write leaves the previous files byte-identical. A second run on
the same ``--out`` is refused while this one holds its lock (exit 2, one line).
``--hidden`` / ``--vf`` widths beyond the loaders' ceilings
(:data:`selenv.learned.resources.CHECKPOINT_LIMITS`) are refused up front (exit 2).

Long runs lose at most one iteration (resumable training, without pickle). The run
management is the trainer base's (:mod:`selenv.learned.trainer`: the shared run options, the
output lock, :class:`~selenv.learned.trainer.RunStop`, the stop lines and exit codes); this
script brings RLlib's update step (``Algorithm.train()``, one iteration) and its checkpoint
(:mod:`selenv.learned.rl.rllib_checkpoint`):

* ``--checkpoint-every N`` writes, after every ``N``-th iteration, the checkpoint
  ``<out>.last.json`` + ``.last.pth`` (an export of the module, playable as
  ``rllib:path=<out>.last.json``, marked ``"complete": false``) with ``.last.optimizer.pth``
  (the learner's Adam state: tensors and plain values, read back with
  ``torch.load(weights_only=True)``) and ``.last.metrics.json`` (the metrics so far); the
  four files are written as one atomic group, their sizes and sha256 recorded in the JSON,
  and removed once the final export is written. The JSON's ``resume_state`` holds the
  iteration count, RLlib's lifetime counters and this process's random generators.
* The safe point is the end of an iteration. SIGINT / SIGTERM during an iteration let it
  finish (a second signal abandons it at once); ``--max-minutes M`` stops at the end of the
  first iteration that ends ``M`` minutes or more after the run started (Ray's start-up
  included; at least one iteration runs). Either way the last completed iteration is kept as
  that checkpoint (``"interrupted"``: ``"SIGINT"``, ``"SIGTERM"`` or ``"max-minutes"``), the
  evaluation is skipped, and the run exits 130 / 143 / 75 with one line naming the checkpoint
  and the ``--resume`` option to continue with. A stop after the last iteration writes the
  complete export and skips only the evaluation. (``ray.init`` replaces the SIGTERM handler
  with an immediate exit; the run's own handlers are installed once Ray has started.)
* ``--resume <out>.last.json`` (with the options of the stopped run: another training
  option is refused, exit 2, naming it) builds a fresh Algorithm, restores the module
  weights, the optimizer state (``Algorithm.set_state``, then synced to the env runners), the
  iteration count, the lifetime counters and the generators, and trains up to
  ``--iterations``; its metrics continue the checkpoint's (iterations 1..n). RLlib is
  reseeded with ``--seed`` + the iterations done, so the resumed env runners do not replay
  the first episodes: deterministic given the checkpoint, not bit-identical to an
  uninterrupted run (env runners sample asynchronously). A checkpoint left next to ``--out``
  makes a run without ``--resume`` or ``--force`` exit 2. RLlib's own (pickled) checkpoints
  are never written nor read.

After training, ``--eval-episodes`` held-out episodes (seeds ``--eval-seed ...``) are played by
``greedy`` and the exported module through ``selenv bench``'s runner (team return, paired
difference with its 95 % CI); the summary goes into the JSON.

    python -m selenv.train.train_rllib_marl --env fim_selection_v0 --iterations 40
    python -m selenv.train.train_rllib_marl --config configs/rllib_fim_selection_v0.toml \
        --out checkpoints/rllib_fim_selection_v0 --force     # the shipped module's run
    selenv bench selenv.multiagent.fim_selection_v0 --agents greedy,random,rllib:path=P

with ``P = runs/rllib_fim_selection_v0/policy.json``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import torch as th
from tqdm.auto import tqdm

from selenv.atomic import write_json
from selenv.exits import Terminated, UsageError
from selenv.learned.config import arg, check_outputs, usage_error
from selenv.learned.resources import bounded_widths, read_metadata
from selenv.learned.rl import rllib_checkpoint as checkpoint
from selenv.learned.rl.candidate_policy import obs_layout
from selenv.learned.rl.rllib_checkpoint import (
    METRICS_FILE,
    OPTIMIZER_FILE,
    Resumed,
    Snapshot,
    read_optimizer_state,
)
from selenv.learned.rl.rllib_checkpoint import restore as _restore
from selenv.learned.rl.rllib_env import SelenvMultiAgentEnv, resolve_env
from selenv.learned.trainer import (
    RESUME_FREE,
    RunStop,
    Script,
    check_run_options,
    evaluation_stops,
    output_lock,
    run_arg,
    run_cli,
    stop_exception,
)
from selenv.untrusted import json_object

__all__ = [
    "Config",
    "UsageError",
    "build_config",
    "last_paths",
    "main",
    "outputs",
    "parse_args",
    "read_optimizer_state",
]

ENVS = ("fim_selection_v0", "receiver_clustering_v1")
#: --gain-skip-init when not given: 0 (near uniform) as the shipped fim_marl run; 1 for
#: clustering, whose view gives the "stay" label the only positive gain (p(stay) ~ 0.999)
GAIN_SKIP_DEFAULTS = {"fim_selection_v0": 0.0, "receiver_clustering_v1": 1.0}
SCRIPT = "selenv.train.train_rllib_marl"


@dataclass
class Config:
    """Every option of the command line (``--kebab-case``); see ``--help`` for each."""

    env: str = arg("fim_selection_v0", "PettingZoo module of selenv.multiagent to train on",
                   choices=ENVS)  # fmt: skip
    iterations: int = arg(
        200,
        "PPO iterations (each samples --train-batch-size env steps, then learns); the shipped "
        "fim_selection_v0 module: 200 iterations of 1,024 steps (204,800 env steps)",
    )
    max_minutes: float | None = run_arg("max_minutes", None, unit="the end of an iteration")
    seed: int = arg(0, "seed of RLlib (env runners' env resets, torch initialisation, minibatches)")
    env_kwargs: str = arg(
        "{}", "JSON object of the env constructor's keywords ({}: the env's defaults)"
    )
    num_env_runners: int = arg(
        0,
        "remote RLlib env runners (Ray actors) sampling in parallel; 0 samples in this process "
        "(the shipped fim_selection_v0 module: 2, on 2 cores twice the steps per second of 0)",
    )
    num_envs_per_env_runner: int = arg(1, "envs stepped together by each env runner")
    address: str | None = arg(
        None,
        "join the running Ray cluster at HOST:PORT (or 'auto'); None: start a local "
        "Ray instance and stop it at the end",
    )
    num_cpus: int | None = arg(None, "CPUs of the local Ray instance (None: all of this machine's)")
    out: str | None = arg(
        None,
        "output stem: writes OUT.pth, OUT.json, OUT.metrics.json (None: runs/rllib_<env>/policy)",
    )
    force: bool = run_arg("force", False)
    train_batch_size: int = arg(
        1024, "env steps sampled per iteration (RLlib train_batch_size_per_learner)"
    )
    minibatch_size: int = arg(512, "minibatch size of the PPO epochs (agent steps)")
    num_epochs: int = arg(4, "passes over each iteration's batch")
    lr: float = arg(1e-3, "Adam learning rate")
    gamma: float = arg(1.0, "discount (1: the undiscounted team return is the objective)")
    lambda_: float = arg(0.95, "GAE lambda")
    clip_param: float = arg(0.2, "PPO clip range")
    entropy_coeff: float = arg(1e-3, "entropy bonus coefficient")
    vf_loss_coeff: float = arg(0.5, "value loss coefficient")
    vf_clip_param: float = arg(
        1e6,
        "clip of the squared value error (RLlib's default 10 stops value learning when "
        "returns are ~36 nats; large = no clip)",
    )
    grad_clip: float = arg(0.5, "max global gradient norm (0: none)")
    advantage_norm: str = arg(
        "masked",
        "masked: standardise each minibatch's advantages over the steps in the loss, as SB3 "
        "(selenv.learned.rl.rllib_learner); rllib: RLlib's batch-wide standardisation, which "
        "also counts the artificial bootstrap step of every agent's episode",
        choices=("masked", "rllib"),
    )
    hidden: str = arg("64,64", "comma-separated widths of the shared per-candidate MLP")
    vf: str = arg("64", "comma-separated widths of the value MLP on the pooled embedding")
    activation: str = arg("tanh", "activation of both MLPs", choices=("tanh", "relu"))
    gain_skip_init: float | None = arg(
        None,
        "initial weight w of the relative-gain skip w r_k in every logit (None: per env "
        f"{GAIN_SKIP_DEFAULTS}; 1 starts receiver clustering near 'stay')",
    )
    eval_episodes: int = run_arg(
        "eval_episodes", 30, note="played by greedy and the exported module after training"
    )
    eval_seed: int = run_arg("eval_seed", 10_000)
    tensorboard_dir: str = arg(
        "", "also write TensorBoard scalars there (empty: only OUT.metrics.json)"
    )
    progress: bool = run_arg("progress", True, note="one over the iterations")
    torch_threads: int = arg(1, "torch CPU threads of this process")
    checkpoint_every: int = run_arg(
        "checkpoint_every", 10, note="the checkpoint is OUT.last.json (+ .last.pth, "
        ".last.optimizer.pth, .last.metrics.json)",
    )  # fmt: skip
    allow_large: bool = arg(
        False,
        "lift the ceilings of --iterations (100,000), --num-envs-per-env-runner (1,024), "
        "--train-batch-size and --minibatch-size (1,048,576), --num-epochs (1,000) and "
        "--eval-episodes (100,000)",
    )
    resume: str = run_arg(
        "resume", "", unit="checkpoint OUT.last.json", note="module weights, optimizer state, "
        "iteration count, metrics and random generators",
    )  # fmt: skip


#: options that may differ between an interrupted run and its resumption: the trainer base's
#: run options, how long and where it runs; every other option must be the checkpoint's
RUN_OPTIONS = frozenset({
    *RESUME_FREE, "iterations", "address", "num_cpus", "num_env_runners", "tensorboard_dir",
    "torch_threads",
    "env_kwargs",  # env_kwargs: compared parsed, not as text
})  # fmt: skip
RUN = Script(SCRIPT, Config, __doc__)
PROG = RUN.prog
#: ceilings of the sizes that multiply work or memory (``--allow-large`` lifts them)
CEILINGS = {
    "iterations": 100_000, "num_envs_per_env_runner": 1_024, "train_batch_size": 1 << 20,
    "minibatch_size": 1 << 20, "num_epochs": 1_000, "eval_episodes": 100_000,
}  # fmt: skip


def _fail(message: object) -> NoReturn:
    usage_error(PROG, message)


def _widths(text: str, option: str) -> list[int]:
    try:
        widths = [int(w) for w in text.split(",") if w.strip()]
    except ValueError:
        raise UsageError(f"{option} must be comma-separated positive ints, got {text!r}") from None
    if (option == "--hidden" and not widths) or any(w < 1 for w in widths):
        raise UsageError(f"{option} must be comma-separated positive ints, got {text!r}")
    try:  # the loaders refuse larger exports: refuse them before training, not after
        return bounded_widths(widths, option, "model_config")
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def parse_args(argv: list[str] | None = None) -> tuple[Config, dict[str, Any]]:
    """The config and the parsed env kwargs; usage errors exit 2 with a one-line reason.

    ``--config FILE`` (TOML) supplies defaults (:func:`selenv.learned.config.parse_config`);
    the shared run options are checked by :func:`selenv.learned.trainer.check_run_options`.
    Existing outputs are checked by :func:`main` (:func:`outputs`), not here.
    """
    cfg = RUN.parse(argv)
    check_run_options(cfg, PROG)
    try:
        env_kwargs = _check(cfg)
    except UsageError as exc:
        _fail(exc)
    return cfg, env_kwargs


def outputs(cfg: Config) -> list[Path]:
    """The files the run writes: ``<out>.json``, ``<out>.pth``, ``<out>.metrics.json``."""
    return list(_outputs(cfg))


def _check(cfg: Config) -> dict[str, Any]:
    """Validate ``cfg`` (module docstring); return the env kwargs. Raises :class:`UsageError`."""
    at_least = {
        "iterations": 1, "seed": 0, "num_env_runners": 0, "num_envs_per_env_runner": 1,
        "train_batch_size": 1, "minibatch_size": 1, "num_epochs": 1, "eval_seed": 0,
        "torch_threads": 1,
    }  # fmt: skip
    for name, low in at_least.items():
        if getattr(cfg, name) < low:
            raise UsageError(f"--{name.replace('_', '-')} must be >= {low}")
    if not cfg.allow_large:
        for name, ceiling in CEILINGS.items():
            if getattr(cfg, name) > ceiling:
                raise UsageError(
                    f"--{name.replace('_', '-')} {getattr(cfg, name):,} is above its ceiling "
                    f"{ceiling:,}; pass --allow-large to run it anyway"
                )
    if cfg.address is None:  # env runners are processes of this machine
        from selenv.parallel.executors import max_pool_workers

        if cfg.num_env_runners > max_pool_workers():
            raise UsageError(
                f"--num-env-runners {cfg.num_env_runners:,} exceeds the "
                f"{max_pool_workers()} processes this machine runs (8 per CPU); use fewer, or "
                "a Ray cluster (--address)"
            )
    if cfg.gain_skip_init is not None and not math.isfinite(cfg.gain_skip_init):
        raise UsageError("--gain-skip-init must be finite")
    if cfg.num_cpus is not None and cfg.num_cpus < 1:
        raise UsageError("--num-cpus must be >= 1")
    if cfg.minibatch_size > cfg.train_batch_size:
        raise UsageError("--minibatch-size must not exceed --train-batch-size")
    positive = ("lr", "clip_param", "vf_clip_param")
    nonneg = ("entropy_coeff", "vf_loss_coeff", "grad_clip")
    for name in (*positive, *nonneg):
        value = getattr(cfg, name)
        if not math.isfinite(value) or value < 0 or (name in positive and value == 0):
            kind = "> 0" if name in positive else ">= 0"
            raise UsageError(f"--{name.replace('_', '-')} must be finite and {kind}")
    if not (0 < cfg.gamma <= 1 and 0 <= cfg.lambda_ <= 1):
        raise UsageError("--gamma must be in (0, 1] and --lambda in [0, 1]")
    _widths(cfg.hidden, "--hidden")
    _widths(cfg.vf, "--vf")
    try:  # size and nesting bounded before parsing
        env_kwargs = json_object(cfg.env_kwargs, "--env-kwargs")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    try:  # the env rejects bad keywords now, not inside an env runner
        SelenvMultiAgentEnv({"env": cfg.env, "env_kwargs": env_kwargs}).close()
    except (TypeError, ValueError) as exc:
        raise UsageError(f"--env-kwargs rejected by {cfg.env}: {exc}") from None
    return env_kwargs


def _outputs(cfg: Config) -> tuple[Path, Path, Path]:
    from selenv.learned.rl.rllib_agent import export_paths

    json_path, pth_path = export_paths(cfg.out or f"runs/rllib_{cfg.env}/policy")
    return json_path, pth_path, json_path.with_suffix(".metrics.json")


def last_paths(cfg: Config) -> list[Path]:
    """The checkpoint of an unfinished run: ``<out>.last.json``, ``.pth``, and its extra files."""
    return checkpoint.checkpoint_paths(_outputs(cfg)[0])


def _shared(agent_id: Any, episode: Any, **kwargs: Any) -> str:
    """Policy mapping: every agent plays the one shared module (parameter sharing)."""
    from selenv.learned.rl.rllib_module import SHARED_MODULE_ID

    return SHARED_MODULE_ID


def build_config(cfg: Config, env_kwargs: dict[str, Any], *, seed: int | None = None) -> Any:
    """The RLlib ``PPOConfig`` of ``cfg`` (new API stack, one shared RLModule).

    ``seed`` replaces ``cfg.seed`` (a resumed run's ``seed + iterations done``).
    """
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    from selenv.learned.rl.rllib_learner import MaskedAdvantagePPOTorchLearner
    from selenv.learned.rl.rllib_module import SHARED_MODULE_ID, CandidateScoringRLModule

    learner: dict[str, Any] = {}
    if cfg.advantage_norm == "masked":
        learner["learner_class"] = MaskedAdvantagePPOTorchLearner
    env_config = {"env": cfg.env, "env_kwargs": env_kwargs}
    probe = SelenvMultiAgentEnv(env_config)
    spec = RLModuleSpec(
        module_class=CandidateScoringRLModule,
        observation_space=probe.agent_observation_space,
        action_space=probe.agent_action_space,
        model_config=_model_config(cfg),
    )
    probe.close()
    return (
        PPOConfig()
        .api_stack(enable_rl_module_and_learner=True, enable_env_runner_and_connector_v2=True)
        .environment(SelenvMultiAgentEnv, env_config=env_config)
        .env_runners(
            num_env_runners=cfg.num_env_runners,
            num_envs_per_env_runner=cfg.num_envs_per_env_runner,
        )
        .learners(num_learners=0)
        .multi_agent(policies={SHARED_MODULE_ID}, policy_mapping_fn=_shared)
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs={SHARED_MODULE_ID: spec}))
        .training(
            train_batch_size_per_learner=cfg.train_batch_size,
            minibatch_size=cfg.minibatch_size,
            num_epochs=cfg.num_epochs,
            lr=cfg.lr,
            gamma=cfg.gamma,
            lambda_=cfg.lambda_,
            clip_param=cfg.clip_param,
            vf_clip_param=cfg.vf_clip_param,
            entropy_coeff=cfg.entropy_coeff,
            vf_loss_coeff=cfg.vf_loss_coeff,
            grad_clip=cfg.grad_clip or None,
            use_kl_loss=False,  # clipped surrogate only, as SB3's PPO
            **learner,
        )
        .debugging(seed=cfg.seed if seed is None else seed, log_level="ERROR")
    )


def _model_config(cfg: Config) -> dict[str, Any]:
    return {
        "hidden": _widths(cfg.hidden, "--hidden"),
        "vf": _widths(cfg.vf, "--vf"),
        "activation": cfg.activation,
        "gain_skip_init": (
            GAIN_SKIP_DEFAULTS[cfg.env] if cfg.gain_skip_init is None else cfg.gain_skip_init
        ),
    }


def _get(result: dict[str, Any], *path: str) -> float | None:
    node: Any = result
    for key in path:
        if not isinstance(node, dict) or key not in node:
            return None
        node = node[key]
    try:
        return float(node)
    except (TypeError, ValueError):
        return None


def _record(it: int, result: dict[str, Any], seconds: float) -> dict[str, Any]:
    """One metrics record of an iteration's result (``None`` where RLlib reported nothing)."""
    from selenv.learned.rl.rllib_module import SHARED_MODULE_ID

    learner = ("learners", SHARED_MODULE_ID)
    return {
        "iteration": it,
        "wall_seconds": round(seconds, 3),
        "sample_seconds": _get(result, "timers", "env_runner_sampling_timer"),
        "learn_seconds": _get(result, "timers", "learner_update_timer"),
        "env_steps_lifetime": _get(result, "env_runners", "num_env_steps_sampled_lifetime"),
        "module_steps_lifetime": _get(
            result, "env_runners", "num_module_steps_sampled_lifetime", SHARED_MODULE_ID
        ),
        "episodes": _get(result, "env_runners", "num_episodes"),
        "episode_return_mean_sum_over_agents": _get(result, "env_runners", "episode_return_mean"),
        "agent_episode_returns_mean": {
            str(a): float(v)
            for a, v in result.get("env_runners", {}).get("agent_episode_returns_mean", {}).items()
        },
        "episode_len_mean": _get(result, "env_runners", "episode_len_mean"),
        "policy_loss": _get(result, *learner, "policy_loss"),
        "vf_loss": _get(result, *learner, "vf_loss"),
        "vf_explained_var": _get(result, *learner, "vf_explained_var"),
        "entropy": _get(result, *learner, "entropy"),
    }


def _evaluate(cfg: Config, env_kwargs: dict[str, Any], json_path: Path) -> dict[str, Any]:
    """Greedy and the exported module on the held-out seeds, through the bench's runner."""
    from selenv.bench import run_bench

    env_id = resolve_env(cfg.env)
    spec = f"rllib:path={json_path}"
    res = run_bench(
        env_id, ["greedy", spec], episodes=cfg.eval_episodes, seed=cfg.eval_seed,
        env_kwargs=env_kwargs, progress=False, baseline="greedy",
    )  # fmt: skip
    doc = res.to_json()
    out = {}
    for name, agent in doc["agents"].items():
        keep = ("mean_return", "std_return", "mean_final_objective", "paired", "skipped")
        out["rllib" if name == spec else name] = {k: agent[k] for k in keep if k in agent}
    return {
        "seeds": [cfg.eval_seed, cfg.eval_seed + cfg.eval_episodes - 1],
        "episodes": cfg.eval_episodes,
        "env_kwargs": env_kwargs,
        "baseline": "greedy",
        "agents": out,
    }


# -- resumable training ------------------------------------------------------------------------
def _metadata(
    cfg: Config,
    env_kwargs: dict[str, Any],
    records: list[dict[str, Any]],
    wall: float,
    metrics_file: str,
    stopped: str | None,
    *,
    complete: bool,
) -> dict[str, Any]:
    """The export's JSON content (before :func:`export_module` adds the module's facts)."""
    import ray

    from selenv import __version__ as selenv_version

    skip = ("force", "progress", "resume")
    return {
        "env_id": resolve_env(cfg.env),
        "env_kwargs": env_kwargs,
        "training": {
            **{k: v for k, v in dataclasses.asdict(cfg).items() if k not in skip},
            "algorithm": "RLlib PPO (new API stack), one shared RLModule",
            "iterations_done": len(records),
            "env_steps": records[-1]["env_steps_lifetime"] if records else 0,
            "agent_steps": records[-1]["module_steps_lifetime"] if records else 0,
            "wall_seconds": round(wall, 1),
            "metrics_file": metrics_file,
            "complete": complete,
            **({"interrupted": stopped} if stopped else {}),
        },
        "iterations": len(records),
        "ray_version": ray.__version__,
        "torch_version": th.__version__,
        "selenv_version": selenv_version,
    }


def _module_of(cfg: Config, env_kwargs: dict[str, Any], weights: dict[str, Any]) -> Any:
    """A fresh :class:`CandidateScoringRLModule` of ``cfg`` holding ``weights`` (strict)."""
    from selenv.learned.rl.rllib_module import build_module

    probe = SelenvMultiAgentEnv({"env": cfg.env, "env_kwargs": env_kwargs})
    layout = obs_layout(probe.agent_observation_space)
    probe.close()
    module = build_module(layout["n"], layout["whitened_dim"], _model_config(cfg))
    module.load_state_dict({k: th.as_tensor(v) for k, v in weights.items()}, strict=True)
    return module


def _save_last(
    cfg: Config,
    env_kwargs: dict[str, Any],
    snap: Snapshot,
    records: list[dict[str, Any]],
    wall: float,
    stopped: str | None,
) -> Path:
    """Write the checkpoint of ``snap`` (:func:`last_paths`, one atomic group); its JSON."""
    last = last_paths(cfg)
    kept = records[: snap.iteration]
    meta = _metadata(cfg, env_kwargs, kept, wall, last[3].name, stopped, complete=False)
    module = _module_of(cfg, env_kwargs, snap.weights)
    return checkpoint.save(last, module, meta, snap, kept, wall)


def _read_resume(cfg: Config, env_kwargs: dict[str, Any]) -> Resumed:
    """The checkpoint ``cfg.resume``, checked against this run (``UsageError`` otherwise)."""
    from selenv.learned.rl.rllib_agent import export_paths, load_exported

    json_path, _ = export_paths(cfg.resume)
    if not json_path.is_file():
        raise UsageError(f"--resume {cfg.resume}: no such checkpoint ({json_path} not found)")
    where = f"--resume {json_path}"
    try:
        module, meta = load_exported(json_path)  # the module's files, checked and loaded
    except ValueError as exc:
        raise UsageError(f"{where}: {exc}") from None
    state = meta.get("resume_state")
    training = meta.get("training")
    done = state.get("iterations_done") if isinstance(state, dict) else None
    if not isinstance(training, dict) or not isinstance(done, int) or done < 1:
        raise UsageError(f"{where}: no resume state in it (a checkpoint {json_path.name} written "
                         "by --checkpoint-every or a stopped run is needed)")  # fmt: skip
    theirs = {"env": meta.get("env_id"), "env_kwargs": meta.get("env_kwargs")}
    ours = {"env": resolve_env(cfg.env), "env_kwargs": env_kwargs}
    for name, value in dataclasses.asdict(cfg).items():
        if name not in RUN_OPTIONS and name != "env":
            theirs[name], ours[name] = training.get(name, "(not recorded)"), value
    for name, value in ours.items():
        if theirs[name] != value:
            option = "--" + name.rstrip("_").replace("_", "-")
            raise UsageError(
                f"{where}: it was trained with {option} {theirs[name]!r:.200}, this run has "
                f"{value!r:.200}; resume with the options of the interrupted run"
            )
    if done > cfg.iterations:
        raise UsageError(f"{where}: it already ran {done} iterations, more than --iterations "
                         f"{cfg.iterations}")  # fmt: skip
    try:
        return checkpoint.read(json_path, module, meta, done, where)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Train, export, evaluate; return the exported metadata (the JSON's content).

    The outputs are locked for the run (a second run on the same ``--out``: exit 2, one
    line). A stop (SIGINT / SIGTERM, the latter while :func:`selenv.exits.sigterm_raises` is
    active as under :func:`cli`, or ``--max-minutes``) keeps the last completed iteration as
    the checkpoint :func:`last_paths` (``"complete": false``, ``"interrupted"``) with the
    metrics so far, skips the evaluation and raises the trainer base's
    :func:`~selenv.learned.trainer.stop_exception` (exit 130 / 143 / 75 with one line through
    :func:`cli`, naming the ``--resume`` option that continues the run).
    """
    cfg, env_kwargs = parse_args(argv)
    folders = [cfg.tensorboard_dir] if cfg.tensorboard_dir else []
    last = last_paths(cfg)[0]
    if last.exists() and not cfg.resume and not cfg.force:
        _fail(f"{last} exists (an unfinished run of this --out): continue it with --resume "
              f"{last}, or pass --force to start over")  # fmt: skip
    check_outputs(PROG, outputs(cfg), force=cfg.force, folders=folders)
    resumed = None
    if cfg.resume:
        try:
            resumed = _read_resume(cfg, env_kwargs)
        except UsageError as exc:
            _fail(exc)
    flag = RunStop(cfg.max_minutes)  # the budget counts from here, Ray's start-up included
    with output_lock(_outputs(cfg)[0], PROG):
        return _train(cfg, env_kwargs, resumed, flag)


def _train(
    cfg: Config, env_kwargs: dict[str, Any], resumed: Resumed | None, flag: RunStop
) -> dict[str, Any]:
    """:func:`main` after the checks, under the output lock: iterations until done or stopped."""
    from selenv.learned.rl.rllib_agent import export_module
    from selenv.parallel import ExecutorError, ray_session

    th.set_num_threads(cfg.torch_threads)
    json_path, _, metrics_path = _outputs(cfg)
    records: list[dict[str, Any]] = list(resumed.records) if resumed else []
    done = resumed.snapshot.iteration if resumed else 0
    wall_before = resumed.wall_seconds if resumed else 0.0
    snap = resumed.snapshot if resumed else None  # the last completed iteration
    writer = None
    if cfg.tensorboard_dir:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(cfg.tensorboard_dir)
    start = time.perf_counter()
    abandoned: str | None = None  # a second signal abandoned the iteration in progress
    with contextlib.ExitStack() as stack:
        try:
            stack.enter_context(ray_session(cfg.address, cfg.num_cpus))
        except ExecutorError as exc:
            _fail(exc)
        stack.enter_context(flag)  # after ray.init, whose SIGTERM handler exits at once
        algo = build_config(cfg, env_kwargs, seed=cfg.seed + done).build_algo()
        stack.callback(algo.stop)
        if resumed is not None:
            try:
                _restore(algo, resumed)
            except (ValueError, RuntimeError, KeyError) as exc:
                _fail(f"--resume {resumed.path}: cannot restore its state: {exc}")
        bar = tqdm(range(done + 1, cfg.iterations + 1), desc=f"rllib {cfg.env}", unit="it",
                   initial=done, total=cfg.iterations, disable=not cfg.progress)  # fmt: skip
        stack.callback(bar.close)
        try:
            for it in bar:
                if flag.signal is not None:  # received during the start-up
                    break
                t0 = time.perf_counter()
                result = algo.train()  # the update step: sample, then learn
                record = _record(it, result, time.perf_counter() - t0)
                new = checkpoint.snapshot(algo, it)
                records.append(record)  # abandoned in between: records[: snap.iteration] kept
                snap = new
                _log(bar, writer, record)
                if it < cfg.iterations and flag.check_budget():  # the safe point
                    break
                if cfg.checkpoint_every and it % cfg.checkpoint_every == 0 and it < cfg.iterations:
                    wall = wall_before + time.perf_counter() - start
                    _save_last(cfg, env_kwargs, snap, records, wall, None)
        except KeyboardInterrupt:
            abandoned = "SIGINT"
        except Terminated:
            abandoned = "SIGTERM"
    wall = wall_before + time.perf_counter() - start
    if writer is not None:
        writer.close()
    stopped = abandoned or flag.signal
    if stopped is not None and (snap is None or snap.iteration < cfg.iterations):
        if snap is None:
            raise stop_exception(stopped, "no iteration had completed: nothing was written")
        with flag:
            last = _save_last(cfg, env_kwargs, snap, records[: snap.iteration], wall, stopped)
        raise stop_exception(
            stopped,
            f"saved iteration {snap.iteration} of {cfg.iterations} as {last} (+ .pth, "
            f".{OPTIMIZER_FILE}, .{METRICS_FILE}), marked incomplete; continue with the same "
            f"command and --resume {last}",
        )
    assert snap is not None  # every iteration ran (or the checkpoint had run them)
    records = records[: snap.iteration]
    module = _module_of(cfg, env_kwargs, snap.weights)
    metadata = _metadata(cfg, env_kwargs, records, wall, metrics_path.name, None, complete=True)
    with flag:  # the export, its metrics and the removal of the checkpoint, signals held
        json_path, _ = export_module(module, json_path, metadata)
        write_json(metrics_path, records, indent=1)
        checkpoint.remove(last_paths(cfg))  # superseded by the complete export
    if stopped is not None:
        raise stop_exception(
            stopped,
            f"training had completed: saved {json_path} (+ .pth, .metrics.json); its "
            "evaluation was skipped",
        )
    metadata = read_metadata(json_path, "RLlib export metadata")
    if cfg.eval_episodes:
        with evaluation_stops(json_path):
            metadata["eval"] = _evaluate(cfg, env_kwargs, json_path)
        write_json(json_path, metadata)  # the weights are unchanged: the pair still matches
    print(f"wrote {json_path} (+ .pth, .metrics.json) in {wall:.0f} s", file=sys.stderr)
    return metadata


def _log(bar: Any, writer: Any, record: dict[str, Any]) -> None:
    """An iteration's record on the tqdm bar and, if any, the TensorBoard writer."""
    ret = record["episode_return_mean_sum_over_agents"]
    if ret is not None and np.isfinite(ret):
        bar.set_postfix_str(f"return(sum over agents)={ret:.3f}")
    if writer is not None:
        for key, value in record.items():
            if isinstance(value, int | float) and key != "iteration":
                writer.add_scalar(f"rllib/{key}", value, record["iteration"])


def cli(argv: list[str] | None = None) -> int:
    """Command-line entry point: :func:`main` with the exit codes of the trainer base.

    Returns 0 after a run; 1 with one line for an I/O failure (the previous outputs are left
    as they were); 130 / 143 / 75 with one line naming what was kept after SIGINT / SIGTERM /
    ``--max-minutes`` (:func:`selenv.learned.trainer.run_cli`). A usage error or a busy
    output exits 2 with one line (``SystemExit``, as argparse does).
    """
    return run_cli(main, PROG, argv)


if __name__ == "__main__":
    sys.exit(cli())
