r"""How far from optimal: every FIMSelection agent against the exact solver's certified bound.

For each seed, the episode's instance of ``selenv/FIMSelection-v1`` (defaults unless
``--env-kwargs``) is solved by :func:`~selenv.agents.fim_exact.branch_and_bound_whitened`
(``--time-limit`` seconds or ``--node-limit`` nodes): its incumbent (the best subset known) and
its certified upper bound on the optimum. The agents (``--agents``, default ``greedy``, ``swap``
and ``learned``) play the same episode; for each, per seed:

* ``gap = (bound - f) / |bound|``: certified, the true gap to the optimum is at most this;
* ``gap to best = (best - f) / |best|``: to the best subset known, at most the true gap.

Both coincide on the seeds solved exactly. Also the root relaxation bound alone (its tightness
``(relaxation - best) / |best|``). Prints a Markdown table (mean gap with its 95 % bootstrap CI
over the seeds, the worst seed, the seeds at gap 0, decision ms) and writes every per-seed
number to ``--json`` (atomically).

    .venv/bin/python benchmarks/fim_exact_gaps.py --seed 30000 --episodes 30 --time-limit 60 \\
        --json docs/bench/fim_exact_gaps.json --store /tmp/fim_exact_gaps

The time limit makes the bound depend on the machine's speed (the node limit does not).
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import gymnasium as gym
import numpy as np
from tqdm import tqdm

import selenv  # noqa: F401  (registers the envs and agents)
from selenv.agents import make as make_agent
from selenv.agents.fim_exact import branch_and_bound_whitened, relaxation_bound_whitened
from selenv.atomic import write_json
from selenv.bench.stats import bootstrap_ci
from selenv.core.information import logdet_objective
from selenv.parallel.store import ResultStore, task_key

ENV_ID = "selenv/FIMSelection-v1"


def play(agent_name: str, env: gym.Env[Any, Any], seed: int) -> tuple[np.ndarray, float]:
    """The subset ``agent_name`` selects on the episode ``seed`` and its decision seconds."""
    env.reset(seed=seed)
    agent = make_agent(agent_name, ENV_ID)
    agent.reset(env, seed=seed)
    obs, info = env.reset(seed=seed)
    spent, done = 0.0, False
    while not done:
        t0 = time.perf_counter()
        action = agent.act(obs, info)
        spent += time.perf_counter() - t0
        obs, _, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    return np.flatnonzero(env.unwrapped.state.selected), spent  # type: ignore[attr-defined]


def solve_seed(args: argparse.Namespace, env: gym.Env[Any, Any], seed: int) -> dict[str, Any]:
    """One seed's record: the exact solver's best and bound, the relaxation, each agent."""
    env.reset(seed=seed)
    state = env.unwrapped.state  # type: ignore[attr-defined]
    Q0, G = state.information.copy(), state.G.copy()
    budget = int(env.unwrapped.budget_left)  # type: ignore[attr-defined]
    t0 = time.perf_counter()
    relax = relaxation_bound_whitened(Q0, G, budget)
    relax_s = time.perf_counter() - t0
    exact = branch_and_bound_whitened(
        Q0, G, budget, node_limit=args.node_limit, time_limit=args.time_limit
    )
    row: dict[str, Any] = {
        "seed": seed,
        "best": exact.objective,
        "bound": exact.upper_bound,
        "optimal": exact.optimal,
        "nodes": exact.nodes,
        "exact_seconds": exact.seconds,
        "relaxation": relax.bound,
        "relaxation_seconds": relax_s,
        "agents": {},
    }
    for name in args.agents:
        picks, spent = play(name, env, seed)
        f = logdet_objective(Q0, G, picks.tolist())
        row["agents"][name] = {"objective": f, "decision_seconds": spent}
    return row


def _to_arrays(row: dict[str, Any], agents: list[str]) -> dict[str, np.ndarray]:
    keys = ("best", "bound", "optimal", "nodes", "exact_seconds", "relaxation",
            "relaxation_seconds")  # fmt: skip
    out = {k: np.asarray(float(row[k])) for k in keys}
    out["objectives"] = np.array([row["agents"][a]["objective"] for a in agents])
    out["decision_seconds"] = np.array([row["agents"][a]["decision_seconds"] for a in agents])
    return out


def _from_arrays(seed: int, arr: dict[str, np.ndarray], agents: list[str]) -> dict[str, Any]:
    row: dict[str, Any] = {k: float(v) for k, v in arr.items() if v.ndim == 0}
    row["seed"], row["optimal"], row["nodes"] = seed, bool(row["optimal"]), int(row["nodes"])
    row["agents"] = {
        a: {"objective": float(arr["objectives"][i]),
            "decision_seconds": float(arr["decision_seconds"][i])}
        for i, a in enumerate(agents)
    }  # fmt: skip
    return row


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Solve and play every seed (resuming from ``--store``); the per-seed records."""
    env = gym.make(ENV_ID, **args.env_kwargs)
    store = None if args.store is None else ResultStore(args.store)
    rows = []
    for seed in tqdm(range(args.seed, args.seed + args.episodes), desc="seeds", unit="seed"):
        task = {"seed": seed, "env_kwargs": args.env_kwargs, "agents": args.agents,
                "time_limit": args.time_limit, "node_limit": args.node_limit}  # fmt: skip
        key = task_key(task)
        if store is not None and key in store:
            rows.append(_from_arrays(seed, store.get(key), args.agents))
            continue
        t0 = time.perf_counter()
        row = solve_seed(args, env, seed)
        if store is not None:
            store.write({key: _to_arrays(row, args.agents)}, time.perf_counter() - t0)
        rows.append(row)
    return {"env_id": ENV_ID, "env_kwargs": args.env_kwargs, "config": vars(args), "rows": rows}


def summarise(result: dict[str, Any]) -> str:
    """The Markdown tables of a :func:`run` result."""
    rows = result["rows"]
    best = np.array([r["best"] for r in rows])
    bound = np.array([r["bound"] for r in rows])
    relax = np.array([r["relaxation"] for r in rows])
    cert = (bound - best) / np.abs(bound)
    n = len(rows)
    lines = [
        f"{n} seeds from {rows[0]['seed']}; exact solver: "
        f"{sum(r['optimal'] for r in rows)} solved to optimality, certified gap <= 0.1 % on "
        f"{int(np.sum(cert <= 1e-3))}, median {np.median(cert) * 100:.3f} %, worst "
        f"{cert.max() * 100:.3f} %; median {np.median([r['nodes'] for r in rows]):.0f} nodes, "
        f"{np.median([r['exact_seconds'] for r in rows]):.1f} s.",
        f"Root relaxation bound above the best known subset: mean "
        f"{np.mean((relax - best) / np.abs(best)) * 100:.3f} % "
        f"({np.mean(relax - best):.4f} nats), "
        f"{np.median([r['relaxation_seconds'] for r in rows]) * 1e3:.0f} ms.",
        "",
        "| agent | objective (mean) | gap, certified (mean [95 % CI]) | worst | gap to best known "
        "(mean) | seeds at the best known | ms per episode |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name in result["config"]["agents"]:
        f = np.array([r["agents"][name]["objective"] for r in rows])
        gap = (bound - f) / np.abs(bound)
        lo, hi = bootstrap_ci(gap)
        to_best = (best - f) / np.abs(best)
        at_best = int(np.sum(to_best <= 1e-9))
        ms = np.mean([r["agents"][name]["decision_seconds"] for r in rows]) * 1e3
        lines.append(
            f"| `{name}` | {f.mean():.4f} | {gap.mean() * 100:.3f} % [{lo * 100:.3f}, "
            f"{hi * 100:.3f}] | {gap.max() * 100:.3f} % | {to_best.mean() * 100:.4f} % | "
            f"{at_best}/{n} | {ms:.1f} |"
        )
    lines.append(
        f"| exact solver (best known) | {best.mean():.4f} | {cert.mean() * 100:.3f} % | "
        f"{cert.max() * 100:.3f} % | 0 | {n}/{n} | "
        f"{np.mean([r['exact_seconds'] for r in rows]) * 1e3:.0f} |"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Parse, run, print and (optionally) write the JSON."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=30000)
    p.add_argument("--episodes", type=int, default=30)
    p.add_argument("--time-limit", type=float, default=60.0, help="seconds per instance")
    p.add_argument("--node-limit", type=int, default=10**9, help="nodes per instance")
    p.add_argument("--agents", default="greedy,swap,learned", help="comma-separated")
    p.add_argument("--env-kwargs", type=json.loads, default={}, help="JSON object")
    p.add_argument("--json", default=None, help="write the per-seed numbers here")
    p.add_argument("--store", default=None, help="keep each finished seed here and resume")
    args = p.parse_args(argv)
    args.agents = [a for a in args.agents.split(",") if a]
    if args.episodes < 1:
        p.error("--episodes: expected >= 1")
    result = run(args)
    print(summarise(result))
    if args.json:
        write_json(args.json, result)
    return result


if __name__ == "__main__":
    main()
