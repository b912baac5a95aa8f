"""Thread settings: the public solvers and the ppo agent with the library's default threads.

A user does not set ``OPENBLAS_NUM_THREADS``. This measures, in one process with interleaved
rounds, ``greedy`` (``d = 15``, ``K = 10`` of ``N`` scalar candidates) as shipped (wrapped in
:func:`selenv.threads.small_blas`) against the same function without the wrapper at the
library's default thread count, and against a minimal rank-one greedy loop run with one
thread; and the ``ppo`` agent's decision on ``FIMSelection-v1`` with torch's default threads
against one thread (what ``selenv bench`` now uses). Medians of ``--rounds`` rounds.

    .venv/bin/python benchmarks/bench_threads.py [--rounds 15] [--n 200 2000]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
import warnings

import numpy as np

from selenv.agents.fim_solvers import greedy
from selenv.threads import blas_threads, small_blas


def rank_one_greedy(Q0: np.ndarray, G: np.ndarray, k: int) -> list[int]:
    """The minimal greedy: Sherman-Morrison on ``P`` and the gains of scalar candidates."""
    P = np.linalg.inv(Q0)
    g = G[:, 0, :]
    chosen: list[int] = []
    q = np.einsum("nd,de,ne->n", g, P, g)
    for _ in range(k):
        q[chosen] = -np.inf
        j = int(np.argmax(q))
        chosen.append(j)
        u = P @ g[j]
        P = P - np.outer(u, u) / (1.0 + g[j] @ u)
        c = g @ u
        q = q - c * c / (1.0 + g[j] @ u)
        q[chosen] = -np.inf
    return chosen


def timed(fn, *args) -> float:
    t = time.perf_counter()
    fn(*args)
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--n", type=int, nargs="+", default=[200, 2000])
    args = ap.parse_args()
    default = blas_threads()
    print(f"BLAS threads by default: {default}; cores: {os.cpu_count()}")
    print(
        "| N | greedy, default threads, unwrapped | greedy as shipped | minimal loop, 1 "
        "thread | unwrapped / shipped | shipped / minimal |"
    )
    print("|---|---|---|---|---|---|")
    rng = np.random.default_rng(0)
    raw = greedy.__wrapped__  # type: ignore[attr-defined]
    for n in args.n:
        Q0 = np.eye(15)
        H = rng.normal(size=(n, 1, 15))
        R = np.ones((n, 1, 1))
        G = H.copy()
        ts: dict[str, list[float]] = {"raw": [], "shipped": [], "minimal": []}
        for _ in range(args.rounds):
            ts["raw"].append(timed(raw, Q0, H, R, 10))
            ts["shipped"].append(timed(greedy, Q0, H, R, 10))
            with small_blas():
                ts["minimal"].append(timed(rank_one_greedy, Q0, G, 10))
        m = {k: statistics.median(v) * 1e3 for k, v in ts.items()}
        print(
            f"| {n} | {m['raw']:.3f} ms | {m['shipped']:.3f} ms | {m['minimal']:.3f} ms | "
            f"{m['raw'] / m['shipped']:.1f}x | {m['shipped'] / m['minimal']:.2f}x |"
        )

    import gymnasium as gym
    import torch

    import selenv  # noqa: F401
    from selenv.agents import make

    warnings.simplefilter("ignore")
    env = gym.make("selenv/FIMSelection-v1")
    agent = make("ppo", "selenv/FIMSelection-v1")
    obs, info = env.reset(seed=0)
    agent.reset(env, seed=0)
    default_torch = torch.get_num_threads()
    td: dict[int, list[float]] = {default_torch: [], 1: []}
    for _ in range(args.rounds):
        for n_threads in td:
            torch.set_num_threads(n_threads)
            t = time.perf_counter()
            for _ in range(10):
                agent.act(obs, info)
            td[n_threads].append((time.perf_counter() - t) / 10)
    torch.set_num_threads(default_torch)
    md = {k: statistics.median(v) * 1e3 for k, v in td.items()}
    print(
        f"\nppo decision on FIMSelection-v1: torch default ({default_torch} threads) "
        f"{md[default_torch]:.3f} ms, 1 thread {md[1]:.3f} ms, "
        f"ratio {md[default_torch] / md[1]:.1f}x"
    )


if __name__ == "__main__":
    main()
