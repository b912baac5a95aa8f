"""Train MaskablePPO on ``selenv/FIMSelection-v0`` and compare it with greedy and random.

Readable top to bottom (CleanRL style): the :class:`Config` dataclass is the command line, then
envs, model, training (tqdm bar, TensorBoard under ``runs/``), save (zip + JSON metadata), and an
evaluation of the saved checkpoint against ``greedy`` and ``random`` on the same held-out
seeds (``eval_seed``, ``eval_seed + 1``, ...; training scenarios come from the ``seed`` stream).

    python -m train.train_fim_ppo  # defaults: the shipped checkpoint
    tensorboard --logdir runs
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
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
from stable_baselines3.common.vec_env import DummyVecEnv
from tqdm.auto import tqdm

import selenv
from learned.agent import SB3PolicyAgent
from learned.fim_policy import make_maskable_ppo
from selenv.agents import Agent
from selenv.agents import make as make_agent

ENV_ID = "selenv/FIMSelection-v0"


@dataclass
class Config:
    """Every knob of a run; each field is a ``--kebab-case`` command-line option."""

    # env (``gymnasium.make(ENV_ID, preset=..., n_candidates=..., budget=...)``)
    preset: str = "example2"
    n_candidates: int = 100
    budget: int = 10
    # training
    total_timesteps: int = 140_000
    seed: int = 0
    n_envs: int = 8
    n_steps: int = 128
    batch_size: int = 512
    n_epochs: int = 4
    learning_rate: float = 1e-3
    ent_coef: float = 1e-3
    # policy
    hidden: str = "64,64"
    activation: str = "tanh"
    gain_skip_init: float = 0.0
    # outputs
    out: str = "checkpoints/fim_selection_ppo.zip"
    tensorboard_dir: str = "runs"  # empty string: no TensorBoard logs
    progress: bool = True
    torch_threads: int = 1
    # evaluation on held-out seeds
    eval_episodes: int = 100
    eval_seed: int = 10_000

    @property
    def env_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of ``gymnasium.make``."""
        return {"preset": self.preset, "n_candidates": self.n_candidates, "budget": self.budget}


def parse_args(argv: list[str] | None = None) -> Config:
    """Build a :class:`Config` from the command line (one option per field)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for f in dataclasses.fields(Config):
        flag = "--" + f.name.replace("_", "-")
        if f.type in ("bool", bool):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=f.default)
        else:
            typ = {"int": int, "float": float, "str": str}[str(f.type)]
            parser.add_argument(flag, type=typ, default=f.default)
    return Config(**vars(parser.parse_args(argv)))


class TqdmCallback(BaseCallback):
    """A tqdm bar over the timesteps (SB3's ``progress_bar=True`` needs ``rich``)."""

    def _on_training_start(self) -> None:
        self.bar = tqdm(total=self.locals["total_timesteps"], unit="step", desc="MaskablePPO")

    def _on_step(self) -> bool:
        self.bar.update(self.training_env.num_envs)
        return True

    def _on_rollout_end(self) -> None:
        buf = self.model.ep_info_buffer
        if buf:
            self.bar.set_postfix(ep_return=f"{np.mean([ep['r'] for ep in buf]):.3f}")

    def _on_training_end(self) -> None:
        self.bar.close()


def run_episodes(agent: Agent, env_kwargs: dict[str, Any], seeds: list[int]) -> list[float]:
    """Final objective of ``agent`` on one episode per seed (same scenarios for every agent)."""
    env = gym.make(ENV_ID, **env_kwargs)
    finals = []
    for seed in seeds:
        obs, info = env.reset(seed=seed)
        agent.reset(env, seed=seed)
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(agent.act(obs, info))
            done = terminated or truncated
        finals.append(float(info["objective"]))
    env.close()
    return finals


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Train, save the checkpoint and its metadata, evaluate; return the metadata dict."""
    cfg = parse_args(argv)
    torch.set_num_threads(cfg.torch_threads)
    out = Path(cfg.out)
    if cfg.eval_episodes < 1:
        raise ValueError(f"--eval-episodes must be >= 1, got {cfg.eval_episodes}")
    if out.suffix != ".zip":
        raise ValueError(f"--out must end in .zip, got {cfg.out!r}")
    out.parent.mkdir(parents=True, exist_ok=True)

    # 1. envs: n_envs copies in one process (each step is cheap; the policy update dominates)
    def make_env() -> gym.Env[Any, Any]:
        return Monitor(gym.make(ENV_ID, **cfg.env_kwargs))

    venv = DummyVecEnv([make_env for _ in range(cfg.n_envs)])
    venv.seed(cfg.seed)
    base = venv.envs[0].unwrapped
    m, d = int(base.m), int(base.d)  # type: ignore[attr-defined]

    # 2. model
    hidden = [int(h) for h in cfg.hidden.split(",")]
    model = make_maskable_ppo(
        venv,
        seed=cfg.seed,
        learning_rate=cfg.learning_rate,
        n_steps=cfg.n_steps,
        batch_size=cfg.batch_size,
        n_epochs=cfg.n_epochs,
        ent_coef=cfg.ent_coef,
        tensorboard_log=cfg.tensorboard_dir or None,
        policy_kwargs={
            "features_extractor_kwargs": {
                "hidden": hidden,
                "activation": cfg.activation,
                "gain_skip_init": cfg.gain_skip_init,
            }
        },
    )

    # 3. train
    start = time.perf_counter()
    callbacks: list[BaseCallback] = [TqdmCallback()] if cfg.progress else []
    model.learn(cfg.total_timesteps, callback=callbacks, tb_log_name="fim_ppo")
    wall = time.perf_counter() - start
    venv.close()

    # 4. save the zip and its metadata (metrics filled in after the evaluation)
    # (rollout state and episode stats are not needed to act or to resume; they would double
    # the zip)
    model.save(out, exclude=["_last_obs", "_last_original_obs", "ep_info_buffer"])
    n_params = sum(p.numel() for p in model.policy.parameters())
    meta: dict[str, Any] = {
        "env_id": ENV_ID,
        "env_kwargs": cfg.env_kwargs,
        "architecture": {
            "policy": "learned.fim_policy.CandidateScoringPolicy",
            "features_extractor": "learned.fim_policy.CandidateScorer",
            "hidden": hidden,
            "activation": cfg.activation,
            "gain_skip_init": cfg.gain_skip_init,
            "net_arch": {"pi": [], "vf": [64]},
            "n_parameters": int(n_params),
            "pool_size_independent": True,
        },
        "obs_layout": {
            "m": m,
            "d": d,
            "whitened_dim": m * d,
            "n_features": 4,
            "n_candidates_trained": int(base.n),  # type: ignore[attr-defined]
        },
        "training": {
            "algorithm": "MaskablePPO",
            "total_timesteps": int(model.num_timesteps),
            "seed": cfg.seed,
            "n_envs": cfg.n_envs,
            "n_steps": cfg.n_steps,
            "batch_size": cfg.batch_size,
            "n_epochs": cfg.n_epochs,
            "learning_rate": cfg.learning_rate,
            "ent_coef": cfg.ent_coef,
            "gamma": model.gamma,
            "wall_seconds": round(wall, 1),
        },
        "metrics": None,
        "selenv_version": selenv.__version__,
        "torch_version": torch.__version__,
        "sb3_version": stable_baselines3.__version__,
        "sb3_contrib_version": sb3_contrib.__version__,
    }
    json_path = out.with_suffix(".json")
    json_path.write_text(json.dumps(meta, indent=2) + "\n")

    # 5. evaluate the saved checkpoint (round trip through the agent) against the baselines
    seeds = [cfg.eval_seed + e for e in range(cfg.eval_episodes)]
    agents: dict[str, Agent] = {
        "ppo": SB3PolicyAgent(out),
        "greedy": make_agent("greedy", ENV_ID),
        "random": make_agent("random", ENV_ID),
    }
    finals = {name: run_episodes(a, cfg.env_kwargs, seeds) for name, a in agents.items()}
    meta["metrics"] = {
        f"{name}_mean_objective": round(float(np.mean(v)), 4) for name, v in finals.items()
    }
    meta["metrics"].update(
        {
            "ppo_over_greedy": round(float(np.mean(finals["ppo"]) / np.mean(finals["greedy"])), 4),
            "ppo_ge_greedy_episodes": int(np.sum(np.array(finals["ppo"]) >= finals["greedy"])),
            "episodes": cfg.eval_episodes,
            "eval_seeds": [seeds[0], seeds[-1]] if seeds else [],
        }
    )
    json_path.write_text(json.dumps(meta, indent=2) + "\n")
    print(json.dumps({"metrics": meta["metrics"], "wall_seconds": round(wall, 1)}, indent=2))
    return meta


if __name__ == "__main__":
    main()
