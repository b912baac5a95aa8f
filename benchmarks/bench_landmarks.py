"""Landmark selection (Soubaras & Chahbazian 2023): selection and EKF update times.

States are taken from a real ``selenv/LandmarkSelection-v1`` episode (seed 0, N = 30, K = 2,
VNS agent): the gain states of filter steps ``--start`` .. ``--start + --states - 1`` (50 states
from step 50 by default), with the previous step's played selection as VNS's warm start.

(a) brute force over the C(30, 2) = 435 pairs (vectorised ``brute_force_whitened``),
(b) VNS (``vns_whitened``) warm-started from the previous step's selection, and greedy,
(c) one EKF update (``LandmarkEKF.update`` after ``predict``, timed alone) with K = 2 vs all
    N landmarks, for N = 30, 100, 200 (200: the largest ``n_landmarks``), plus the bare
    Joseph-form ``kf_update`` on the stacked rows (the linear algebra without the Jacobians
    and input checks),
(d) a naive brute force: a Python loop over the pairs, one ``kf_update`` + ``slogdet`` each,
(e) the solvers at N = 100 and 200 (brute force is O(N^2) pairs, VNS O(N) per move),
(f) one 300-step episode: env + brute-force agent, env with k = N and the ``all`` agent, and
    ``LandmarkEKF`` driven directly with every landmark.

    .venv/bin/python benchmarks/bench_landmarks.py [--repeat 20] [--states 50] [--start 50]

Medians over ``--repeat`` passes over the states. One BLAS thread (set before numpy loads).
"""

from __future__ import annotations

import os

os.environ["OPENBLAS_NUM_THREADS"] = "1"  # tiny BLAS calls: threads only add overhead

import argparse
import copy
import itertools
import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

import selenv  # noqa: F401  (registers the env and the agents)
from selenv.agents import make as make_agent
from selenv.agents.fim_solvers import brute_force_whitened, greedy_whitened
from selenv.agents.vns import vns_whitened
from selenv.core.information import whiten
from selenv.core.kalman import kf_update
from selenv.core.linalg import cholesky_spd
from selenv.families.landmarks.models import wrap_angle
from selenv.families.landmarks.scenario import (
    LandmarkConfig,
    LandmarkEKF,
    make_landmark_problem,
)

ENV_ID = "selenv/LandmarkSelection-v1"
K = 2
PAPER_MS = {"brute_force": 4.81, "vns": 1.53}


def collect_states(start: int, n_states: int) -> list[dict[str, Any]]:
    """Play seed 0 with the VNS agent; the gain state and filter of steps start..start+n-1."""
    env = gym.make(ENV_ID, n_landmarks=30, k=K, horizon=start + n_states)
    obs, info = env.reset(seed=0)
    agent = make_agent("vns", ENV_ID)
    agent.reset(env, seed=0)
    base: Any = env.unwrapped
    states, prev = [], None
    for step in range(start + n_states):
        if step >= start:
            ekf = base.ekf
            H, hx = ekf.candidates()
            states.append(
                {
                    "Q0": base.state.information,
                    "G": np.ascontiguousarray(base.state.G),
                    "prev": prev,
                    "x": ekf.x.copy(),
                    "P": ekf.P.copy(),
                    "H": H.copy(),
                    "y": wrap_angle(ekf.measurements - hx),
                    "R": ekf.problem.R_landmark,
                }
            )
        for _ in range(K):
            obs, _, _, _, info = env.step(agent.act(obs, info))
        prev = [j for j in info["last_selection"].tolist() if j >= 0]  # -1: padding
    return states


def median_time(fn: Callable[[dict[str, Any], int], Any], states: list, repeat: int) -> float:
    """Median wall time (s) of ``fn(state, r)`` over ``repeat`` passes over the states."""
    ts = []
    for r in range(repeat):
        for s in states:
            t0 = time.perf_counter()
            fn(s, r)
            ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def naive_brute_force(s: dict[str, Any]) -> tuple[int, ...]:
    """Python loop over the pairs: Joseph-form update, then ``slogdet`` of the posterior."""
    x, P, H, y, R = s["x"], s["P"], s["H"], s["y"], s["R"]
    R2 = np.kron(np.eye(K), R)
    best = np.inf
    best_pair: tuple[int, ...] = ()
    for pair in itertools.combinations(range(H.shape[0]), K):
        idx = list(pair)
        H2 = H[idx].reshape(-1, 9)
        res = kf_update(x, P, H2 @ x + y[idx].reshape(-1), H2, R2)
        val = np.linalg.slogdet(res.P)[1]
        if val < best:
            best, best_pair = val, pair
    return best_pair


def update_times(n_landmarks: int, repeat: int, warm: int = 50) -> dict[str, float]:
    """Median time of ``LandmarkEKF.update`` with K = 2 and with all landmarks (after predict)."""
    problem = make_landmark_problem(
        LandmarkConfig(n_landmarks=n_landmarks, horizon=warm + 1), np.random.default_rng(0)
    )
    ekf = LandmarkEKF(problem)
    everyone = list(range(n_landmarks))
    for _ in range(warm):
        ekf.predict()
        ekf.update(everyone)
    ekf.predict()
    n_rep = max(repeat * 10, 50)
    out: dict[str, float] = {}
    H, _ = copy.copy(ekf).candidates()
    R1 = problem.R_landmark
    for label, sel in (("k2", [0, 1]), ("all", everyone)):
        ts = []
        for _ in range(n_rep):
            e = copy.copy(ekf)  # update replaces x and P, so a shallow copy keeps ekf intact
            t0 = time.perf_counter()
            e.update(sel)
            ts.append(time.perf_counter() - t0)
        out[label] = float(np.median(ts))
        H2 = H[sel].reshape(-1, 9)
        R2 = np.kron(np.eye(len(sel)), R1)
        z = H2 @ ekf.x
        ts = []
        for _ in range(n_rep):
            t0 = time.perf_counter()
            kf_update(ekf.x, ekf.P, z, H2, R2, validate=False)
            ts.append(time.perf_counter() - t0)
        out[f"{label}_kf"] = float(np.median(ts))
    return out


def solver_scaling(n_landmarks: int, repeat: int) -> dict[str, float]:
    """Brute force, VNS (warm start: the previous optimum) and greedy on one state at step 50."""
    problem = make_landmark_problem(
        LandmarkConfig(n_landmarks=n_landmarks, horizon=51), np.random.default_rng(0)
    )
    ekf = LandmarkEKF(problem)
    prev = None
    for _ in range(51):
        ekf.predict()
        H, _ = ekf.candidates()
        G = whiten(H, np.broadcast_to(problem.R_landmark, (n_landmarks, 2, 2)))
        L = cholesky_spd(ekf.P, "P")
        Linv = np.linalg.solve(L, np.eye(9))
        Q0 = Linv.T @ Linv
        bf = brute_force_whitened(Q0, G, K)
        state = {"Q0": Q0, "G": G, "prev": prev}
        prev = list(bf.indices)
        ekf.update(prev)
    reps = [state] * 5
    return {
        "brute_force": median_time(
            lambda s, r: brute_force_whitened(s["Q0"], s["G"], K), reps, max(2, repeat // 4)
        ),
        "vns": median_time(
            lambda s, r: vns_whitened(s["Q0"], s["G"], K, initial=s["prev"], rng=r), reps, repeat
        ),
        "greedy": median_time(lambda s, r: greedy_whitened(s["Q0"], s["G"], K), reps, repeat),
    }


def episode_times(horizon: int = 300) -> dict[str, float]:
    """Wall time of one episode: env + brute force; env with k = N + ``all``; direct EKF."""
    out = {}
    for label, k, agent_name in (("env_bf", K, "brute_force"), ("env_all", 30, "all")):
        env = gym.make(ENV_ID, n_landmarks=30, horizon=horizon, k=k)
        t0 = time.perf_counter()
        obs, info = env.reset(seed=0)
        agent = make_agent(agent_name, ENV_ID)
        agent.reset(env, seed=0)
        done = False
        while not done:
            obs, _, done, _, info = env.step(agent.act(obs, info))
        out[label] = time.perf_counter() - t0
        if label == "env_all":
            logdet_env = info["objective"]
    problem = env.unwrapped.problem  # type: ignore[attr-defined]
    t0 = time.perf_counter()
    ekf = LandmarkEKF(problem)
    for _ in range(horizon):
        ekf.predict()
        ekf.update(range(30))
    out["direct_all"] = time.perf_counter() - t0
    out["same_filter"] = float(abs(ekf.logdet_P - logdet_env) < 1e-9)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=20, help="passes over the states")
    ap.add_argument("--states", type=int, default=50, help="filter steps taken as states")
    ap.add_argument("--start", type=int, default=50, help="first filter step used")
    ap.add_argument("--naive-states", type=int, default=10, help="states for the naive loop")
    a = ap.parse_args()
    states = collect_states(a.start, a.states)
    bf_ms = 1e3 * median_time(
        lambda s, r: brute_force_whitened(s["Q0"], s["G"], K), states, a.repeat
    )
    vns_ms = 1e3 * median_time(
        lambda s, r: vns_whitened(s["Q0"], s["G"], K, initial=s["prev"], rng=r), states, a.repeat
    )
    greedy_ms = 1e3 * median_time(
        lambda s, r: greedy_whitened(s["Q0"], s["G"], K), states, a.repeat
    )
    naive = states[: a.naive_states]
    naive_ms = 1e3 * median_time(lambda s, r: naive_brute_force(s), naive, 1)
    agree = all(
        sorted(naive_brute_force(s)) == sorted(brute_force_whitened(s["Q0"], s["G"], K).indices)
        for s in naive
    )
    vns_opt = np.mean(
        [
            vns_whitened(s["Q0"], s["G"], K, initial=s["prev"], rng=r).objective
            >= brute_force_whitened(s["Q0"], s["G"], K).objective - 1e-9
            for r in range(5)
            for s in states
        ]
    )
    print(
        f"selection at N = 30, K = 2: {len(states)} states of seed 0 (steps {a.start}.."
        f"{a.start + a.states - 1}), median of {a.repeat} passes"
    )
    print(f"{'method':<44}{'ms':>9}{'paper ms':>10}{'vs BF':>8}")
    rows = [
        ("(a) brute force, 435 pairs vectorised", bf_ms, PAPER_MS["brute_force"]),
        ("(b) VNS, warm start = previous selection", vns_ms, PAPER_MS["vns"]),
        ("    greedy (extra)", greedy_ms, None),
        ("(d) naive brute force, kf_update per pair", naive_ms, None),
    ]
    for name, ms, paper in rows:
        p = f"{paper:.2f}" if paper else ""
        print(f"{name:<44}{ms:>9.3f}{p:>10}{ms / bf_ms:>7.2f}x")
    print(f"naive picks == brute-force picks: {agree}; VNS finds the optimum in {vns_opt:.0%}")

    print("\n(c) one EKF update after predict, median (us); K = 2 vs all N landmarks")
    print(f"{'N':>5}{'K=2':>9}{'all':>9}{'ratio':>8}{'kf K=2':>9}{'kf all':>9}{'ratio':>8}")
    for n in (30, 100, 200):
        u = update_times(n, a.repeat)
        print(
            f"{n:>5}{1e6 * u['k2']:>9.1f}{1e6 * u['all']:>9.1f}{u['all'] / u['k2']:>7.1f}x"
            f"{1e6 * u['k2_kf']:>9.1f}{1e6 * u['all_kf']:>9.1f}{u['all_kf'] / u['k2_kf']:>7.1f}x"
        )
    print("(kf = the bare Joseph-form kf_update on the stacked rows, validate=False)")

    print("\n(e) solvers vs N (K = 2, one state at step 50, median ms)")
    print(f"{'N':>5}{'pairs':>8}{'brute force':>13}{'VNS':>9}{'greedy':>9}")
    for n in (30, 100, 200):
        s = solver_scaling(n, a.repeat)
        print(
            f"{n:>5}{n * (n - 1) // 2:>8}{1e3 * s['brute_force']:>13.3f}"
            f"{1e3 * s['vns']:>9.3f}{1e3 * s['greedy']:>9.3f}"
        )

    e = episode_times()
    print("\n(f) one 300-step episode (s)")
    print(f"env + brute_force agent (k = 2)          {e['env_bf']:.2f}")
    print(f"env with k = 30 + 'all' agent            {e['env_all']:.2f}")
    print(f"LandmarkEKF direct, update(range(30))    {e['direct_all']:.2f}")
    print(
        f"env k = 30 / direct: {e['env_all'] / e['direct_all']:.1f}x; "
        f"same final log det P: {bool(e['same_filter'])}"
    )


if __name__ == "__main__":
    main()
