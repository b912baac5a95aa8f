r"""How close a warm start must be to ``swap``'s result for the swap search to be cheap.

``swap`` on ``FIMSelection-v1`` is greedy's picks polished by best-improvement 1-swaps
(:func:`selenv.agents.fim_solvers.swap_whitened`); each polish round costs one pass over every
(selected, unselected) pair. A learned warm start can only beat ``swap``'s decision time if its
polish needs fewer rounds than greedy's start does. This script measures that: for each seeded
episode it computes ``swap``'s final selection ``S*`` (the polish of greedy's picks,
:func:`selenv.learned.families.fim.polish`), replaces ``r`` of its picks by random others
(an explicit ``numpy.random.Generator`` seeded by ``--perturb-seed``), polishes that start,
and reports the rounds made (the last round is the one that finds no improving swap) and the
final objective against ``swap``'s (W/T/L, ``|Δ| <= 1e-9`` nats a tie). Greedy's own start is
the reference line.

``--policy-steps 0,1,2`` adds the learned starts of the shipped candidate-scoring policy
(``ppo_swap``'s, :meth:`~selenv.learned.families.fim.FIMPolicySwapAgent.policy_picks`): the
policy makes the first ``s`` picks (0: all of them) and greedy completes; and the one-shot
start of the policy's ``K`` highest scores on the first observation. Each is polished the same
way, so the table says how many of ``swap``'s picks a learned start holds and what its polish
costs in rounds.

    .venv/bin/python benchmarks/fim_swap_warm_starts.py --seed 20000 --episodes 30 \
        [--policy-steps 0,1,2,4]

Prints one table; ``--json PATH`` writes the rows (atomically).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from typing import Any

import gymnasium as gym
import numpy as np

import selenv  # noqa: F401  (registers the envs)
from selenv.agents.fim_solvers import greedy_whitened
from selenv.atomic import write_json
from selenv.core.information import logdet_objective
from selenv.learned.families.fim import FIMPolicySwapAgent, polish
from selenv.threads import limit_threads

TIE = 1e-9


def measure(
    seeds: list[int],
    replaced: list[int],
    env_kwargs: dict[str, Any],
    perturb_seed: int,
    policy_steps: list[int] | None = None,
) -> list[dict[str, object]]:
    """One row per start: its picks of ``swap``'s result, mean polish rounds, Δ and W/T/L.

    The starts: greedy's, ``swap``'s result with ``r`` picks replaced, and with
    ``policy_steps`` the shipped policy's (module docstring).
    """
    rng = np.random.default_rng(perturb_seed)
    rows: dict[str, dict[str, list[float]]] = {}
    agents = {s: FIMPolicySwapAgent(starts="policy", policy_steps=s) for s in policy_steps or []}

    def add(name: str, rounds: int, diff: float, kept: int) -> None:
        row = rows.setdefault(name, {"rounds": [], "diff": [], "kept": []})
        row["rounds"].append(rounds)
        row["diff"].append(diff)
        row["kept"].append(kept)

    for seed in seeds:
        env = gym.make("selenv/FIMSelection-v1", **env_kwargs)
        obs, info = env.reset(seed=seed)
        state = env.unwrapped.state  # type: ignore[attr-defined]
        prior, G = state.information, np.asarray(state.G)
        budget = int(env.unwrapped.budget_left)  # type: ignore[attr-defined]
        greedy = np.array(greedy_whitened(prior, G, budget).indices, dtype=np.intp)
        best, rounds = polish(prior, G, greedy.copy())
        value = logdet_objective(prior, G, best)
        add("greedy", rounds, 0.0, len(set(greedy.tolist()) & set(best.tolist())))
        others = np.setdiff1d(np.arange(G.shape[0]), best)
        for r in replaced:
            start = best.copy()
            slots = rng.choice(budget, size=r, replace=False)
            start[slots] = rng.choice(others, size=r, replace=False)
            sel, n = polish(prior, G, start)
            gap = logdet_objective(prior, G, sel) - value
            add(f"swap's result, {r} replaced", n, gap, budget - r)
        starts: dict[str, Any] = {}
        for s, agent in agents.items():
            agent.reset(env, seed)
            starts[f"policy start, {s or 'all'} policy picks"] = agent.policy_picks(obs, budget)
        if agents:  # the one-shot start: the policy's K highest scores on the first observation
            policy = next(iter(agents.values())).policy
            assert policy is not None  # built for starts="policy"
            logits = policy.logits(obs, info, backend="numpy")
            starts["policy's K highest first scores"] = np.argsort(-logits, kind="stable")[:budget]
        for name, picks in starts.items():
            start = np.array(picks, dtype=np.intp)
            sel, n = polish(prior, G, start.copy())
            gap = logdet_objective(prior, G, sel) - value
            add(name, n, gap, len(set(start.tolist()) & set(best.tolist())))
        env.close()
    out = []
    for name, row in rows.items():
        diff = np.array(row["diff"])
        out.append(
            {
                "start": name,
                "picks_of_swap_kept": float(np.mean(row["kept"])),
                "rounds_mean": float(np.mean(row["rounds"])),
                "mean_diff_vs_swap": float(diff.mean()),
                "wins": int((diff > TIE).sum()),
                "ties": int((np.abs(diff) <= TIE).sum()),
                "losses": int((diff < -TIE).sum()),
            }
        )
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=20000, help="first episode seed")
    parser.add_argument("--episodes", type=int, default=30, help="seeded episodes")
    parser.add_argument(
        "--replaced", default="0,1,2,3,4", help="comma-separated numbers of picks replaced"
    )
    parser.add_argument("--perturb-seed", type=int, default=0, help="seed of the replacements")
    parser.add_argument(
        "--policy-steps",
        default="",
        help="comma-separated policy picks of the learned starts (0: every pick; default: none)",
    )
    parser.add_argument("--env-kwargs", default="{}", help="JSON keywords of the env")
    parser.add_argument("--json", default=None, help="write the rows to this path")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    try:
        replaced = [int(x) for x in args.replaced.split(",") if x.strip()]
        policy_steps = [int(x) for x in args.policy_steps.split(",") if x.strip()]
        env_kwargs = json.loads(args.env_kwargs)
    except ValueError as exc:
        parser.error(f"--replaced / --env-kwargs: {exc}")
    if not isinstance(env_kwargs, dict):
        parser.error("--env-kwargs must be a JSON object")
    if any(s < 0 for s in policy_steps):
        parser.error(f"--policy-steps must be ints >= 0, got {args.policy_steps!r}")
    seeds = list(range(args.seed, args.seed + args.episodes))
    with limit_threads(1):
        rows = measure(seeds, replaced, env_kwargs, args.perturb_seed, policy_steps)
    print(f"{'start':<32} {'swap picks kept':>15} {'rounds':>7} {'mean Δ vs swap':>15}  W/T/L")
    for row in rows:
        print(
            f"{row['start']:<32} {row['picks_of_swap_kept']:>15.1f} {row['rounds_mean']:>7.1f} "
            f"{row['mean_diff_vs_swap']:>+15.1e}  {row['wins']}/{row['ties']}/{row['losses']}"
        )
    if args.json:
        command = shlex.join([sys.executable, *sys.argv])
        write_json(args.json, {"command": command, "seeds": seeds, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
