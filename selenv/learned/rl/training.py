"""The MaskablePPO / PPO training loop shared by the ``train/*_ppo.py`` scripts.

A script defines a :class:`PPOConfig` subclass with its env's defaults and calls
:func:`train`, which reads top to bottom:

1. envs: the family's native batched vector env (``vec_env="native"``, the default:
   ``gymnasium.make_vec`` through :class:`~selenv.learned.rl.vec_env.NativeVecEnv`, the
   candidate view applied per sub-env), or ``n_envs`` copies of ``make_env()`` (the env
   wrapped in its candidate view, :mod:`selenv.learned.rl.views`) in one process
   (``"dummy"``) or in worker processes (``"subproc"``,
   :class:`~stable_baselines3.common.vec_env.SubprocVecEnv`);
2. model: :func:`~selenv.learned.rl.candidate_policy.make_ppo` (candidate-scoring policy) with
   ``algo="maskable_ppo"`` (default: masks from the env's ``action_masks()``) or ``"ppo"``;
3. training with a tqdm bar and TensorBoard logs (``runs/``); with ``--curve-every N`` a
   learning curve: the current policy evaluated on ``--curve-episodes`` held-out seeds at step
   0, every ``N`` steps and at the end, the baselines once
   (:mod:`selenv.learned.rl.curves`, ``learning_curve`` in the JSON; the trained weights are
   the same as without it);
4. checkpoint ``<out>.zip`` + metadata ``<out>.json`` (env id and kwargs, candidate view,
   layout, architecture, hyper-parameters, versions, the zip's ``checkpoint_sha256``), written
   as a pair by :func:`save_checkpoint` (temporary files, then both renamed: an interrupted or
   failed write leaves the previous pair byte-identical); an existing file is refused without
   ``--force`` (:func:`check_run_outputs`, which the scripts call before any work);
5. evaluation of the saved checkpoint, reloaded through the ``ppo`` agent adapter, against
   the env's heuristics on the same held-out seeds (``eval_seed``, ``eval_seed + 1``, ...);
   the metrics are written into the JSON.

Long runs lose at most one interval:

* ``--checkpoint-every N`` writes ``<out stem>.last.zip`` + ``.last.json`` (``"complete":
  false``, ``num_timesteps``, the training log, the random generators' states) at the first
  iteration boundary after every ``N`` environment steps; the pair is removed once the final
  checkpoint is written.
* SIGINT / SIGTERM during PPO stop at the end of the current rollout or update: the last
  completed iteration is saved as the ``.last`` pair (``"interrupted": "SIGINT"``) and
  :class:`TrainingInterrupted` / :class:`TrainingTerminated` (exit 130 / 143 through
  :func:`run_cli`) carry the one line naming the file and the ``--resume`` option.
  ``--max-minutes M`` stops the same way at the first iteration boundary after ``M``
  minutes (``"interrupted": "max-minutes"``, :class:`TrainingBudgetReached`, exit 75).
* The run management (output lock, checkpoint pairs, random generators, the stop
  exceptions, :func:`run_cli`, :func:`evaluate`) is the trainer base's
  (:mod:`selenv.learned.trainer`); this module adds PPO's update step around SB3.
* ``--resume PATH`` rebuilds the model from the options, loads the weights and the Adam state
  from ``PATH`` (tensors only, never SB3's unpickling ``load``), restores the step count, the
  update count, the training log and the ``random`` / ``numpy`` / ``torch`` generators, and
  trains up to the same ``--total-timesteps``. SB3 does not save the envs' state: the resumed
  run resets them with seeds ``seed + num_timesteps + b`` (deterministic given the checkpoint,
  not bit-identical to an uninterrupted run).
* Sizes are bounded before anything is built (:data:`LIMITS`, ``--allow-large``) and the
  memory of the rollout buffer and the minibatch is estimated before the model is built
  (``--max-memory-gb``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import sb3_contrib
import stable_baselines3
import torch
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv, VecNormalize
from tqdm.auto import tqdm

import selenv
from selenv.agents import Agent
from selenv.atomic import write_json
from selenv.envs.resolved import resolved_env_config
from selenv.exits import UsageError
from selenv.learned.config import arg, check_outputs, usage_error
from selenv.learned.rl.candidate_policy import ALGORITHMS, CandidateScorer, make_ppo, obs_layout
from selenv.learned.rl.compiled import compile_policy
from selenv.learned.rl.finetune import CriticWarmup, init_from_checkpoint
from selenv.learned.rl.vec_env import make_native_vec_env
from selenv.learned.tensor_load import load_tensors
from selenv.learned.trainer import (
    MAX_OPTIMIZER_BYTES,
    RunStop,
    TrainingBudgetReached,
    TrainingInterrupted,
    TrainingTerminated,
    check_max_minutes,
    evaluate,
    evaluation_stops,
    file_sha256,
    last_paths,
    output_lock,
    read_checkpoint_metadata,
    read_resume_pair,
    run_arg,
    run_cli,
    save_checkpoint,
    verify_pair,
)
from selenv.learned.trainer import rng_state as _rng_state
from selenv.learned.trainer import set_rng_state as _set_rng_state
from selenv.learned.trainer import stop_exception as _stop_exception
from selenv.learned.trainer import zip_member as _zip_member
from selenv.untrusted import json_object

#: the ``--vec-env`` choices
VEC_ENVS = ("native", "dummy", "subproc")

__all__ = [
    "LIMITS",
    "VEC_ENVS",
    "PPOConfig",
    "TqdmCallback",
    "TrainingBudgetReached",
    "TrainingInterrupted",
    "TrainingTerminated",
    "check_bounds",
    "check_run_outputs",
    "estimate_memory_bytes",
    "evaluate",
    "evaluate_checkpoint",
    "file_sha256",
    "last_paths",
    "output_lock",
    "output_paths",
    "ppo_run",
    "read_checkpoint_metadata",
    "run_cli",
    "save_checkpoint",
    "train",
    "verify_pair",
]

#: ceilings of the sizes that multiply work or memory (``--allow-large`` lifts them; the
#: memory estimate, ``--max-memory-gb``, still applies)
LIMITS: dict[str, int] = {
    "total_timesteps": 10**9,
    "n_envs": 1024,
    "n_steps": 65_536,
    "batch_size": 1_048_576,
    "n_epochs": 1000,
    "eval_episodes": 100_000,
    "curve_every": 10**9,
    "curve_episodes": 10_000,
    "hidden_width": 4096,
    "hidden_layers": 16,
}


@dataclass
class PPOConfig:
    """Knobs common to every RL training script; each is a ``--kebab-case`` option."""

    env_kwargs: str = arg("{}", "JSON object of gymnasium.make keyword arguments")
    # training
    algo: str = arg("maskable_ppo", "maskable_ppo (masks from action_masks()) or ppo")
    total_timesteps: int = arg(
        100_000, "PPO environment steps in total (SB3 rounds up to whole rollouts)"
    )
    seed: int = arg(0, "seed of the training envs, the network initialisation and PPO")
    n_envs: int = arg(8, "training envs stepped together (one rollout: n_envs * n_steps)")
    vec_env: str = arg(
        "native",
        "native (the env's batched vector env: one numpy computation steps all n_envs), "
        "dummy (n_envs Python envs in this process) or subproc (one worker process per env)",
    )
    n_steps: int = arg(128, "steps per env per rollout")
    batch_size: int = arg(512, "minibatch size of the PPO epochs")
    n_epochs: int = arg(4, "passes over each rollout")
    learning_rate: float = arg(1e-3, "Adam learning rate (constant)")
    ent_coef: float = arg(1e-3, "entropy bonus coefficient")
    gamma: float = arg(1.0, "discount (1: the episode's total gain is the objective)")
    # policy
    hidden: str = arg("64,64", "comma-separated widths of the shared per-candidate MLP")
    activation: str = arg("tanh", "activation of the per-candidate MLP (tanh or relu)")
    gain_skip_init: float = arg(
        0.0,
        "initial weight w of the gain skip w * gain in every candidate's logit "
        "(0: near-uniform start; > 0: a softened greedy)",
    )
    shortlist: int = arg(
        0,
        "m > 0: the policy scores only the m unselected candidates of largest gain (the others "
        "masked), so rollouts and updates cost about m / N of the whole pool's; 0: every "
        "candidate (the candidate-scoring policies only)",
    )
    # outputs
    out: str = arg("", "checkpoint path (.zip); its metadata goes next to it as .json")
    force: bool = run_arg("force", False)
    tensorboard_dir: str = arg("runs", "TensorBoard log folder (empty: no TensorBoard logs)")
    progress: bool = run_arg("progress", True, note="one over the timesteps")
    torch_threads: int = arg(1, "torch CPU threads of this process")
    compile: bool = arg(
        False,
        "compile the candidate scorer with torch.compile (TorchInductor: fused kernels for the "
        "update; a warm-up of seconds to a minute at the first rollout and minibatch; where it "
        "cannot run, one warning and the eager scorer, which gives the same outputs)",
    )
    # evaluation on held-out seeds
    eval_episodes: int = run_arg("eval_episodes", 20, note="the saved checkpoint, reloaded")
    eval_seed: int = run_arg("eval_seed", 10_000)
    baselines: str = arg(
        "greedy,random", "comma-separated registered agents evaluated next to the policy"
    )
    # learning curve
    curve_every: int = arg(
        0,
        "environment steps between learning-curve points: the current policy evaluated "
        "deterministically on --curve-episodes held-out seeds at the next iteration boundary "
        "(also at step 0 and at the end; recorded as learning_curve in the JSON; 0: no curve)",
    )
    curve_episodes: int = arg(
        20, "held-out episodes per learning-curve point (seeds --eval-seed, +1, ...)"
    )
    # fine-tuning a trained policy
    init_from: str = arg(
        "",
        "start from this checkpoint's weights (same env id, candidate view and architecture, "
        "e.g. a distilled policy to fine-tune with PPO); the optimizer starts afresh",
    )
    critic_warmup: int = arg(
        0,
        "environment steps at the start whose PPO updates train only the value head (the "
        "policy is frozen while the critic of an --init-from policy learns)",
    )
    target_kl: float = arg(
        0.0, "stop a PPO update's epochs once the approximate KL exceeds this (0: off)"
    )
    normalize_reward: bool = arg(
        False,
        "scale the training rewards by a running estimate of the discounted return's standard "
        "deviation (SB3's VecNormalize, rewards only): for envs whose returns are large, where "
        "the value head cannot fit the raw scale; evaluation and the checkpoint are unchanged; "
        "the statistics restart on --resume",
    )
    # long runs
    checkpoint_every: int = run_arg(
        "checkpoint_every",
        50_000,
        unit="environment steps",
        note="<out stem>.last.zip (+ .last.json) is written at the next iteration boundary",
    )
    resume: str = run_arg(
        "resume",
        "",
        unit="<out stem>.last.zip",
        note="weights, optimizer state, step count, training log and random generators",
    )
    max_minutes: float | None = run_arg("max_minutes", None, unit="iteration boundaries")
    max_memory_gb: float = arg(
        8.0, "refuse a run whose estimated rollout-buffer plus minibatch memory exceeds this"
    )
    allow_large: bool = arg(
        False,
        "lift the ceilings of --total-timesteps (1e9), --n-envs (1024), --n-steps (65536), "
        "--batch-size (1048576), --n-epochs (1000), --eval-episodes (100000), --curve-every "
        "(1e9), --curve-episodes (10000) and --hidden (16 layers of <= 4096)",
    )

    def kwargs(self) -> dict[str, Any]:
        """``env_kwargs`` parsed (a JSON object)."""
        try:  # size and nesting bounded before parsing
            return json_object(self.env_kwargs, "--env-kwargs")
        except ValueError as exc:
            raise UsageError(str(exc)) from None


def output_paths(cfg: PPOConfig) -> list[Path]:
    """The files a run writes: the checkpoint ``cfg.out`` and its ``.json`` metadata."""
    out = Path(cfg.out)
    return [out, out.with_suffix(".json")]


def check_bounds(cfg: PPOConfig) -> None:
    """Raise :class:`~selenv.exits.UsageError` naming the option when a size is out of range.

    Lower bounds always apply; the ceilings of :data:`LIMITS` unless ``cfg.allow_large``.
    """

    def limit(option: str, value: int, key: str, low: int = 1) -> None:
        if value < low:
            raise UsageError(f"{option} must be >= {low}, got {value}")
        if not cfg.allow_large and value > LIMITS[key]:
            raise UsageError(
                f"{option} {value} is above its ceiling {LIMITS[key]}: pass --allow-large to "
                "lift the ceilings (the memory estimate, --max-memory-gb, still applies)"
            )

    limit("--total-timesteps", cfg.total_timesteps, "total_timesteps", 0)
    limit("--n-envs", cfg.n_envs, "n_envs")
    limit("--n-steps", cfg.n_steps, "n_steps")
    limit("--batch-size", cfg.batch_size, "batch_size")
    limit("--n-epochs", cfg.n_epochs, "n_epochs")
    limit("--eval-episodes", cfg.eval_episodes, "eval_episodes", 0)
    limit("--curve-every", cfg.curve_every, "curve_every", 0)
    limit("--curve-episodes", cfg.curve_episodes, "curve_episodes")
    limit("--critic-warmup", cfg.critic_warmup, "total_timesteps", 0)
    if not (cfg.target_kl >= 0 and np.isfinite(cfg.target_kl)):
        raise UsageError(f"--target-kl must be a finite number >= 0, got {cfg.target_kl}")
    if cfg.init_from and not Path(cfg.init_from).with_suffix(".zip").is_file():
        raise UsageError(f"--init-from {cfg.init_from}: no such checkpoint")
    hidden = parse_hidden(cfg.hidden)
    limit("--hidden (number of layers)", len(hidden), "hidden_layers")
    for width in hidden:
        limit("--hidden (width)", width, "hidden_width")
    if cfg.checkpoint_every < 0:
        raise UsageError(f"--checkpoint-every must be >= 0, got {cfg.checkpoint_every}")
    check_max_minutes(cfg.max_minutes)
    if not cfg.max_memory_gb > 0:
        raise UsageError(f"--max-memory-gb must be > 0, got {cfg.max_memory_gb}")


@contextlib.contextmanager
def ppo_run(cfg: PPOConfig, prog: str) -> Iterator[None]:
    """Check the run's options and outputs (exit 2, one line), then hold the ``--out`` lock."""
    check_run_outputs(cfg, prog)
    with output_lock(cfg.out, prog):  # one run per --out
        yield


def parse_hidden(text: str) -> list[int]:
    """``"64,64"`` -> ``[64, 64]``; :class:`~selenv.exits.UsageError` naming ``--hidden``."""
    try:
        widths = [int(h) for h in text.split(",")]
    except ValueError:
        raise UsageError(f"--hidden must be comma-separated integers, got {text!r}") from None
    return widths


def estimate_memory_bytes(
    cfg: PPOConfig, obs_floats: int, n_candidates: int, candidate_features: int
) -> int:
    """A coarse upper estimate of the memory PPO allocates for one run's sizes.

    The rollout buffer (``n_envs * n_steps`` float32 observations, masks and scalars, and
    the flattened copy SB3 makes per update), the minibatch activations and gradients of the
    per-candidate network (``batch_size * n_candidates * sum(hidden)``, times 6), and the
    parameters with their gradients and Adam moments.
    """
    hidden = parse_hidden(cfg.hidden)
    samples = cfg.n_envs * cfg.n_steps
    buffer = 2 * samples * (obs_floats + n_candidates + 8) * 4
    activations = 6 * cfg.batch_size * max(n_candidates, 1) * (sum(hidden) + candidate_features)
    widths = [candidate_features, *hidden, 1]
    params = sum(a * b + b for a, b in itertools.pairwise(widths))
    return int(buffer + activations * 4 + 4 * params * 4)


def check_run_outputs(cfg: PPOConfig, prog: str) -> None:
    """Exit 2 (one line, before any work) on outputs that exist or cannot be written.

    An existing ``cfg.out`` or its ``.json`` without ``--force``, an output or TensorBoard
    folder that cannot be written (a real write probe:
    :func:`selenv.learned.config.check_outputs`), an unfinished run's ``.last`` checkpoint
    next to ``--out`` without ``--resume`` or ``--force``, a ``--resume`` file that does not
    exist, or a size out of range (:func:`check_bounds`).
    """
    folders = [cfg.tensorboard_dir] if cfg.tensorboard_dir else []
    try:
        check_bounds(cfg)
    except UsageError as exc:
        usage_error(prog, exc)
    if cfg.resume and not Path(cfg.resume).is_file():
        usage_error(prog, f"--resume {cfg.resume}: no such checkpoint")
    last = last_paths(cfg.out)[0]
    if last.exists() and not cfg.resume and not cfg.force:
        usage_error(
            prog,
            f"{last} exists (an unfinished run of this --out): continue it with --resume "
            f"{last}, or pass --force to start over",
        )
    check_outputs(prog, output_paths(cfg), force=cfg.force, folders=folders)


class _CheckpointCallback(BaseCallback):
    """Iteration boundaries: periodic checkpoints, the training log, stop on a signal.

    At every rollout start (the previous update is complete) the step count, update count and
    generator states are recorded, the wall-clock budget is checked, and a periodic checkpoint
    is written when ``every`` steps passed since the last one; a pending signal or a spent
    budget makes the next step end training.
    """

    def __init__(
        self, every: int, save: Callable[[str | None], None], flag: RunStop, log: list[Any]
    ) -> None:
        super().__init__()
        self.every = every
        self.save_last = save
        self.flag = flag
        self.log = log
        self.boundary: dict[str, Any] | None = None
        self.last_saved = -1

    def _on_rollout_start(self) -> None:
        n = int(self.model.num_timesteps)
        self.boundary = {
            "num_timesteps": n,
            "n_updates": int(getattr(self.model, "_n_updates", 0)),
            "rng": _rng_state(),
        }
        self.flag.check_budget()  # a spent --max-minutes stops here, as a signal does
        if self.last_saved < 0:
            self.last_saved = n  # the start (or the resumed step): nothing new to save
        elif self.every and n - self.last_saved >= self.every and self.flag.signal is None:
            self.save_last(None)
            self.last_saved = n

    def _on_rollout_end(self) -> None:
        buf = self.model.ep_info_buffer
        entry: dict[str, Any] = {"timesteps": int(self.model.num_timesteps)}
        if buf:
            entry["ep_return_mean"] = round(float(np.mean([ep["r"] for ep in buf])), 5)
            entry["ep_length_mean"] = round(float(np.mean([ep["l"] for ep in buf])), 2)
        self.log.append(entry)

    def _on_step(self) -> bool:
        return self.flag.signal is None


class TqdmCallback(BaseCallback):
    """A tqdm bar over the timesteps (SB3's ``progress_bar=True`` needs ``rich``)."""

    def _on_training_start(self) -> None:
        desc = type(self.model).__name__
        self.bar = tqdm(
            total=self.locals["total_timesteps"],
            initial=int(self.model.num_timesteps),  # a resumed run continues its count
            unit="step",
            desc=desc,
        )

    def _on_step(self) -> bool:
        self.bar.update(self.training_env.num_envs)
        return True

    def _on_rollout_end(self) -> None:
        buf = self.model.ep_info_buffer
        if buf:
            self.bar.set_postfix(ep_return=f"{np.mean([ep['r'] for ep in buf]):.3f}")

    def _on_training_end(self) -> None:
        self.bar.close()


def evaluate_checkpoint(
    checkpoint: str | Path,
    *,
    env_id: str,
    make_eval_env: Callable[[], gym.Env[Any, Any]],
    seeds: list[int],
    baselines: str = "",
    policy_variants: dict[str, dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """The ``metrics`` block of a checkpoint's JSON (held-out evaluation).

    The saved file, reloaded through the ``ppo`` agent (plus ``policy_variants``: name ->
    agent keyword arguments), against the comma-separated registered ``baselines``, one
    episode per seed each. A checkpoint whose JSON records another ``checkpoint_sha256``
    than the zip's is refused (``ValueError``).
    """
    from selenv.agents import make as make_agent
    from selenv.learned.rl.agent import SB3PolicyAgent  # the adapter sits above this module's users

    if Path(checkpoint).with_suffix(".json").is_file():  # a mismatched pair is refused
        verify_pair(checkpoint, read_checkpoint_metadata(checkpoint))
    agents: dict[str, Agent] = {"ppo": SB3PolicyAgent(checkpoint, env_id=env_id)}
    for name, kw in (policy_variants or {}).items():
        agents[name] = SB3PolicyAgent(checkpoint, env_id=env_id, **kw)
    for name in [b.strip() for b in baselines.split(",") if b.strip()]:
        agents[name] = make_agent(name, env_id)
    return {
        "episodes": len(seeds),
        "eval_seeds": [seeds[0], seeds[-1]],
        "agents": evaluate(make_eval_env, agents, seeds),
    }


def train(
    cfg: PPOConfig,
    *,
    env_id: str,
    make_env: Callable[[], gym.Env[Any, Any]],
    make_eval_env: Callable[[], gym.Env[Any, Any]],
    view: str,
    tb_name: str,
    extra_meta: dict[str, Any] | None = None,
    pretrain: Callable[[Any], dict[str, Any]] | None = None,
    policy_variants: dict[str, dict[str, Any]] | None = None,
    features_extractor: type[CandidateScorer] = CandidateScorer,
    extractor_kwargs: dict[str, Any] | None = None,
    native: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Train, save ``cfg.out`` (+ JSON), evaluate against ``cfg.baselines``; return the metadata.

    With ``cfg.curve_every`` the metadata holds a ``learning_curve``
    (:mod:`selenv.learned.rl.curves`), also in the ``.last`` checkpoints; ``cfg.resume``
    continues it.

    Args:
        cfg: the run's configuration.
        env_id: id written into the metadata (the env the ``ppo`` agent will accept).
        make_env: builds one training env, already in its candidate view.
        make_eval_env: builds the raw env (no view) the agents are compared on.
        view: name of the candidate view (metadata; the agent re-applies it).
        tb_name: TensorBoard run name.
        extra_meta: merged into the metadata.
        pretrain: called with the fresh model before PPO (e.g. the ranking fit of
            :mod:`selenv.learned.rl.ranking`); its returned dict is stored as
            ``meta["pretraining"]``.
        policy_variants: further agents evaluated from the saved checkpoint, name ->
            keyword arguments of :class:`~selenv.learned.rl.agent.SB3PolicyAgent` (e.g.
            ``{"ppo_top4": {"verify_top_k": 4}}``).
        features_extractor: the policy's scorer (a ``CandidateScorer`` or subclass, e.g.
            :class:`~selenv.learned.families.clustering_edits.FactorisedEditScorer`); recorded
            in the metadata's ``architecture`` with ``extractor_kwargs``.
        extractor_kwargs: further keyword arguments of ``features_extractor`` (JSON values).
        native: how ``vec_env="native"`` builds the training envs: the keywords of
            :func:`~selenv.learned.rl.vec_env.make_native_vec_env` (``env_id``,
            ``env_kwargs``, ``view``) describing the same env as ``make_env``; ``None``: the
            script's env has no native vector env (``--vec-env native`` is refused).
    """
    torch.set_num_threads(cfg.torch_threads)
    out = Path(cfg.out)
    _check_train(cfg, env_id, native)
    from selenv.learned.rl.curves import (  # the curve evaluates through the ppo agent
        CurveCallback,
        CurveRecorder,
        resumed_curve,
    )

    resumed = _read_resume(cfg, env_id, view) if cfg.resume else None
    resumed_points = resumed_curve(cfg, resumed) if resumed is not None else None
    out.parent.mkdir(parents=True, exist_ok=True)

    # 1. envs, 2. model (fresh, --init-from or --resume)
    venv, layout = _make_venv(cfg, make_env, native)
    model = _make_model(cfg, venv, features_extractor, extractor_kwargs)
    init_from = _start_weights(model, venv, cfg, env_id, view, resumed)
    if cfg.compile:
        compile_policy(model.policy)
    training_log: list[dict[str, Any]] = list((resumed or {}).get("training_log") or [])
    metadata = _Record(
        cfg=cfg,
        env_id=env_id,
        view=view,
        layout=layout,
        model=model,
        extractor=features_extractor,
        extractor_kwargs=extractor_kwargs or {},
        init_from=init_from,
        extra=extra_meta or {},
        wall_before=float((resumed or {}).get("training", {}).get("wall_seconds", 0.0)),
    )

    # 3. (optional pre-training, then) PPO
    start = time.perf_counter()
    if resumed is not None:  # the weights already hold the pre-training
        pretraining = resumed.get("pretraining")
    else:
        pretraining = pretrain(model) if pretrain is not None else None
    last_zip = last_paths(out)[0]
    flag = RunStop(cfg.max_minutes)  # signals and --max-minutes: stop at a boundary
    curve = None
    if cfg.curve_every:
        curve = CurveRecorder(
            cfg,
            env_id=env_id,
            make_eval_env=make_eval_env,
            metadata=lambda: metadata(0.0, None, complete=False),
            clock=lambda: metadata.wall_before + time.perf_counter() - start,
            flag=flag,
            resumed=resumed_points,
        )

    def save_last(interrupted: str | None) -> None:
        boundary = cb.boundary
        assert boundary is not None  # set at the first rollout start
        reached = int(model.num_timesteps)
        model.num_timesteps = boundary["num_timesteps"]  # the last completed iteration
        try:
            meta = metadata(time.perf_counter() - start, pretraining, complete=False)
            meta["resume_state"] = boundary
            meta["training_log"] = [
                e for e in training_log if e["timesteps"] <= boundary["num_timesteps"]
            ]
            if curve is not None:
                meta["learning_curve"] = curve.record(upto=boundary["num_timesteps"])
            if interrupted is not None:
                meta["interrupted"] = interrupted
            save_checkpoint(model, meta, last_zip, exclude=_NOT_SAVED)
        finally:
            model.num_timesteps = reached

    cb = _CheckpointCallback(cfg.checkpoint_every, save_last, flag, training_log)
    callbacks: list[BaseCallback] = [TqdmCallback()] if cfg.progress else []
    if curve is not None:  # before cb: a .last written at a boundary carries its point
        callbacks.append(CurveCallback(curve))
    if cfg.critic_warmup:
        callbacks.append(CriticWarmup(cfg.critic_warmup))
    remaining = cfg.total_timesteps - int(model.num_timesteps)
    with flag:
        if remaining > 0:  # 0: keep the pre-trained (or resumed) policy as it is
            model.learn(
                remaining,
                callback=[*callbacks, cb],
                tb_log_name=tb_name,
                reset_num_timesteps=resumed is None,
            )
        if curve is not None and flag.signal is None and curve.due(model.num_timesteps, final=True):
            curve.add_point(model)  # the end of the run
    wall = time.perf_counter() - start
    venv.close()
    stopped = flag.signal
    if stopped is not None and int(model.num_timesteps) < cfg.total_timesteps:
        save_last(stopped)
        done = cb.boundary["num_timesteps"] if cb.boundary else 0
        raise _stop_exception(
            stopped,
            f"saved the last completed iteration ({done} of {cfg.total_timesteps} steps) as "
            f"{last_zip} (+ .json); continue with the same command and --resume {last_zip}",
        )

    # 4. checkpoint + metadata (rollout buffers and episode stats are not needed to act)
    meta = metadata(wall, pretraining, complete=True)
    meta["resume_state"] = {
        "num_timesteps": int(model.num_timesteps),
        "n_updates": int(getattr(model, "_n_updates", 0)),
        "rng": _rng_state(),
    }
    meta["training_log"] = training_log
    if curve is not None:
        meta["learning_curve"] = curve.record()
    save_checkpoint(model, meta, out, exclude=_NOT_SAVED)
    for stale in last_paths(out):  # superseded by the complete checkpoint
        stale.unlink(missing_ok=True)
    if stopped is not None:
        raise _stop_exception(
            stopped, f"training had completed: saved {out} (+ .json); its evaluation was skipped"
        )

    # 5. evaluate the saved checkpoint (round trip through the agent) against the baselines
    if cfg.eval_episodes:
        seeds = [cfg.eval_seed + e for e in range(cfg.eval_episodes)]
        with evaluation_stops(out):
            meta["metrics"] = evaluate_checkpoint(
                out,
                env_id=env_id,
                make_eval_env=make_eval_env,
                seeds=seeds,
                baselines=cfg.baselines,
                policy_variants=policy_variants,
            )
        write_json(out.with_suffix(".json"), meta)
        summary = {k: v["mean_return"] for k, v in meta["metrics"]["agents"].items()}
        print(json.dumps({"mean_return": summary, "wall_seconds": round(wall, 1)}, indent=2))
    return meta


def _check_train(cfg: PPOConfig, env_id: str, native: dict[str, Any] | None) -> None:
    """The options of :func:`train`, checked before any work (``UsageError`` naming one)."""
    if Path(cfg.out).suffix != ".zip":
        raise UsageError(f"--out must end in .zip, got {cfg.out!r}")
    check_bounds(cfg)
    if cfg.algo not in ALGORITHMS:
        raise UsageError(f"--algo must be one of {sorted(ALGORITHMS)}, got {cfg.algo!r}")
    if cfg.shortlist < 0:
        raise UsageError(f"--shortlist must be an int >= 0 (0: all), got {cfg.shortlist}")
    if cfg.vec_env not in VEC_ENVS:
        raise UsageError(f"--vec-env must be one of {list(VEC_ENVS)}, got {cfg.vec_env!r}")
    if cfg.vec_env == "native" and native is None:
        raise UsageError(
            f"--vec-env native: {env_id} is trained through a wrapper without a native vector "
            "env; use --vec-env dummy or subproc"
        )
    if cfg.curve_every and env_id not in gym.registry:
        raise UsageError(
            f"--curve-every: the learning curve plays the policy through the ppo agent on a "
            f"Gymnasium env, and {env_id} is not one (its script evaluates on its own)"
        )
    check_run_outputs(cfg, "selenv.learned.rl.training.train")  # the scripts check first


def _make_venv(
    cfg: PPOConfig, make_env: Callable[[], gym.Env[Any, Any]], native: dict[str, Any] | None
) -> tuple[VecEnv, dict[str, Any]]:
    """The training envs and their observation layout; the memory estimate checked.

    Raises:
        UsageError: the run would need more than ``--max-memory-gb`` (the envs are closed).
    """

    def monitored() -> gym.Env[Any, Any]:
        return Monitor(make_env())

    factories = [monitored for _ in range(cfg.n_envs)]
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # workers: tiny matrices, no contention
    venv: VecEnv
    if cfg.vec_env == "native":
        assert native is not None  # checked by _check_train
        venv = make_native_vec_env(n_envs=cfg.n_envs, seed=cfg.seed, **native)
    else:
        venv = (
            SubprocVecEnv(factories, start_method="spawn")
            if cfg.vec_env == "subproc"
            else DummyVecEnv(factories)
        )
        venv.seed(cfg.seed)
    if cfg.normalize_reward:  # training statistics only: the policy acts on raw observations
        venv = VecNormalize(venv, norm_obs=False, norm_reward=True, gamma=cfg.gamma)
    layout = obs_layout(venv.observation_space)
    obs_floats = sum(
        int(np.prod(sp.shape or (1,)))
        for sp in getattr(venv.observation_space, "spaces", {"": venv.observation_space}).values()
    )
    need = estimate_memory_bytes(cfg, obs_floats, int(layout["n"]), int(layout["n_features"]))
    if need > cfg.max_memory_gb * 2**30:
        venv.close()
        raise UsageError(
            f"this run needs about {need / 2**30:.1f} GB (rollout buffer of --n-envs x --n-steps "
            f"= {cfg.n_envs * cfg.n_steps} observations of {obs_floats} floats, minibatches of "
            f"--batch-size {cfg.batch_size} x {layout['n']} candidates x --hidden "
            f"{cfg.hidden}), more than --max-memory-gb {cfg.max_memory_gb:g}: lower these "
            "options or raise --max-memory-gb"
        )
    return venv, layout


def _make_model(
    cfg: PPOConfig,
    venv: VecEnv,
    features_extractor: type[CandidateScorer],
    extractor_kwargs: dict[str, Any] | None,
) -> Any:
    """The fresh (Maskable)PPO model of the run's options on ``venv``."""
    return make_ppo(
        venv,
        cfg.algo,
        seed=cfg.seed,
        learning_rate=cfg.learning_rate,
        n_steps=cfg.n_steps,
        batch_size=cfg.batch_size,
        n_epochs=cfg.n_epochs,
        ent_coef=cfg.ent_coef,
        gamma=cfg.gamma,
        target_kl=cfg.target_kl or None,
        tensorboard_log=cfg.tensorboard_dir or None,
        policy_kwargs={
            "features_extractor_class": features_extractor,
            "features_extractor_kwargs": {
                "hidden": parse_hidden(cfg.hidden),
                "activation": cfg.activation,
                "gain_skip_init": cfg.gain_skip_init,
                **({"shortlist": cfg.shortlist} if cfg.shortlist else {}),
                **(extractor_kwargs or {}),
            },
        },
    )


def _start_weights(
    model: Any,
    venv: VecEnv,
    cfg: PPOConfig,
    env_id: str,
    view: str,
    resumed: dict[str, Any] | None,
) -> Any:
    """Load ``--init-from`` or the ``--resume`` state into ``model``; the ``init_from`` record.

    Raises:
        UsageError: an ``--init-from`` checkpoint that does not fit (the envs are closed).
    """
    if resumed is not None:  # a resumed run holds its own weights
        _restore(model, venv, cfg, resumed)
        return resumed.get("init_from")
    if not cfg.init_from:
        return None
    try:
        return init_from_checkpoint(model, cfg.init_from, env_id, view)
    except ValueError as exc:
        venv.close()
        raise UsageError(f"--init-from: {exc}") from None


@dataclass
class _Record:
    """The metadata of a PPO run's checkpoints (``.last`` and final), built when saved."""

    cfg: PPOConfig
    env_id: str
    view: str
    layout: dict[str, Any]
    model: Any
    extractor: type[CandidateScorer]
    extractor_kwargs: dict[str, Any]
    init_from: Any
    extra: dict[str, Any]
    wall_before: float
    env_config: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.env_id in gym.registry:  # the configuration trained on, resolved
            probe = gym.make(self.env_id, **self.cfg.kwargs())
            self.env_config = resolved_env_config(probe)
            probe.close()

    def __call__(self, wall: float, pretraining: Any, complete: bool) -> dict[str, Any]:
        """The metadata after ``wall`` seconds of this invocation."""
        cfg, model, layout, extractor = self.cfg, self.model, self.layout, self.extractor
        return {
            "env_id": self.env_id,
            "env_kwargs": cfg.kwargs(),
            "env_config": self.env_config,
            "view": self.view,
            "obs_layout": {
                "whitened_dim": layout["whitened_dim"],
                "n_features": layout["n_features"],
                "n_candidates_trained": layout["n"],
            },
            "architecture": {
                "policy": f"selenv.learned.rl.candidate_policy.{type(model.policy).__name__}",
                "features_extractor": f"{extractor.__module__}.{extractor.__name__}",
                "hidden": parse_hidden(cfg.hidden),
                "activation": cfg.activation,
                "gain_skip_init": cfg.gain_skip_init,
                **({"shortlist": cfg.shortlist} if cfg.shortlist else {}),
                **self.extractor_kwargs,
                "net_arch": {"pi": [], "vf": [64]},
                "n_parameters": int(sum(p.numel() for p in model.policy.parameters())),
                "pool_size_independent": True,
            },
            "training": {
                **dataclasses.asdict(cfg),
                "algorithm": type(model).__name__,
                "timesteps_done": int(model.num_timesteps),
                "wall_seconds": round(self.wall_before + wall, 1),
            },
            "pretraining": pretraining,
            "init_from": self.init_from,
            "metrics": None,
            "complete": complete,
            "num_timesteps": int(model.num_timesteps),
            "selenv_version": selenv.__version__,
            "torch_version": torch.__version__,
            "sb3_version": stable_baselines3.__version__,
            "sb3_contrib_version": sb3_contrib.__version__,
            **self.extra,
        }


#: model attributes a checkpoint leaves out (rollout state and episode stats: not needed)
_NOT_SAVED = ["_last_obs", "_last_original_obs", "ep_info_buffer"]


#: metadata that must agree between a resumed checkpoint and the options of the run
_RESUME_KEYS = ("env_id", "env_kwargs", "view", "algorithm", "hidden", "activation")


def _read_resume(cfg: PPOConfig, env_id: str, view: str) -> dict[str, Any]:
    """The metadata of ``cfg.resume``, checked against the run (``UsageError`` otherwise)."""
    path = Path(cfg.resume)
    meta = read_resume_pair(path)
    state = meta.get("resume_state")
    if not isinstance(state, dict) or not isinstance(state.get("num_timesteps"), int):
        raise UsageError(
            f"--resume {path}: no resume state in its metadata (a checkpoint written by a "
            "training run of this version: <out stem>.last.zip or a final checkpoint)"
        )
    training = meta.get("training")
    training = training if isinstance(training, dict) else {}
    arch = meta.get("architecture")
    arch = arch if isinstance(arch, dict) else {}
    theirs = {
        "env_id": meta.get("env_id"),
        "env_kwargs": meta.get("env_kwargs"),
        "view": meta.get("view"),
        "algorithm": training.get("algorithm"),
        "hidden": arch.get("hidden"),
        "activation": arch.get("activation"),
    }
    algorithm = {"maskable_ppo": "MaskablePPO", "ppo": "PPO"}.get(cfg.algo, cfg.algo)
    ours = {
        "env_id": env_id,
        "env_kwargs": cfg.kwargs(),
        "view": view,
        "algorithm": algorithm,
        "hidden": parse_hidden(cfg.hidden),
        "activation": cfg.activation,
    }
    for key in _RESUME_KEYS:
        if theirs[key] != ours[key]:
            raise UsageError(
                f"--resume {path}: it was trained with {key} = {theirs[key]!r}, this run has "
                f"{ours[key]!r}; resume with the options of the interrupted run"
            )
    done = state["num_timesteps"]
    if done > cfg.total_timesteps:
        raise UsageError(
            f"--resume {path}: it already made {done} steps, more than --total-timesteps "
            f"{cfg.total_timesteps}"
        )
    return meta


def _restore(model: Any, venv: VecEnv, cfg: PPOConfig, meta: dict[str, Any]) -> None:
    """Weights, Adam state, counters and generators of ``cfg.resume`` into the fresh ``model``.

    Only tensors are read (``torch.load(weights_only=True)``); the zip's pickled ``data``
    entry is never deserialised. The envs are reseeded with ``seed + num_timesteps``.
    """
    from selenv.learned.rl.safe_load import read_weights

    path = Path(cfg.resume)
    state = meta["resume_state"]
    try:
        model.policy.load_state_dict(read_weights(path), strict=True)
        raw = _zip_member(path, "policy.optimizer.pth", MAX_OPTIMIZER_BYTES)
    except (ValueError, RuntimeError, KeyError, TypeError) as exc:
        raise UsageError(f"--resume {path}: cannot load its weights: {exc}") from None
    try:  # hostile or junk: one line, nothing run
        optimizer = load_tensors(
            raw, "policy.optimizer.pth", kind="plain tensors", junk="plain tensors"
        )
        model.policy.optimizer.load_state_dict(optimizer)
    except (ValueError, RuntimeError, KeyError, TypeError) as exc:
        raise UsageError(f"--resume {path}: {exc}") from None
    done = int(state["num_timesteps"])
    model.num_timesteps = done
    model._n_updates = int(state.get("n_updates", 0))
    venv.seed(cfg.seed + done)
    try:
        _set_rng_state(state["rng"])
    except (KeyError, ValueError) as exc:
        raise UsageError(f"--resume {path}: {exc}") from None
