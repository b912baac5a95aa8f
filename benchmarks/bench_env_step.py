"""One ``selenv/FIMSelection-v0`` step at N = 1000 candidates vs a naive step.

The env keeps gains and whitened rows by rank-one / triangular updates; the naive step
recomputes the FIM, its Cholesky factor, every gain (batched slogdet) and every whitened row.

    .venv/bin/python benchmarks/bench_env_step.py [--n-candidates 500] [--episodes 20]
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
from scipy.linalg import solve_triangular

import selenv  # noqa: F401  (registers the env)
from selenv.core.information import information_matrix


def naive_step(Q0: np.ndarray, G: np.ndarray, selected: list[int]) -> None:
    A = information_matrix(Q0, G, selected)
    L = np.linalg.cholesky(A)
    Qk = np.einsum("kmi,kmj->kij", G, G)
    np.linalg.slogdet(A + Qk)  # every candidate's gain
    solve_triangular(L, G.reshape(-1, G.shape[2]).T, lower=True)  # whitened rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n-candidates", type=int, default=500, help="per sensor (x2 sensors)")
    ap.add_argument("--budget", type=int, default=50)
    ap.add_argument("--episodes", type=int, default=20)
    a = ap.parse_args()
    results = {}
    for label, wrapped in (("unwrapped", False), ("gym.make (checker+order)", True)):
        env = gym.make("selenv/FIMSelection-v0", n_candidates=a.n_candidates, budget=a.budget)
        target = env if wrapped else env.unwrapped
        times = []
        for ep in range(a.episodes):
            obs, info = target.reset(seed=ep)
            rng = np.random.default_rng(ep)
            done = False
            while not done:
                act = int(rng.choice(np.flatnonzero(info["action_mask"])))
                t = time.perf_counter()
                _obs, _r, done, _, info = target.step(act)
                times.append(time.perf_counter() - t)
        results[label] = np.median(times)
        n = env.unwrapped.n
    prob = env.unwrapped.problem
    sel: list[int] = []
    nt = []
    for j in range(a.budget):
        t = time.perf_counter()
        naive_step(prob.Q0, prob.G, sel)
        nt.append(time.perf_counter() - t)
        sel.append(j)
    t_naive = float(np.median(nt))
    print(f"FIMSelection-v0 step, N = {n} candidates, m = {prob.G.shape[1]}, d = {prob.G.shape[2]}")
    for label, t in results.items():
        print(f"  {label:<28} median {t * 1e6:8.1f} us/step   naive/this = {t_naive / t:5.1f}x")
    print(f"  {'naive recomputation':<28} median {t_naive * 1e6:8.1f} us/step")


if __name__ == "__main__":
    main()
