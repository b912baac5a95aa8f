"""Overhead ratio: public ``greedy(Q0, H, R, budget)`` vs a minimal rank-one greedy loop.

Also m = 3 vs m = 2 vector candidates.

Scalar candidates ``H (N, d)``, ``R (N,)``, d = 15, K = 10, N from 200 to 20000. The minimal
loop (:func:`minimal_greedy`) is the floor: whiten by ``H / sqrt(R)``, ``P = Q0^-1``,
``s_k = g_k^T P g_k``, pick the argmax of ``log1p(s)`` among the unselected, Sherman-Morrison
update of ``P`` and ``s``. Vector candidates: greedy with m = 3 rows over m = 2 at N = 5000.

Timings: one process, interleaved rounds (A, B, A, B, ...), median of ``--repeat`` rounds.
``OPENBLAS_NUM_THREADS=1`` is set before numpy is imported: on a loaded 2-core machine the
multi-threaded OpenBLAS makes the tiny triangular solves ~10x slower.

    .venv/bin/python benchmarks/bench_greedy_setup.py [--repeat 61]
"""

from __future__ import annotations

import os

os.environ["OPENBLAS_NUM_THREADS"] = "1"

import argparse
import functools
import statistics
import time
from collections.abc import Callable

import numpy as np

from selenv.agents.fim_solvers import greedy


def minimal_greedy(Q0: np.ndarray, H: np.ndarray, R: np.ndarray, k: int) -> list[int]:
    """The floor: rank-one greedy on scalar candidates in a handful of numpy calls."""
    G = H / np.sqrt(R)[:, None]
    P = np.linalg.inv(Q0)
    s = np.einsum("kd,de,ke->k", G, P, G, optimize=True)
    free = np.ones(len(G), dtype=bool)
    chosen: list[int] = []
    for _ in range(k):
        j = int(np.argmax(np.where(free, np.log1p(s), -np.inf)))
        chosen.append(j)
        free[j] = False
        u = P @ G[j]
        q = float(G[j] @ u)
        P = P - np.outer(u, u) / (1.0 + q)
        c = G @ u
        s = s - c * c / (1.0 + q)
    return chosen


def interleaved(fns: list[Callable[[], object]], repeat: int) -> list[float]:
    """Median seconds of each function over ``repeat`` interleaved rounds."""
    ts: list[list[float]] = [[] for _ in fns]
    for _ in range(repeat):
        for i, fn in enumerate(fns):
            t = time.perf_counter()
            fn()
            ts[i].append(time.perf_counter() - t)
    return [statistics.median(t) for t in ts]


def problem(
    n: int, d: int, m: int | None, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``Q0``, ``H`` and ``R``: scalar candidates (``m=None``) or ``m``-row blocks."""
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(d, d))
    Q0 = M @ M.T / d + 0.1 * np.eye(d)
    if m is None:
        return Q0, rng.normal(size=(n, d)), rng.uniform(0.5, 2.0, size=n)
    A = rng.normal(size=(n, m, m))
    return Q0, rng.normal(size=(n, m, d)), A @ A.transpose(0, 2, 1) + 0.5 * np.eye(m)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--d", type=int, default=15)
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=61)
    ap.add_argument("--sizes", type=int, nargs="*", default=[200, 500, 2000, 5000, 20000])
    a = ap.parse_args()
    print(f"public greedy vs minimal rank-one loop, scalar candidates, d={a.d}, K={a.k}")
    print(f"{'N':>7}{'public ms':>11}{'minimal ms':>12}{'ratio':>8}  same picks")
    for n in a.sizes:
        Q0, H, R = problem(n, a.d, None)
        rep = a.repeat if n <= 5000 else max(5, a.repeat // 3)
        fns: list[Callable[[], object]] = [
            functools.partial(greedy, Q0, H, R, a.k),
            functools.partial(minimal_greedy, Q0, H, R, a.k),
        ]
        t_pub, t_min = interleaved(fns, rep)
        same = list(greedy(Q0, H, R, a.k).indices) == minimal_greedy(Q0, H, R, a.k)
        print(f"{n:>7}{t_pub * 1e3:>11.3f}{t_min * 1e3:>12.3f}{t_pub / t_min:>7.2f}x  {same}")
    n = 5000
    p2, p3 = problem(n, a.d, 2), problem(n, a.d, 3)
    t2, t3 = interleaved([lambda: greedy(*p2, a.k), lambda: greedy(*p3, a.k)], a.repeat // 2)
    print(
        f"vector candidates N={n}: m=2 {t2 * 1e3:.2f} ms, m=3 {t3 * 1e3:.2f} ms, "
        f"m=3 / m=2 = {t3 / t2:.2f}x"
    )


if __name__ == "__main__":
    main()
