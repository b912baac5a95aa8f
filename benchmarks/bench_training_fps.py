"""MaskablePPO training fps: the native vector envs against the DummyVecEnv path.

For each family, the training script's own defaults (``Config()`` of ``train_fim_ppo``,
``train_landmark_ppo``, ``train_cl_ppo``, ``train_clustering_ppo``: env keywords, candidate
view, ``n_envs``, ``n_steps``, ``batch_size``, ``n_epochs``, network), two ways:

* **DummyVecEnv** (``"before"`` in the JSON): ``DummyVecEnv`` over ``n_envs``
  ``gymnasium.make`` envs in their candidate view, and for ReceiverClustering the per-edit MLP
  scorer (``--scorer mlp``);
* **native** (``"after"``): the script's default, ``vec_env="native"`` (``NativeVecEnv`` over
  ``gymnasium.make_vec``) and for ReceiverClustering the factorised edit scorer.

fps = environment steps / wall seconds of ``model.learn(rollouts * n_envs * n_steps)`` (rollout
collection and the PPO update; the model is built outside the timing), one BLAS and one torch
thread, interleaved rounds, median.

    .venv/bin/python benchmarks/bench_training_fps.py [--rounds 3] [--rollouts 1]
        [--families fim landmarks cl clustering] [--json PATH]
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import time
import warnings
from typing import Any

import gymnasium as gym
import torch
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

import selenv  # noqa: F401
from selenv.learned.rl.candidate_policy import CandidateScorer, make_ppo
from selenv.learned.rl.vec_env import make_native_vec_env
from selenv.learned.rl.views import CandidateViewWrapper, view_for
from selenv.threads import limit_threads

FAMILIES = {
    "fim": ("selenv.train.train_fim_ppo", None),
    "landmarks": ("selenv.train.train_landmark_ppo", None),
    "cl": ("selenv.train.train_cl_ppo", "view"),
    "clustering": ("selenv.train.train_clustering_ppo", "clustering_edits"),
}


def _setup(family: str) -> dict[str, Any]:
    module_name, view_spec = FAMILIES[family]
    mod = importlib.import_module(module_name)
    cfg = mod.Config()
    kwargs = cfg.kwargs()
    if family == "clustering":
        kwargs = {**kwargs, "action_mode": "edit"}
    view = getattr(cfg, "view", None) if view_spec == "view" else view_spec
    return {"mod": mod, "cfg": cfg, "env_id": mod.ENV_ID, "kwargs": kwargs, "view": view}


def _dummy(s: dict[str, Any]) -> DummyVecEnv:
    env_id, kwargs, view = s["env_id"], s["kwargs"], s["view"]

    def make() -> gym.Env[Any, Any]:
        env = gym.make(env_id, **kwargs)
        if view is not None:
            env = CandidateViewWrapper(env, view_for(env_id, env, view))
        return Monitor(env)

    venv = DummyVecEnv([make for _ in range(s["cfg"].n_envs)])
    venv.seed(s["cfg"].seed)
    return venv


def _extractor(s: dict[str, Any], after: bool) -> tuple[type[CandidateScorer], dict[str, Any]]:
    cfg = s["cfg"]
    if s["mod"].__name__.endswith("train_clustering_ppo"):
        from selenv.learned.families.clustering_edits import scorer_policy_kwargs

        return scorer_policy_kwargs(cfg.scorer if after else "mlp", cfg.edit_rank)
    return CandidateScorer, {}


def fps(s: dict[str, Any], after: bool, rollouts: int) -> float:
    """Environment steps per second of one ``learn`` call (model built outside the timing)."""
    cfg = s["cfg"]
    venv = (
        make_native_vec_env(
            s["env_id"], cfg.n_envs, seed=cfg.seed, view=s["view"], env_kwargs=s["kwargs"]
        )
        if after
        else _dummy(s)
    )
    extractor, extra = _extractor(s, after)
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
        policy_kwargs={
            "features_extractor_class": extractor,
            "features_extractor_kwargs": {
                "hidden": [int(h) for h in cfg.hidden.split(",")],
                "activation": cfg.activation,
                "gain_skip_init": cfg.gain_skip_init,
                **extra,
            },
        },
    )
    steps = rollouts * cfg.n_envs * cfg.n_steps
    t = time.perf_counter()
    model.learn(steps)
    wall = time.perf_counter() - t
    venv.close()
    return model.num_timesteps / wall


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--rollouts", type=int, default=1, help="rollouts per learn() call")
    ap.add_argument("--families", nargs="*", default=list(FAMILIES), choices=list(FAMILIES))
    ap.add_argument("--json", help="write the figures to this JSON file (atomically)")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    out: dict[str, Any] = {}
    print("| env (script defaults) | DummyVecEnv | native | native / DummyVecEnv |")
    print("|---|---|---|---|")
    with limit_threads(blas=1, torch=1):
        torch.set_num_threads(1)
        for family in args.families:
            s = _setup(family)
            runs: dict[str, list[float]] = {"before": [], "after": []}
            for _ in range(args.rounds):
                runs["before"].append(fps(s, False, args.rollouts))
                runs["after"].append(fps(s, True, args.rollouts))
            med = {k: statistics.median(v) for k, v in runs.items()}
            out[s["env_id"]] = {**med, "ratio": med["after"] / med["before"], "runs": runs}
            print(
                f"| {s['env_id']} | {med['before']:,.0f} fps | {med['after']:,.0f} fps | "
                f"{med['after'] / med['before']:.1f}x |",
                flush=True,
            )
    if args.json:
        from bench_vector import write_json  # the script's folder is on sys.path

        write_json(args.json, out)


if __name__ == "__main__":
    main()
