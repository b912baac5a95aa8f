r"""Decision time of several agents on one env, in interleaved rounds, as ratios to a baseline.

Each round plays the same seeded episodes with every agent (the order rotates from round to
round) and times only ``agent.act``; the figure per agent is the median over rounds of its mean
seconds per decision, and the ratio is taken to the baseline's median. One BLAS and one torch
thread (as in ``selenv bench``).

    .venv/bin/python benchmarks/bench_decision_time.py --env-kwargs '{"n_candidates": 500}' \
        --agents greedy,ppo:top_m=128,ppo --rounds 7
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import sys
import time
from typing import Any

import gymnasium as gym
import torch  # noqa: F401  (imported first, so limit_threads sets its threads too)

import selenv  # noqa: F401  (registers the envs)
from selenv.agents import make, parse_spec
from selenv.atomic import write_json
from selenv.threads import limit_threads


def play(agent: Any, env: Any, seeds: list[int]) -> tuple[float, int]:
    """Seconds spent in ``agent.act`` and the number of decisions over the episodes ``seeds``."""
    spent, decisions = 0.0, 0
    for seed in seeds:
        obs, info = env.reset(seed=seed)
        agent.reset(env, seed=seed)
        done = False
        while not done:
            t0 = time.perf_counter()
            action = agent.act(obs, info)
            spent += time.perf_counter() - t0
            decisions += 1
            obs, _, term, trunc, info = env.step(action)
            done = term or trunc
    return spent, decisions


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Time the agents; print and return ``{agent: {"ms": median, "ratio": to baseline}}``."""
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    p.add_argument("--env", default="selenv/FIMSelection-v1")
    p.add_argument("--env-kwargs", default="{}")
    p.add_argument("--agents", default="greedy,ppo:top_m=128,ppo")
    p.add_argument("--baseline", default="greedy")
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--episodes", type=int, default=5, help="episodes per agent and round")
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = p.parse_args(argv)
    specs = args.agents.split(",")
    if args.baseline not in specs:
        p.error(f"--baseline {args.baseline!r} is not among --agents")
    kwargs = json.loads(args.env_kwargs)
    seeds = list(range(args.seed, args.seed + args.episodes))
    per: dict[str, list[float]] = {s: [] for s in specs}
    with limit_threads(1, 1):
        agents = {}
        for s in specs:
            name, extra = parse_spec(s)
            agents[s] = make(name, args.env, **extra)
        envs = {s: gym.make(args.env, **kwargs) for s in specs}
        for s in specs:  # warm-up (imports, caches, rebuilt policies)
            play(agents[s], envs[s], seeds[:1])
        for r in range(args.rounds):
            order = specs[r % len(specs) :] + specs[: r % len(specs)]
            for s in order:
                spent, n = play(agents[s], envs[s], seeds)
                per[s].append(spent / n)
    base = statistics.median(per[args.baseline])
    out = {
        s: {"ms": 1e3 * statistics.median(v), "ratio": statistics.median(v) / base}
        for s, v in per.items()
    }
    print(f"{args.env} {kwargs}, {args.rounds} rounds x {args.episodes} episodes")
    for s, v in out.items():
        print(f"  {s:28s} {v['ms']:8.3f} ms per decision   {v['ratio']:5.2f}x {args.baseline}")
    if args.json:
        command = shlex.join(["benchmarks/bench_decision_time.py", *(argv or sys.argv[1:])])
        doc = {
            "env_id": args.env,
            "env_kwargs": kwargs,
            "baseline": args.baseline,
            "rounds": args.rounds,
            "episodes": args.episodes,
            "seed": args.seed,
            "command": command,
            "agents": out,
        }
        write_json(args.json, doc)
    return out


if __name__ == "__main__":
    main()
