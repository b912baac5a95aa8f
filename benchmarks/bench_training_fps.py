"""MaskablePPO training fps of each family against SB3's PPO on CartPole-v1, in one process.

For each family, the training script's own defaults (``Config()`` of ``train_fim_ppo``,
``train_landmark_ppo``, ``train_cl_ppo``, ``train_clustering_ppo``: env keywords, candidate
view, ``n_envs``, ``n_steps``, ``batch_size``, ``n_epochs``, network), up to four contenders:

* **dummy**: ``DummyVecEnv`` over ``n_envs`` ``gymnasium.make`` envs in their candidate view,
  and for ReceiverClustering the per-edit MLP scorer (``--scorer mlp``);
* **native**: the script's default, ``vec_env="native"`` (``NativeVecEnv`` over
  ``gymnasium.make_vec``) and for ReceiverClustering the factorised edit scorer;
* **compiled**: native with the scorer compiled (``--compile``,
  :func:`selenv.learned.rl.compiled.compile_policy`);
* **CartPole**: SB3's ``PPO("MlpPolicy")`` on ``make_vec_env("CartPole-v1", n_envs)`` with the
  same ``n_envs``, ``n_steps``, ``batch_size`` and ``n_epochs`` (the anchor). ``--n-envs`` /
``--n-steps`` replace the scripts' rollout layout, for every contender alike.

Each model is built and warmed up by one untimed rollout and update (TorchInductor compiles
there); then the rounds are interleaved: each times one ``learn()`` of ``--rollouts`` rollouts
per contender, continuing the same model. fps = environment steps / wall seconds of
``learn()`` (rollout collection and the PPO update), median over the rounds; a ratio is the
median of the per-round ratios. One BLAS and one torch thread.

    .venv/bin/python benchmarks/bench_training_fps.py [--rounds 3] [--rollouts 1]
        [--families fim landmarks cl clustering] [--contenders dummy native compiled]
        [--shortlist M] [--n-envs B --n-steps T] [--json PATH]
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
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

import selenv  # noqa: F401
from selenv.learned.rl.candidate_policy import CandidateScorer, make_ppo
from selenv.learned.rl.compiled import compile_policy
from selenv.learned.rl.vec_env import make_native_vec_env
from selenv.learned.rl.views import CandidateViewWrapper, view_for
from selenv.threads import limit_threads

FAMILIES = {
    "fim": ("selenv.train.train_fim_ppo", None),
    "landmarks": ("selenv.train.train_landmark_ppo", None),
    "cl": ("selenv.train.train_cl_ppo", "view"),
    "clustering": ("selenv.train.train_clustering_ppo", "clustering_edits"),
}


def _setup(family: str, layout: dict[str, int] | None = None) -> dict[str, Any]:
    """The script's defaults (``layout``: ``n_envs`` / ``n_steps`` overriding them)."""
    module_name, view_spec = FAMILIES[family]
    mod = importlib.import_module(module_name)
    cfg = mod.Config(**(layout or {}))
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


def _extractor(s: dict[str, Any], native: bool) -> tuple[type[CandidateScorer], dict[str, Any]]:
    cfg = s["cfg"]
    if s["mod"].__name__.endswith("train_clustering_ppo"):
        from selenv.learned.families.clustering_edits import scorer_policy_kwargs

        return scorer_policy_kwargs(cfg.scorer if native else "mlp", cfg.edit_rank)
    return CandidateScorer, {}


class Contender:
    """One model, built and warmed up; :meth:`fps` times one ``learn()`` that continues it."""

    def __init__(self, s: dict[str, Any], kind: str, shortlist: int = 0) -> None:
        cfg = s["cfg"]
        self.steps_per_rollout = cfg.n_envs * cfg.n_steps
        if kind == "cartpole":
            self.venv = make_vec_env("CartPole-v1", n_envs=cfg.n_envs, seed=cfg.seed)
            self.model = PPO(
                "MlpPolicy", self.venv, n_steps=cfg.n_steps, batch_size=cfg.batch_size,
                n_epochs=cfg.n_epochs, seed=cfg.seed, device="cpu",
            )  # fmt: skip
        else:
            self.venv, self.model = _family_model(s, kind, shortlist)
        self.model.learn(self.steps_per_rollout)  # warm-up (and TorchInductor's compile)

    def fps(self, rollouts: int) -> float:
        """Environment steps per second of one ``learn()`` of ``rollouts`` rollouts."""
        before = self.model.num_timesteps
        t = time.perf_counter()
        self.model.learn(rollouts * self.steps_per_rollout, reset_num_timesteps=False)
        return (self.model.num_timesteps - before) / (time.perf_counter() - t)

    def close(self) -> None:  # noqa: D102
        self.venv.close()


def _family_model(s: dict[str, Any], kind: str, shortlist: int = 0) -> tuple[Any, Any]:
    cfg = s["cfg"]
    native = kind in ("native", "compiled")
    venv = (
        make_native_vec_env(
            s["env_id"], cfg.n_envs, seed=cfg.seed, view=s["view"], env_kwargs=s["kwargs"]
        )
        if native
        else _dummy(s)
    )
    extractor, extra = _extractor(s, native)
    if shortlist and native and extractor is CandidateScorer:
        extra = {**extra, "shortlist": shortlist}
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
    if kind == "compiled":
        compile_policy(model.policy)
    return venv, model


KINDS = ("dummy", "native", "compiled")


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--rollouts", type=int, default=1, help="rollouts per learn() call")
    ap.add_argument("--families", nargs="*", default=list(FAMILIES), choices=list(FAMILIES))
    ap.add_argument("--contenders", nargs="*", default=list(KINDS), choices=list(KINDS))
    ap.add_argument(
        "--shortlist", type=int, default=0,
        help="m > 0: the native and compiled contenders score the m best-gain candidates only",
    )  # fmt: skip
    ap.add_argument("--n-envs", type=int, help="rollout layout (default: the script's)")
    ap.add_argument("--n-steps", type=int, help="rollout layout (default: the script's)")
    ap.add_argument("--json", help="write the figures to this JSON file (atomically)")
    args = ap.parse_args()
    layout = {k: v for k, v in (("n_envs", args.n_envs), ("n_steps", args.n_steps)) if v}
    warnings.simplefilter("ignore")
    out: dict[str, Any] = {}
    kinds = [k for k in KINDS if k in args.contenders]
    head = [*(f"{k} fps" for k in kinds), "CartPole PPO fps", *(f"{k} / CartPole" for k in kinds)]
    if "compiled" in kinds and "native" in kinds:
        head.append("compiled / native")
    print("| env (script defaults) | " + " | ".join(head) + " |")
    print("|---|" + "---|" * len(head))
    with limit_threads(blas=1, torch=1):
        torch.set_num_threads(1)
        for family in args.families:
            s = _setup(family, layout)
            contenders = {k: Contender(s, k, args.shortlist) for k in [*kinds, "cartpole"]}
            runs: dict[str, list[float]] = {k: [] for k in contenders}
            for _ in range(args.rounds):
                for k, c in contenders.items():
                    runs[k].append(c.fps(args.rollouts))
            for c in contenders.values():
                c.close()
            med = {k: statistics.median(v) for k, v in runs.items()}
            ratios = {f"{k}_vs_cartpole": _ratio(runs[k], runs["cartpole"]) for k in kinds}
            if "compiled" in kinds and "native" in kinds:
                ratios["compiled_vs_native"] = _ratio(runs["compiled"], runs["native"])
            out[s["env_id"]] = {"fps": med, **ratios, "runs": runs}
            cells = [*(f"{med[k]:,.0f}" for k in kinds), f"{med['cartpole']:,.0f}"]
            cells += [f"{v:.3f}x" if "cartpole" in r else f"{v:.2f}x" for r, v in ratios.items()]
            print(f"| {s['env_id']} | " + " | ".join(cells) + " |", flush=True)
    if args.json:
        from bench_vector import write_json  # the script's folder is on sys.path

        write_json(args.json, out)


def _ratio(num: list[float], den: list[float]) -> float:
    """Median of the per-round ratios."""
    return statistics.median(a / b for a, b in zip(num, den, strict=True))


if __name__ == "__main__":
    main()
