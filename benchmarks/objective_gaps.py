"""Greedy (and swap) gap to the brute-force optimum for each selection objective.

For log det (D-optimal, Kirchner et al. 2020 eq. 5/9), trace (A-optimal, eq. 6) and max_eig
(E-optimal, eq. 7), on small instances of ``selenv/FIMSelection-v1`` (the env's default preset;
trace / max_eig score the target position ``(x, y)``): per seed, the relative gap
``(OPT - f(alg)) / OPT`` with ``OPT`` from ``brute_force_whitened``. Prints, per objective and
algorithm, the mean relative gap with its 95 % percentile-bootstrap CI over the seeds (the gap
is a per-seed paired difference to the optimum), the worst gap and the fraction of seeds where
the algorithm is optimal (95 % Wilson interval).

    .venv/bin/python benchmarks/objective_gaps.py [--seeds 50] [--n-candidates 7] [--budget 4]
        [--preset NAME]

``N = n_candidates x sensors`` (14 with the default camera + Doppler preset).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

import selenv  # noqa: F401  (registers the envs)
from selenv.agents.fim_solvers import (
    Selection,
    brute_force_whitened,
    greedy_whitened,
    swap_whitened,
)
from selenv.bench.stats import bootstrap_ci

OBJECTIVES = ("logdet", "trace", "max_eig")
GUARANTEE = {
    "logdet": "monotone submodular: greedy >= (1 - 1/e) OPT",
    "trace": "monotone, not submodular: none",
    "max_eig": "monotone, not submodular (not smooth): none",
}
SOLVERS: dict[str, Callable[..., Selection]] = {"greedy": greedy_whitened, "swap": swap_whitened}


def wilson(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """95 % Wilson score interval of a proportion ``k / n``."""
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def gaps(objective: str, args: argparse.Namespace) -> dict[str, np.ndarray]:
    """Relative gaps ``(OPT - f) / OPT`` per solver, ``(seeds,)`` each."""
    kwargs: dict[str, Any] = {"n_candidates": args.n_candidates, "budget": args.budget}
    if args.preset:
        kwargs["preset"] = args.preset
    env = gym.make("selenv/FIMSelection-v1", objective=objective, **kwargs).unwrapped
    out: dict[str, list[float]] = {name: [] for name in SOLVERS}
    for seed in range(args.seeds):
        env.reset(seed=seed)
        Q0, G = env.problem.Q0, env.problem.G
        obj = {} if objective == "logdet" else {"objective": objective, "interest": env.interest}
        opt = brute_force_whitened(Q0, G, args.budget, **obj).objective
        for name, solver in SOLVERS.items():
            val = solver(Q0, G, args.budget, **obj).objective
            out[name].append((opt - val) / opt)
    # |gap| < 1e-12: both values are exact recomputations of the same subset (rounding only)
    return {name: np.where(np.abs(v) < 1e-12, 0.0, v) for name, v in out.items()}


def main(argv: list[str] | None = None) -> None:
    """Print the Markdown table of gaps."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=50)
    p.add_argument("--n-candidates", type=int, default=7)
    p.add_argument("--budget", type=int, default=4)
    p.add_argument("--preset", default=None)
    args = p.parse_args(argv)
    env = gym.make(
        "selenv/FIMSelection-v1",
        n_candidates=args.n_candidates,
        budget=args.budget,
        **({"preset": args.preset} if args.preset else {}),
    ).unwrapped
    print(
        f"FIMSelection-v1 preset={env.config.preset} N={env.n} d={env.d} budget={args.budget} "
        f"seeds=0..{args.seeds - 1}"
    )
    print()
    print(
        "| objective | solver | mean rel. gap [95 % CI] | worst gap | optimal [95 % CI] | "
        "guarantee |"
    )
    print("|---|---|---|---|---|---|")
    for objective in OBJECTIVES:
        for name, g in gaps(objective, args).items():  # g: (seeds,) relative gaps
            lo, hi = bootstrap_ci(g)
            k = int(np.sum(g <= 1e-9))
            wlo, whi = wilson(k, g.size)
            print(
                f"| {objective} | {name} | {100 * g.mean():.3g} % [{100 * lo:.3g}, "
                f"{100 * hi:.3g}] | {100 * g.max():.3g} % | {k}/{g.size} = "
                f"{100 * k / g.size:.0f} % [{100 * wlo:.0f}, {100 * whi:.0f}] | "
                f"{GUARANTEE[objective] if name == 'greedy' else 'swap >= greedy'} |"
            )


if __name__ == "__main__":
    main()
