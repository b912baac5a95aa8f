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
3. training with a tqdm bar and TensorBoard logs (``runs/``);
4. checkpoint ``<out>.zip`` + metadata ``<out>.json`` (env id and kwargs, candidate view,
   layout, architecture, hyper-parameters, versions); an existing file is refused without
   ``--force`` (:func:`check_run_outputs`, which the scripts call before any work);
5. evaluation of the saved checkpoint, reloaded through the ``ppo`` agent adapter, against
   the env's heuristics on the same held-out seeds (``eval_seed``, ``eval_seed + 1``, ...);
   the metrics are written into the JSON.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable
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
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv
from tqdm.auto import tqdm

import selenv
from selenv.agents import Agent
from selenv.bench.runner import AgentResult, run_episode
from selenv.envs.resolved import resolved_env_config
from selenv.learned.config import arg, check_outputs
from selenv.learned.rl.candidate_policy import ALGORITHMS, CandidateScorer, make_ppo, obs_layout
from selenv.learned.rl.vec_env import make_native_vec_env

#: the ``--vec-env`` choices
VEC_ENVS = ("native", "dummy", "subproc")

__all__ = [
    "VEC_ENVS",
    "PPOConfig",
    "TqdmCallback",
    "check_run_outputs",
    "evaluate",
    "evaluate_checkpoint",
    "output_paths",
    "train",
]


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
    # outputs
    out: str = arg("", "checkpoint path (.zip); its metadata goes next to it as .json")
    force: bool = arg(False, "overwrite an existing --out (.zip or .json)")
    tensorboard_dir: str = arg("runs", "TensorBoard log folder (empty: no TensorBoard logs)")
    progress: bool = arg(True, "show a tqdm bar over the timesteps")
    torch_threads: int = arg(1, "torch CPU threads of this process")
    # evaluation on held-out seeds
    eval_episodes: int = arg(
        20, "held-out episodes on which the saved checkpoint is evaluated (0: none)"
    )
    eval_seed: int = arg(10_000, "seed of the first held-out episode (then +1, +2, ...)")
    baselines: str = arg(
        "greedy,random", "comma-separated registered agents evaluated next to the policy"
    )

    def kwargs(self) -> dict[str, Any]:
        """``env_kwargs`` parsed (a JSON object)."""
        try:
            out = json.loads(self.env_kwargs)
        except json.JSONDecodeError as exc:
            raise ValueError(f"--env-kwargs must be a JSON object: {exc}") from None
        if not isinstance(out, dict):
            raise ValueError(f"--env-kwargs must be a JSON object, got {self.env_kwargs!r}")
        return out


def output_paths(cfg: PPOConfig) -> list[Path]:
    """The files a run writes: the checkpoint ``cfg.out`` and its ``.json`` metadata."""
    out = Path(cfg.out)
    return [out, out.with_suffix(".json")]


def check_run_outputs(cfg: PPOConfig, prog: str) -> None:
    """Exit 2 (one line, before any work) on outputs that exist or cannot be written.

    An existing ``cfg.out`` or its ``.json`` without ``--force``, or an output or TensorBoard
    folder that cannot be written (:func:`selenv.learned.config.check_outputs`).
    """
    folders = [cfg.tensorboard_dir] if cfg.tensorboard_dir else []
    check_outputs(prog, output_paths(cfg), force=cfg.force, folders=folders)


class TqdmCallback(BaseCallback):
    """A tqdm bar over the timesteps (SB3's ``progress_bar=True`` needs ``rich``)."""

    def _on_training_start(self) -> None:
        desc = type(self.model).__name__
        self.bar = tqdm(total=self.locals["total_timesteps"], unit="step", desc=desc)

    def _on_step(self) -> bool:
        self.bar.update(self.training_env.num_envs)
        return True

    def _on_rollout_end(self) -> None:
        buf = self.model.ep_info_buffer
        if buf:
            self.bar.set_postfix(ep_return=f"{np.mean([ep['r'] for ep in buf]):.3f}")

    def _on_training_end(self) -> None:
        self.bar.close()


def evaluate(
    make_env: Callable[[], gym.Env[Any, Any]], agents: dict[str, Agent], seeds: list[int]
) -> dict[str, dict[str, Any]]:
    """Each agent on one episode per seed: returns, final objectives, decision seconds.

    Envs that count objective evaluations also give ``cost_evaluations_per_decision``.
    """
    out: dict[str, dict[str, Any]] = {}
    for name, agent in agents.items():
        env = make_env()
        res = AgentResult(name)
        for seed in seeds:
            ret, obj = run_episode(env, agent, seed, res)
            res.returns.append(ret)
            res.final_objectives.append(obj)
        env.close()
        out[name] = {
            "mean_return": round(float(np.mean(res.returns)), 5),
            "mean_final_objective": round(float(np.mean(res.final_objectives)), 5),
            "returns": [round(r, 5) for r in res.returns],
            "decision_seconds_mean": res.decision_seconds / max(res.decisions, 1),
        }
        if res.cost_evaluations is not None:
            out[name]["cost_evaluations_per_decision"] = res.cost_evaluations_per_decision
    return out


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
    episode per seed each.
    """
    from selenv.agents import make as make_agent
    from selenv.learned.rl.agent import SB3PolicyAgent  # the adapter sits above this module's users

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
            :class:`~selenv.learned.rl.edit_policy.FactorisedEditScorer`); recorded in the
            metadata's ``architecture`` with ``extractor_kwargs``.
        extractor_kwargs: further keyword arguments of ``features_extractor`` (JSON values).
        native: how ``vec_env="native"`` builds the training envs: the keywords of
            :func:`~selenv.learned.rl.vec_env.make_native_vec_env` (``env_id``,
            ``env_kwargs``, ``view``) describing the same env as ``make_env``; ``None``: the
            script's env has no native vector env (``--vec-env native`` is refused).
    """
    torch.set_num_threads(cfg.torch_threads)
    out = Path(cfg.out)
    if out.suffix != ".zip":
        raise ValueError(f"--out must end in .zip, got {cfg.out!r}")
    if cfg.total_timesteps < 0:
        raise ValueError(f"--total-timesteps must be >= 0, got {cfg.total_timesteps}")
    if cfg.eval_episodes < 0:
        raise ValueError(f"--eval-episodes must be >= 0, got {cfg.eval_episodes}")
    if cfg.algo not in ALGORITHMS:
        raise ValueError(f"--algo must be one of {sorted(ALGORITHMS)}, got {cfg.algo!r}")
    if cfg.vec_env not in VEC_ENVS:
        raise ValueError(f"--vec-env must be one of {list(VEC_ENVS)}, got {cfg.vec_env!r}")
    if cfg.vec_env == "native" and native is None:
        raise ValueError(
            f"--vec-env native: {env_id} is trained through a wrapper without a native vector "
            "env; use --vec-env dummy or subproc"
        )
    check_run_outputs(cfg, "selenv.learned.rl.training.train")  # the scripts check first
    out.parent.mkdir(parents=True, exist_ok=True)

    # 1. envs
    def monitored() -> gym.Env[Any, Any]:
        return Monitor(make_env())

    factories = [monitored for _ in range(cfg.n_envs)]
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # workers: tiny matrices, no contention
    venv: VecEnv
    if cfg.vec_env == "native":
        assert native is not None  # checked above
        venv = make_native_vec_env(n_envs=cfg.n_envs, seed=cfg.seed, **native)
    else:
        venv = (
            SubprocVecEnv(factories, start_method="spawn")
            if cfg.vec_env == "subproc"
            else DummyVecEnv(factories)
        )
        venv.seed(cfg.seed)
    layout = obs_layout(venv.observation_space)

    # 2. model
    hidden = [int(h) for h in cfg.hidden.split(",")]
    model = make_ppo(
        venv,
        cfg.algo,
        seed=cfg.seed,
        learning_rate=cfg.learning_rate,
        n_steps=cfg.n_steps,
        batch_size=cfg.batch_size,
        n_epochs=cfg.n_epochs,
        ent_coef=cfg.ent_coef,
        gamma=cfg.gamma,
        tensorboard_log=cfg.tensorboard_dir or None,
        policy_kwargs={
            "features_extractor_class": features_extractor,
            "features_extractor_kwargs": {
                "hidden": hidden,
                "activation": cfg.activation,
                "gain_skip_init": cfg.gain_skip_init,
                **(extractor_kwargs or {}),
            },
        },
    )

    # 3. (optional pre-training, then) PPO
    start = time.perf_counter()
    pretraining = pretrain(model) if pretrain is not None else None
    callbacks: list[BaseCallback] = [TqdmCallback()] if cfg.progress else []
    if cfg.total_timesteps > 0:  # 0: keep the pre-trained policy as it is
        model.learn(cfg.total_timesteps, callback=callbacks, tb_log_name=tb_name)
    wall = time.perf_counter() - start
    venv.close()

    # 4. checkpoint + metadata (rollout buffers and episode stats are not needed to act)
    model.save(out, exclude=["_last_obs", "_last_original_obs", "ep_info_buffer"])
    env_config = None  # the configuration trained on, resolved (Gymnasium ids)
    if env_id in gym.registry:
        probe = gym.make(env_id, **cfg.kwargs())
        env_config = resolved_env_config(probe)
        probe.close()
    meta: dict[str, Any] = {
        "env_id": env_id,
        "env_kwargs": cfg.kwargs(),
        "env_config": env_config,
        "view": view,
        "obs_layout": {
            "whitened_dim": layout["whitened_dim"],
            "n_features": layout["n_features"],
            "n_candidates_trained": layout["n"],
        },
        "architecture": {
            "policy": f"selenv.learned.rl.candidate_policy.{type(model.policy).__name__}",
            "features_extractor": f"{features_extractor.__module__}.{features_extractor.__name__}",
            "hidden": hidden,
            "activation": cfg.activation,
            "gain_skip_init": cfg.gain_skip_init,
            **(extractor_kwargs or {}),
            "net_arch": {"pi": [], "vf": [64]},
            "n_parameters": int(sum(p.numel() for p in model.policy.parameters())),
            "pool_size_independent": True,
        },
        "training": {
            **dataclasses.asdict(cfg),
            "algorithm": type(model).__name__,
            "timesteps_done": int(model.num_timesteps),
            "wall_seconds": round(wall, 1),
        },
        "pretraining": pretraining,
        "metrics": None,
        "selenv_version": selenv.__version__,
        "torch_version": torch.__version__,
        "sb3_version": stable_baselines3.__version__,
        "sb3_contrib_version": sb3_contrib.__version__,
        **(extra_meta or {}),
    }
    json_path = out.with_suffix(".json")
    json_path.write_text(json.dumps(meta, indent=2) + "\n")

    # 5. evaluate the saved checkpoint (round trip through the agent) against the baselines
    if cfg.eval_episodes:
        seeds = [cfg.eval_seed + e for e in range(cfg.eval_episodes)]
        meta["metrics"] = evaluate_checkpoint(
            out,
            env_id=env_id,
            make_eval_env=make_eval_env,
            seeds=seeds,
            baselines=cfg.baselines,
            policy_variants=policy_variants,
        )
        json_path.write_text(json.dumps(meta, indent=2) + "\n")
        summary = {k: v["mean_return"] for k, v in meta["metrics"]["agents"].items()}
        print(json.dumps({"mean_return": summary, "wall_seconds": round(wall, 1)}, indent=2))
    return meta
