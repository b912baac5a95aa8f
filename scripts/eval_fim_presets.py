r"""One FIMSelection-v1 policy on every Kirchner preset and budget, against greedy and random.

For each preset (its default pool: 100 candidates per sensor and agent, N = 100..400) and each
budget, ``selenv bench`` plays ``--agents`` on the same held-out seeds; the table gives, per
cell, the policy's paired difference to greedy (bootstrap 95 % CI, W/T/L), its normalised score
``(R - R_random) / (R_best - R_random)`` and its decision time relative to greedy's. An agent
that cannot play a preset (the shipped ``ppo`` is tied to ``d = 7``) is listed as refused.

    .venv/bin/python scripts/eval_fim_presets.py                  # ppo, 30 seeds
    .venv/bin/python scripts/eval_fim_presets.py --agent ppo:runs/general/policy.zip \
        --episodes 10 --json runs/eval.json

Writes the JSON atomically (``--json``) and prints a Markdown table; exit 2 on a usage error.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from selenv.atomic import write_json
from selenv.bench import run_bench

ENV_ID = "selenv/FIMSelection-v1"
PRESETS = (
    "example1",
    "example2",
    "example3",
    "example1_moving",
    "example2_moving",
    "example3_moving",
)
BUDGETS = (5, 10, 15, 20)


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line."""
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    p.add_argument("--agent", default="ppo", help="the policy's agent spec")
    p.add_argument("--episodes", type=_positive, default=30, help="held-out seeds per cell")
    p.add_argument("--seed", type=int, default=1000, help="first seed (then +1, +2, ...)")
    p.add_argument("--presets", default=",".join(PRESETS), help="comma-separated presets")
    p.add_argument("--budgets", default=",".join(map(str, BUDGETS)), help="comma-separated budgets")
    p.add_argument("--env-kwargs", default="{}", help="JSON object added to every cell")
    p.add_argument("--json", default="", help="write every cell's statistics here")
    args = p.parse_args(argv)
    try:
        args.extra = json.loads(args.env_kwargs)
        args.budget_list = [int(b) for b in args.budgets.split(",")]
    except ValueError as exc:
        p.error(f"--env-kwargs / --budgets: {exc}")
    if not isinstance(args.extra, dict):
        p.error("--env-kwargs must be a JSON object")
    args.preset_list = args.presets.split(",")
    unknown = sorted(set(args.preset_list) - set(PRESETS))
    if unknown:
        p.error(f"--presets: unknown {unknown}; known: {', '.join(PRESETS)}")
    return args


def cell(preset: str, budget: int, args: argparse.Namespace) -> dict[str, Any]:
    """One preset and budget: the policy, greedy and random on the same seeds."""
    kwargs = {"preset": preset, "budget": budget, **args.extra}
    res = run_bench(
        ENV_ID,
        [args.agent, "greedy", "random"],
        episodes=args.episodes,
        seed=args.seed,
        env_kwargs=kwargs,
        progress=False,
        baseline="greedy",
        skip_inapplicable=True,
    )
    agent = res.agents[args.agent]
    out: dict[str, Any] = {"preset": preset, "budget": budget, "env_kwargs": kwargs}
    if agent.skipped is not None:
        return {**out, "refused": agent.skipped}
    paired = res.paired(args.agent)
    assert paired is not None  # the agent ran, greedy is the baseline
    greedy = res.agents["greedy"]
    return {
        **out,
        "mean_return": agent.mean_return,
        "greedy_mean_return": greedy.mean_return,
        "random_mean_return": res.agents["random"].mean_return,
        "vs_greedy": {
            "mean_diff": paired.mean_diff,
            "ci95": list(paired.ci95),
            "wins": paired.wins,
            "ties": paired.ties,
            "losses": paired.losses,
        },
        "normalized_score": res.normalized_score(args.agent),
        "greedy_normalized_score": res.normalized_score("greedy"),
        "decision_ms": 1e3 * agent.decision_seconds / max(agent.decisions, 1),
        "greedy_decision_ms": 1e3 * greedy.decision_seconds / max(greedy.decisions, 1),
        # mean (bound - return) / |bound| over the seeds with its 95 % CI, None without a bound
        "bound_method": res.bound_method,
        "gap_to_bound": _gap(res.gap_to_bound(args.agent)),
        "greedy_gap_to_bound": _gap(res.gap_to_bound("greedy")),
    }


def _gap(got: tuple[float, float, float] | None) -> dict[str, Any] | None:
    return None if got is None else {"mean": got[0], "ci95": [got[1], got[2]]}


def _pct(gap: dict[str, Any] | None) -> str:
    if gap is None:
        return "-"
    pct = 100 * gap["mean"]
    return f"{0.0 if abs(pct) < 5e-4 else pct:.3f} %"  # a rounding-level -1e-16 reads 0.000


def table(cells: list[dict[str, Any]], agent: str) -> str:
    """The Markdown table of ``cells``."""
    lines = [
        f"| preset | budget | {agent} - greedy [95 % CI] | W/T/L | norm. score | time / greedy "
        f"| gap to bound: {agent} | greedy |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for c in cells:
        if "refused" in c:
            lines.append(f"| {c['preset']} | {c['budget']} | refused: {c['refused']} | | | | | |")
            continue
        v = c["vs_greedy"]
        lo, hi = v["ci95"]
        lines.append(
            f"| {c['preset']} | {c['budget']} | {v['mean_diff']:+.4f} [{lo:+.4f}, {hi:+.4f}] "
            f"| {v['wins']}/{v['ties']}/{v['losses']} | {c['normalized_score']:.4f} "
            f"| {c['decision_ms'] / c['greedy_decision_ms']:.1f}x "
            f"| {_pct(c.get('gap_to_bound'))} | {_pct(c.get('greedy_gap_to_bound'))} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run every cell, print the table, write the JSON."""
    args = parse_args(argv)
    cells = []
    for preset in args.preset_list:
        for budget in args.budget_list:
            cells.append(cell(preset, budget, args))
            print(f"{preset} budget {budget} done", file=sys.stderr, flush=True)
    print(table(cells, args.agent))
    if args.json:
        doc = {
            "env_id": ENV_ID,
            "agent": args.agent,
            "episodes": args.episodes,
            "seeds": [args.seed, args.seed + args.episodes - 1],
            "command": "python scripts/eval_fim_presets.py " + " ".join(argv or sys.argv[1:]),
            "cells": cells,
        }
        write_json(args.json, doc)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
