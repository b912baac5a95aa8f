"""Train one shared MaskablePPO policy for every agent of ``selenv.multiagent.fim_selection_v0``.

Multi-agent FIM selection (Kirchner et al. 2020, Example 3: two agents with camera + Doppler
pools). The PettingZoo -> SB3 path is :class:`selenv.learned.rl.marl.SharedPolicyEnv`: the parallel
env is played turn by turn, each Gymnasium step being one agent's pick, so a single
candidate-scoring policy acts for all agents (parameter sharing) and the return is the team's
log-det gain. Trained in ``mode="cooperative"`` (agents take turns and see the shared FIM);
evaluated against cooperative greedy and independent greedy (Algorithm 1 per agent, no
communication) on held-out seeds, in both modes.

    python -m selenv.train.train_fim_marl   # -> checkpoints/fim_marl_ppo.zip
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from selenv.agents.fim import CooperativeGreedyPolicy
from selenv.learned.config import parse_config
from selenv.learned.rl.marl import SharedPolicyEnv
from selenv.learned.rl.safe_load import load_policy
from selenv.learned.rl.training import PPOConfig, train
from selenv.multiagent import fim_selection_v0

ENV_ID = "selenv.multiagent.fim_selection_v0"


@dataclass
class Config(PPOConfig):
    """Defaults of the shipped run."""

    env_kwargs: str = json.dumps({"preset": "example3", "n_candidates": 50, "budgets": 5})
    mode: str = "cooperative"  # the mode the shared policy is trained in
    total_timesteps: int = 100_000
    out: str = "checkpoints/fim_marl_ppo.zip"
    eval_episodes: int = 50
    eval_only: bool = False  # skip training: evaluate the checkpoint at --out


def play(policy: Any, kwargs: dict[str, Any], mode: str, seed: int) -> float:
    """Final fusion-centre objective of one episode; ``policy`` is a model or greedy."""
    penv = fim_selection_v0.parallel_env(mode=mode, **kwargs)
    if isinstance(policy, CooperativeGreedyPolicy):
        obs, infos = penv.reset(seed=seed)
        while penv.agents:
            obs, _, _, _, infos = penv.step(policy.act(obs, penv.agents))
        return float(next(iter(infos.values()))["objective"])
    env = SharedPolicyEnv(penv)
    o, info = env.reset(seed=seed)
    done = False
    while not done:
        action, _ = policy.predict(o, action_masks=env.action_masks(), deterministic=True)
        o, _, terminated, truncated, info = env.step(int(action))
        done = terminated or truncated
    return float(info["objective"])


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Train the shared policy, save it, compare it with the greedy schemes; return metadata."""
    cfg = parse_config(Config, argv, (__doc__ or "").split("\n")[0])
    kwargs = cfg.kwargs()
    if cfg.eval_only:  # re-evaluate the checkpoint at --out, rewrite its metrics
        meta = json.loads(Path(cfg.out).with_suffix(".json").read_text())
        kwargs = meta["env_kwargs"]  # what the checkpoint was trained on
        return _evaluate(cfg, kwargs, meta)
    meta = train(
        dataclasses.replace(cfg, eval_episodes=0),
        env_id=ENV_ID,
        make_env=lambda: SharedPolicyEnv(fim_selection_v0.parallel_env(mode=cfg.mode, **kwargs)),
        make_eval_env=lambda: SharedPolicyEnv(fim_selection_v0.parallel_env(**kwargs)),
        view="shared_policy_turns",
        tb_name="fim_marl_ppo",
        extra_meta={"marl": {"path": "selenv.learned.rl.marl.SharedPolicyEnv", "mode": cfg.mode}},
    )
    return _evaluate(cfg, kwargs, meta)


def _evaluate(cfg: Config, kwargs: dict[str, Any], meta: dict[str, Any]) -> dict[str, Any]:
    """Final objectives of the shared policy and the greedy schemes on held-out seeds."""
    if cfg.eval_episodes:
        model = load_policy(cfg.out, meta)  # weights only: never unpickles the zip
        seeds = [cfg.eval_seed + e for e in range(cfg.eval_episodes)]
        greedy = CooperativeGreedyPolicy()
        runs = {
            "shared_ppo_cooperative": (model, "cooperative"),
            "shared_ppo_independent": (model, "independent"),
            "cooperative_greedy": (greedy, "cooperative"),
            "independent_greedy": (greedy, "independent"),
        }
        finals = {k: [play(p, kwargs, m, s) for s in seeds] for k, (p, m) in runs.items()}
        meta["metrics"] = {
            "episodes": len(seeds),
            "eval_seeds": [seeds[0], seeds[-1]],
            "mean_final_objective": {k: round(float(np.mean(v)), 4) for k, v in finals.items()},
            "final_objectives": {k: [round(x, 4) for x in v] for k, v in finals.items()},
        }
        Path(cfg.out).with_suffix(".json").write_text(json.dumps(meta, indent=2) + "\n")
        print(json.dumps(meta["metrics"]["mean_final_objective"], indent=2))
    return meta


if __name__ == "__main__":
    main()
