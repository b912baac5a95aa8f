"""Receiver clustering (Greiff et al. 2022): one GA generation and a 500-step episode.

Workload of the paper's Sec. IV-A: n = 30 receivers, N_max = 14, N_S = 20, tau = 20.

* ``selenv``: one :meth:`GeneticClustering.generation` on a :class:`ClusterFilterBank` at steady
  state (per-axis filters, new clusters of equal size stacked into one batched Riccati pass,
  unchanged clusters reused, clusters cached per time step), followed by the re-clustering and
  filter step an env step does (timed separately);
* ``per-candidate loop, per-axis``: the same 20 candidates costed one at a time, every cluster
  of every candidate filtered on its own with :func:`riccati_pass` (no stacking, no reuse);
* ``per-candidate loop, paper model``: Algorithm 1 read literally: the global prior composed
  with the selection maps ``M_I`` in the full 6-states-per-receiver model, then every cluster of
  every candidate run through ``kf_predict``/``kf_update`` for tau steps.

Then a full 500-step episode of ``selenv/ReceiverClustering-v0`` with the ``ga`` agent running a
generation every step (N_T = 1).

    .venv/bin/python benchmarks/bench_clustering.py [--generations 100] [--naive 5]
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np

import selenv  # noqa: F401  (registers the env and agents)
from selenv.agents import make as make_agent
from selenv.agents.clustering_ga import GAConfig, GeneticClustering
from selenv.core.kalman import kf_predict, kf_update
from selenv.core.riccati import riccati_pass
from selenv.scenarios.clustering import (
    ClusteringConfig,
    ClusteringProblem,
    axis_to_full,
    clustering_cost,
    make_clustering_problem,
)
from selenv.scenarios.clustering_filters import ClusterFilterBank, cluster_keys
from selenv.scenarios.clustering_labels import canonical_labels, random_feasible_clustering


def naive_full(problem: ClusteringProblem, bank: ClusterFilterBank, cands: np.ndarray) -> list:
    """Algorithm 1 literally, in the paper's full model, one candidate and cluster at a time."""
    tau = bank.history(bank.clusters[0]).shape[0] - 1
    maps = problem.selection_maps(bank.labels)
    P_l = sum(
        Mu.T @ axis_to_full(bank.history(k)[0]) @ Mu
        + Ms.T @ axis_to_full(bank.history(k)[0]) @ Ms / len(maps)
        for k, (Mu, Ms) in zip(bank.clusters, maps, strict=True)
    )
    costs = []
    for labels in cands:
        keys = cluster_keys(canonical_labels(labels))
        posts = []
        for key, (Mu, Ms) in zip(keys, problem.selection_maps(labels), strict=True):
            if key in bank.clusters:  # Algorithm 1, steps 4-5: unchanged cluster kept
                posts.append(axis_to_full(bank.history(key)[-1]))
                continue
            A, Q, C, R = problem.full_model(key)
            P = Mu @ P_l @ Mu.T + Ms @ P_l @ Ms.T
            x = np.zeros(A.shape[0])
            for _ in range(tau):
                x, P = kf_predict(x, P, A, Q)
                P = kf_update(x, P, np.zeros(C.shape[0]), C, R).P
            posts.append(P)
        costs.append(_cost_full(posts, keys))
    return costs


def _cost_full(posts: list[np.ndarray], keys: list[tuple[int, ...]]) -> float:
    J_G = sum(np.trace(P) for P in posts) / sum(P.shape[0] for P in posts)
    pos = [
        [np.trace(P[4 * a : 4 * a + 2, 4 * a : 4 * a + 2]) / 2 for a in range(len(k))]
        for P, k in zip(posts, keys, strict=True)
    ]
    return float(J_G + max(np.mean(p) for p in pos) + max(max(p) for p in pos))


def naive_axis(problem: ClusteringProblem, bank: ClusterFilterBank, cands: np.ndarray) -> list:
    """Per-axis filters but one candidate and one cluster at a time (no stacking, no reuse)."""
    steps = bank.history(bank.clusters[0]).shape[0] - 1
    out = []
    for labels in cands:
        posts = []
        for key in cluster_keys(canonical_labels(labels)):
            if key in bank.clusters:  # Algorithm 1, steps 4-5: unchanged cluster kept
                posts.append(bank.history(key)[-1])
                continue
            F, Q, H = problem.axis_model(key)
            P0 = bank._composed_prior(key)[None]
            posts.append(riccati_pass(P0, F, Q, H, problem.axis_noise(key), steps)[0, -1])
        out.append(clustering_cost(posts).J)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--generations", type=int, default=100)
    ap.add_argument("--naive", type=int, default=5, help="generations timed with the naive ways")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    problem = make_clustering_problem(ClusteringConfig(), rng)
    bank = ClusterFilterBank(problem, random_feasible_clustering(30, 3, rng))
    for _ in range(60):
        bank.step()
    ga = GeneticClustering(bank.evaluate, bank.labels, 3, GAConfig(), rng=rng)
    gen_t, env_t, cands_log = [], [], []
    for _ in range(a.generations):
        t0 = time.perf_counter()
        best, _ = ga.generation()
        t1 = time.perf_counter()
        cands_log.append(ga.population.copy())
        bank.recluster(best)
        bank.step()
        env_t.append(time.perf_counter() - t1)
        gen_t.append(t1 - t0)
    g = float(np.median(gen_t))
    print(f"n = 30, N_max = 14, N_S = 20, tau = 20 ({a.generations} generations, median)")
    print(f"  GA generation (selenv, batched + cached)     {1e3 * g:8.2f} ms")
    print(f"  re-cluster + filter step (env step)          {1e3 * float(np.median(env_t)):8.2f} ms")
    evals = ga.n_evaluations / (ga.n_generations + 1)
    print(f"  cost evaluations per generation              {evals:8.1f}")
    passes = bank.n_cluster_passes / a.generations
    print(f"  cluster forward passes per generation        {passes:8.1f}")
    # the naive ways, on the same candidate sets at the current bank state
    for label, fn in (
        ("per-candidate loop, per-axis", naive_axis),
        ("per-candidate loop, paper model", naive_full),
    ):
        times = []
        for cands in cands_log[-a.naive :]:
            t0 = time.perf_counter()
            costs = fn(problem, bank, cands)
            times.append(time.perf_counter() - t0)
        ref = bank.evaluate(cands)
        agree = np.allclose(costs, ref, rtol=1e-8)
        t = float(np.median(times))
        print(f"  {label:<44} {1e3 * t:8.2f} ms   ratio {t / g:6.1f}x   (same costs: {agree})")
    # a full episode with a generation every step
    env = gym.make("selenv/ReceiverClustering-v0")
    obs, info = env.reset(seed=a.seed)
    agent = make_agent("ga", "selenv/ReceiverClustering-v0")
    agent.reset(env, seed=a.seed)
    t0 = time.perf_counter()
    done = False
    while not done:
        obs, _, term, trunc, info = env.step(agent.act(obs, info))
        done = term or trunc
    wall = time.perf_counter() - t0
    final = info["objective"]
    print(f"500-step episode, GA generation every step: {wall:.2f} s (final J = {final:.4f})")


if __name__ == "__main__":
    main()
