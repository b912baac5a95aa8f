"""Train MaskablePPO on ``selenv/ReceiverClustering-v0`` (Greiff et al. 2022) with local edits.

The policy plays the env's ``action_mode="edit"`` encoding (one masked edit per filter step:
no-op, move, leave, swap) through :class:`learned.rl.views.ClusteringEditView`, which
describes every edit by the receivers' noise levels, the clusters' composition and sizes
-- without evaluating the cost ``J``, so the policy costs zero cost evaluations per step
where the GA spends a population's worth. Reward ``-J`` per step (``gamma`` < 1: the cost is
a running one). Evaluation: the saved checkpoint (acting through the same view on the
default assignment encoding) against ``ga``, ``greedy`` and ``fixed_random`` on held-out
seeds.

    python -m train.train_clustering_ppo   # -> checkpoints/receiver_clustering_ppo.zip
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import gymnasium as gym

from learned.config import parse_config
from learned.rl.training import PPOConfig, train
from learned.rl.views import CandidateViewWrapper, view_for

ENV_ID = "selenv/ReceiverClustering-v0"


@dataclass
class Config(PPOConfig):
    """Defaults of the shipped run."""

    env_kwargs: str = json.dumps({"n_agents": 30, "horizon": 200})
    eval_horizon: int = 500  # evaluation episodes use the env's default length
    total_timesteps: int = 40_000
    n_envs: int = 4
    vec_env: str = "subproc"
    n_steps: int = 256
    batch_size: int = 256
    gamma: float = 0.98
    learning_rate: float = 3e-4
    ent_coef: float = 1e-3
    gain_skip_init: float = 1.0  # starts at ~94 % "keep the clustering" (see ClusteringEditView)
    out: str = "checkpoints/receiver_clustering_ppo.zip"
    eval_episodes: int = 10
    baselines: str = "ga,greedy,fixed_random"


def make_env(kwargs: dict[str, Any]) -> gym.Env[Any, Any]:
    """One training env: edit encoding, in the edits-as-candidates view."""
    env = gym.make(ENV_ID, **{**kwargs, "action_mode": "edit"})
    return CandidateViewWrapper(env, view_for(ENV_ID, env))


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Train, save, evaluate; return the checkpoint's metadata."""
    cfg = parse_config(Config, argv, (__doc__ or "").split("\n")[0])
    kwargs = cfg.kwargs()
    eval_kwargs = {**kwargs, "horizon": cfg.eval_horizon}
    eval_kwargs.pop("action_mode", None)
    return train(
        cfg,
        env_id=ENV_ID,
        make_env=lambda: make_env(kwargs),
        make_eval_env=lambda: gym.make(ENV_ID, **eval_kwargs),
        view="clustering_edits",
        tb_name="clustering_ppo",
        extra_meta={"eval_env_kwargs": eval_kwargs},
    )


if __name__ == "__main__":
    main()
