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

Then a full 500-step episode of ``selenv/ReceiverClustering-v1`` with the ``ga`` agent running a
generation every step (N_T = 1).

``--compare``: the GA generation against a straightforward implementation of the same GA
(``benchmarks/clustering_ga_reference.py``: every operator call validated, labels by
``np.unique``, an ``evaluate`` without caches), both variants, in one process with interleaved
rounds (reference, selenv, reference, selenv, ...): each side has its own fork of the same
steady-state bank, runs a generation, then re-clusters and steps its bank as the env does; the
populations are checked equal every round. Prints the median per-generation times and their
ratio.

    .venv/bin/python benchmarks/bench_clustering.py [--generations 100] [--naive 5]
    .venv/bin/python benchmarks/bench_clustering.py --compare [--rounds 300] [--seed 0]

``--env-step``: one ``ReceiverClustering-v1`` step (preset ``paper``, ``gym.make``, the action
keeps the clustering) against one ``gym.make("CartPole-v1")`` step (the same wrappers),
interleaved rounds of 100 / 2000 steps; prints the median per-step times and their ratio.

    .venv/bin/python benchmarks/bench_clustering.py --env-step [--rounds 300]

One BLAS thread: ``OPENBLAS_NUM_THREADS=1`` is set before numpy is imported if it is unset.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: tiny linear algebra

import argparse
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import selenv  # noqa: F401  (registers the env and agents)
from selenv.agents import make as make_agent
from selenv.core.kalman import kf_predict, kf_update
from selenv.core.riccati import riccati_pass
from selenv.families.clustering.filters import ClusterFilterBank, cluster_keys
from selenv.families.clustering.ga import GAConfig, GeneticClustering
from selenv.families.clustering.labels import canonical_labels, random_feasible_clustering
from selenv.families.clustering.scenario import (
    ClusteringConfig,
    ClusteringProblem,
    axis_to_full,
    clustering_cost,
    make_clustering_problem,
)


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


def compare_generation(rounds: int, seed: int, variant: str) -> tuple[float, float]:
    """Median seconds of one GA generation, (reference, now), interleaved; checks equality.

    n = 30, N_max = 14 (at most 3 receivers per cluster), N_S = 20, tau = 20, fixed noise; both
    sides start from forks of one bank after 60 filter steps, with equally seeded GAs.
    """
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import clustering_ga_reference as ref  # the straightforward implementation

    rng = np.random.default_rng(seed)
    problem = make_clustering_problem(ClusteringConfig(), rng)
    base = ClusterFilterBank(problem, random_feasible_clustering(30, 3, rng))
    for _ in range(60):
        base.step()
    bank_old, bank_new = base.fork(), base.fork()
    ga_old = ref.GeneticClustering(
        lambda c: ref.old_evaluate(bank_old, c),
        base.labels,
        3,
        ref.GAConfig(variant=variant),
        rng=seed + 1,
    )
    ga_new = GeneticClustering(
        bank_new.evaluate, base.labels, 3, GAConfig(variant=variant), rng=seed + 1
    )
    times: dict[str, list[float]] = {"old": [], "new": []}
    for _ in range(rounds):
        for side, ga, bank in (("old", ga_old, bank_old), ("new", ga_new, bank_new)):
            t0 = time.perf_counter()
            best, _ = ga.generation()
            times[side].append(time.perf_counter() - t0)
            bank.recluster(best)
            bank.step()
        if not (
            np.array_equal(ga_old.population, ga_new.population)
            and np.array_equal(ga_old.costs, ga_new.costs)
        ):
            raise AssertionError("the old and new GA generations differ")
    return float(np.median(times["old"])), float(np.median(times["new"]))


def compare_env_step(rounds: int, seed: int) -> tuple[float, float]:
    """Median seconds per step of (ReceiverClustering-v1, CartPole-v1), interleaved rounds."""
    rc = gym.make("selenv/ReceiverClustering-v1", preset="paper", horizon=100_000)
    cp = gym.make("CartPole-v1")
    rc.reset(seed=seed)
    cp.reset(seed=seed)
    bank = rc.unwrapped.bank  # type: ignore[attr-defined]

    def run(env: gym.Env, action: object, n: int) -> float:
        t0 = time.perf_counter()
        for _ in range(n):
            _, _, term, trunc, _ = env.step(bank.labels if action is None else action)
            if term or trunc:
                env.reset(seed=seed)
        return (time.perf_counter() - t0) / n

    times: dict[str, list[float]] = {"rc": [], "cp": []}
    for _ in range(rounds):
        times["rc"].append(run(rc, None, 100))
        times["cp"].append(run(cp, 0, 2000))
    return float(np.median(times["rc"])), float(np.median(times["cp"]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--generations", type=int, default=100)
    ap.add_argument("--naive", type=int, default=5, help="generations timed with the naive ways")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--compare", action="store_true", help="old vs new GA generation only")
    ap.add_argument("--rounds", type=int, default=300, help="interleaved rounds of --compare")
    ap.add_argument("--env-step", action="store_true", help="env step vs CartPole-v1 only")
    a = ap.parse_args()
    if a.env_step:
        t_rc, t_cp = compare_env_step(a.rounds, a.seed)
        print(
            f"env step ({a.rounds} rounds, median): ReceiverClustering-v1 {1e6 * t_rc:7.1f} us,"
            f" CartPole-v1 {1e6 * t_cp:6.2f} us, ratio {t_rc / t_cp:5.1f}x"
        )
        return
    if a.compare:
        print(f"GA generation, n = 30, N_max = 14, N_S = 20, tau = 20 ({a.rounds} rounds, median)")
        for variant in ("improved", "literal"):
            t_old, t_new = compare_generation(a.rounds, a.seed, variant)
            print(
                f"  {variant:<9} selenv {1e3 * t_new:7.2f} ms   reference {1e3 * t_old:7.2f} ms"
                f"   reference / selenv {t_old / t_new:5.2f}x   (populations identical every round)"
            )
        return
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
    env = gym.make("selenv/ReceiverClustering-v1")
    obs, info = env.reset(seed=a.seed)
    agent = make_agent("ga", "selenv/ReceiverClustering-v1")
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
