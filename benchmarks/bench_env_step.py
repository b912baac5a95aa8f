"""Env step timings: FIMSelection vs a naive step, and the overhead ratios.

Default (``--target fim-naive``): one ``selenv/FIMSelection-v1`` step at N = 1000 candidates
vs a naive step, interleaved (per round: an episode of each env, then the naive steps). The
env keeps gains and whitened rows by rank-one / triangular updates; the naive step recomputes
the FIM, its Cholesky factor, every gain (batched slogdet) and every whitened row.

``--target overheads``: in ONE process, interleaved rounds (a block of env steps, a block of
``CartPole-v1`` steps, env, CartPole, ...; both unwrapped), medians of the per-round means:
CLScheduling-v1 (preset dense: 4 agents, budget 2) step / CartPole step, the
LandmarkSelection-v1 reset, FIMSelection-v1 step at N = 10000 / its core ``GainState.add``.
Run with ``OPENBLAS_NUM_THREADS=1`` (set here before numpy is imported if unset).

    .venv/bin/python benchmarks/bench_env_step.py [--n-candidates 500] [--episodes 20]
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_env_step.py --target overheads
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: tiny linear algebra

import argparse
import copy
import time
from collections.abc import Callable
from typing import Any

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


def _interleaved(work: dict[str, Callable[[], int]], rounds: int) -> dict[str, float]:
    """Median over ``rounds`` of each block's seconds per call, blocks run in turn.

    A block returns its number of calls; time it spent in untimed work (an episode reset
    inside a step block) is in its ``untimed`` attribute and is subtracted.
    """
    per: dict[str, list[float]] = {k: [] for k in work}
    for _ in range(rounds):
        for name, block in work.items():
            block.untimed = 0.0  # type: ignore[attr-defined]
            t = time.perf_counter()
            n = block()
            dt = time.perf_counter() - t - block.untimed  # type: ignore[attr-defined]
            per[name].append(dt / n)
    return {k: float(np.median(v)) for k, v in per.items()}


def _stepper(env: Any, n: int, seed: int = 0) -> Callable[[], int]:
    """A block of ``n`` random masked steps of ``env`` (its resets go to ``untimed``)."""
    rng = np.random.default_rng(seed)
    state: dict[str, object] = {}

    def new_episode() -> None:
        _, info = env.reset(seed=int(rng.integers(1 << 30)))
        state["mask"] = np.asarray(info.get("action_mask", np.ones(2, bool)), bool)

    new_episode()

    def block() -> int:
        steps = 0
        while steps < n:
            mask = state["mask"]
            assert isinstance(mask, np.ndarray)
            t = time.perf_counter()
            action = int(rng.choice(np.flatnonzero(mask)))  # the agent: not the env's time
            block.untimed += time.perf_counter() - t  # type: ignore[attr-defined]
            _, _, term, trunc, info = env.step(action)
            steps += 1
            state["mask"] = np.asarray(info.get("action_mask", np.ones(2, bool)), bool)
            if term or trunc:
                t = time.perf_counter()
                new_episode()
                block.untimed += time.perf_counter() - t  # type: ignore[attr-defined]
        return steps

    block.untimed = 0.0  # type: ignore[attr-defined]
    return block


def overheads(rounds: int) -> None:
    """The ratios (see the module docstring)."""
    cart = gym.make("CartPole-v1").unwrapped
    cart.reset(seed=0)

    cart_actions = [int(a) for a in np.random.default_rng(0).integers(0, 2, 200)]

    def cart_block() -> int:  # pure steps: actions drawn beforehand, resets untimed
        for a in cart_actions:
            if cart.step(a)[2]:
                t = time.perf_counter()
                cart.reset()
                cart_block.untimed += time.perf_counter() - t  # type: ignore[attr-defined]
        return len(cart_actions)

    cl = gym.make("selenv/CLScheduling-v1", preset="dense", n_agents=4, budget=2).unwrapped
    land = gym.make("selenv/LandmarkSelection-v1").unwrapped
    seeds = iter(range(1 << 30))

    def land_reset() -> int:
        for _ in range(2):
            land.reset(seed=next(seeds))
        return 2

    fim: Any = gym.make("selenv/FIMSelection-v1", n_candidates=5000).unwrapped  # 2 sensors
    fim.reset(seed=0)
    fim_state0 = copy.deepcopy(fim.state)
    order = [int(k) for k in np.random.default_rng(0).permutation(fim.n)[: fim.budget]]
    pos = {"i": 0}

    def fim_step() -> int:  # the env step of candidate order[i] (reset outside the timing)
        if pos["i"] == len(order):
            fim.reset(seed=0)
            pos["i"] = 0
        t = time.perf_counter()
        fim.step(order[pos["i"]])
        dt = time.perf_counter() - t
        pos["i"] += 1
        fim_step.t = dt  # type: ignore[attr-defined]
        return 1

    core: dict[str, Any] = {"s": copy.deepcopy(fim_state0), "i": 0}

    def fim_core() -> int:  # the same update on the bare gain state
        if core["i"] == len(order):
            core["s"], core["i"] = copy.deepcopy(fim_state0), 0
        s = core["s"]
        t = time.perf_counter()
        s.add(order[core["i"]])
        fim_core.t = time.perf_counter() - t  # type: ignore[attr-defined]
        core["i"] += 1
        return 1

    res = _interleaved(
        {"cartpole": cart_block, "cl": _stepper(cl, 50), "cartpole2": cart_block,
         "landmark_reset": land_reset},
        rounds,
    )  # fmt: skip
    fim_t: dict[str, list[float]] = {"env": [], "core": []}
    for _ in range(rounds * 5):
        fim_step()
        fim_t["env"].append(fim_step.t)  # type: ignore[attr-defined]
        fim_core()
        fim_t["core"].append(fim_core.t)  # type: ignore[attr-defined]
    t_cart = float(np.median([res["cartpole"], res["cartpole2"]]))
    t_fim, t_core = (float(np.median(v)) for v in fim_t.values())
    print(f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}, {rounds} rounds")
    print(f"  CartPole-v1 step              {t_cart * 1e6:9.1f} us")
    t_cl, t_land = res["cl"], res["landmark_reset"]
    print(f"  CLScheduling-v1 step (dense)  {t_cl * 1e6:9.1f} us  = {t_cl / t_cart:6.1f}x CartPole")
    print(f"  LandmarkSelection-v1 reset    {t_land * 1e3:9.2f} ms")
    print(f"  FIMSelection-v1 step N={fim.n}  {t_fim * 1e6:9.1f} us  = {t_fim / t_core:6.2f}x "
          f"its GainState.add ({t_core * 1e6:.1f} us)")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--target", choices=("fim-naive", "overheads"), default="fim-naive")
    ap.add_argument("--rounds", type=int, default=15, help="overheads: interleaved rounds")
    ap.add_argument("--n-candidates", type=int, default=500, help="per sensor (x2 sensors)")
    ap.add_argument("--budget", type=int, default=50)
    ap.add_argument("--episodes", type=int, default=20)
    a = ap.parse_args()
    if a.target == "overheads":
        overheads(a.rounds)
        return
    fim_vs_naive(a.n_candidates, a.budget, a.episodes)


def fim_vs_naive(n_candidates: int, budget: int, episodes: int) -> None:
    """FIMSelection-v1 step (unwrapped and ``gym.make``-wrapped) vs the naive step, interleaved.

    Each round plays one episode of each env (random masked actions, not timed) and then the
    naive recomputation for the same budget; medians per step over all rounds.
    """
    envs: dict[str, Any] = {}
    for label, wrapped in (("unwrapped", False), ("gym.make (checker+order)", True)):
        env: Any = gym.make("selenv/FIMSelection-v1", n_candidates=n_candidates, budget=budget)
        envs[label] = env if wrapped else env.unwrapped
    times: dict[str, list[float]] = {k: [] for k in envs}
    naive: list[float] = []
    for ep in range(episodes):
        for label, target in envs.items():
            _, info = target.reset(seed=ep)
            rng = np.random.default_rng(ep)
            done = False
            while not done:
                act = int(rng.choice(np.flatnonzero(info["action_mask"])))
                t = time.perf_counter()
                _, _, done, _, info = target.step(act)
                times[label].append(time.perf_counter() - t)
        prob = target.unwrapped.problem
        for j in range(budget):
            t = time.perf_counter()
            naive_step(prob.Q0, prob.G, list(range(j)))
            naive.append(time.perf_counter() - t)
    t_naive = float(np.median(naive))
    n, m, d = target.unwrapped.n, prob.G.shape[1], prob.G.shape[2]
    print(f"FIMSelection-v1 step, N = {n} candidates, m = {m}, d = {d} ({episodes} rounds)")
    for label, ts in times.items():
        t = float(np.median(ts))
        print(f"  {label:<28} median {t * 1e6:8.1f} us/step   naive/this = {t_naive / t:5.1f}x")
    print(f"  {'naive recomputation':<28} median {t_naive * 1e6:8.1f} us/step")


if __name__ == "__main__":
    main()
