"""Decision time of the ``ppo`` agent: SB3 ``predict`` vs the lean path, next to greedy.

For every env with a shipped checkpoint, plays the same episodes three times and times only
``agent.act`` (the decision, not the env step): the ``ppo`` agent through SB3's ``predict``
(``lean=False``), through :class:`selenv.learned.rl.lean.LeanScorer` (the default), and the env's
greedy heuristic. Single thread (``torch.set_num_threads(1)``, as in the bench).

    .venv/bin/python benchmarks/bench_policy_inference.py [--decisions 200]
    .venv/bin/python benchmarks/bench_policy_inference.py --env selenv/FIMSelection-v1 \
        --kwargs '{"n_candidates": 500}'
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th

import selenv  # noqa: F401  (registers the envs)
from selenv.agents import make
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, SB3PolicyAgent


def time_agent(agent: Any, env_id: str, kwargs: dict[str, Any], decisions: int) -> float:
    """Median seconds per ``act`` over ``decisions`` decisions of fresh seeded episodes."""
    env = gym.make(env_id, **kwargs)
    times: list[float] = []
    seed = 0
    while len(times) < decisions:
        obs, info = env.reset(seed=seed)
        agent.reset(env, seed=seed)
        done = False
        while not done and len(times) < decisions:
            t0 = time.perf_counter()
            action = agent.act(obs, info)
            times.append(time.perf_counter() - t0)
            obs, _, term, trunc, info = env.step(action)
            done = term or trunc
        seed += 1
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--decisions", type=int, default=200)
    ap.add_argument("--env", default=None, help="one env id (default: every shipped one)")
    ap.add_argument("--kwargs", default="{}", help="env keyword arguments as JSON")
    a = ap.parse_args()
    th.set_num_threads(1)
    kwargs = json.loads(a.kwargs)
    env_ids = [a.env] if a.env else sorted(DEFAULT_CHECKPOINTS)
    print(f"{'env':32s} {'predict':>10s} {'lean':>10s} {'greedy':>10s} {'speed-up':>9s}")
    for env_id in env_ids:
        t_pred = time_agent(SB3PolicyAgent(env_id=env_id, lean=False), env_id, kwargs, a.decisions)
        t_lean = time_agent(SB3PolicyAgent(env_id=env_id), env_id, kwargs, a.decisions)
        t_greedy = time_agent(make("greedy", env_id=env_id), env_id, kwargs, a.decisions)
        print(
            f"{env_id:32s} {t_pred * 1e6:8.0f}us {t_lean * 1e6:8.0f}us {t_greedy * 1e6:8.0f}us "
            f"{t_pred / t_lean:8.1f}x   (lean / greedy {t_lean / t_greedy:.1f}x)"
        )


if __name__ == "__main__":
    main()
