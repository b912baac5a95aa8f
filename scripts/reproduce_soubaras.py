"""Reproduce Sec. V of Soubaras & Chahbazian (2023): Figs. 3-6 and Table II.

Angles-only UAV navigation (``selenv/LandmarkSelection-v1``, Table I parameters): an EKF with a
10 Hz IMU updates at every step with the angles of arrival of K = 2 of N = 30 landmarks
(Algorithm 3). Monte Carlo over ``--runs`` seeds; each seed is one realisation (landmark
layout, IMU noise, initial error, measurement noise) shared by every method, so the
comparisons are paired. Methods:

* ``all``: every landmark at every step (the lower bound). Driven directly on
  :class:`~selenv.families.landmarks.scenario.LandmarkEKF` with ``update(range(N))``: through the
  env
  it would take ``N`` masked picks per filter step (each updating the observation), ~15x slower
  for the same filter (``tests/landmarks/test_reproduce_soubaras.py`` checks that the two agree).
* ``brute_force`` (Algorithm 1), ``vns`` (Algorithm 2, warm-started from the previous step),
  ``greedy`` (extra): the registered agents played through the env, as ``selenv bench`` does.

Each method's selections are then replayed on a bare ``LandmarkEKF`` (the same deterministic
filter; the replay must reproduce the env's ``log det P`` to 1e-9) to read the posterior
estimate at every step and to time the EKF update alone. Per step we record the cost eq. (11)
(``log det P`` and ``det P``), the true position error, ``trace P_pos`` and the position CRLB on
the true trajectory for the selections made (``crlb_reference``). On the states of the VNS
episode, brute force, VNS (with the agent's warm start) and greedy are timed on identical
inputs (solver calls only) and VNS's pick is compared with the optimum.

Usage::

    python scripts/reproduce_soubaras.py [--runs 100] [--horizon 300] [--workers 2]
                                         [--seed 2023] [--out docs/figures] [--quick]
                                         [--executor local|process|ray] [--address ADDR]
                                         [--n-landmarks 30] [--k 2] [--allow-large]

Sizes are checked before any work (exit 2, one line naming the option): ``--runs`` and
``--horizon`` up to 10,000, ``C(N, K)`` brute-force subsets per step up to 100,000 and about
4 GiB of kept records (:data:`CEILINGS`, :data:`SUBSETS_CEILING`, :data:`MEMORY_CEILING_MIB`);
``--allow-large`` lifts these ceilings.

Runs go to ``--workers`` local processes by default, to Ray tasks with ``--executor ray``
(``--address`` joins a cluster); run ``r`` uses seed ``--seed + r`` whatever the executor.

Writes ``soubaras_fig3.png`` .. ``soubaras_fig6.png`` into ``--out`` and prints Markdown
tables. ``main(argv)`` returns the numbers as a dict. Results: ``docs/reproductions/soubaras.md``.
"""

from __future__ import annotations

import os
import sys

# Tiny BLAS calls (9 x 9, 60 x 60) with several OpenBLAS threads per process on a 2-core box
# are 10-40x slower under contention: one thread per process, set before numpy is imported
# (worker processes are spawned from here and inherit it; Ray workers get one thread from Ray).
os.environ["OPENBLAS_NUM_THREADS"] = "1"
os.environ["OMP_NUM_THREADS"] = "1"
os.environ["MKL_NUM_THREADS"] = "1"

import argparse
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from matplotlib.figure import Figure

import selenv  # noqa: F401  (registers the env and the agents)
from selenv.agents import make as make_agent
from selenv.agents.fim_solvers import (
    MAX_BRUTE_FORCE_SUBSETS,
    brute_force_whitened,
    greedy_whitened,
)
from selenv.agents.vns import vns_whitened
from selenv.atomic import describe_os_error, probe_writable, save_figure
from selenv.core.information import logdet_objective
from selenv.core.linalg import logdet_spd
from selenv.exits import UsageError, check_size, guarded_main
from selenv.families.landmarks.scenario import (
    MAX_LANDMARKS,
    MAX_STEPS,
    LandmarkEKF,
    LandmarkProblem,
    crlb_reference,
)
from selenv.learned.config import UsageParser
from selenv.parallel import Executor, ExecutorError, add_executor_arguments, executor_from_args

ENV_ID = "selenv/LandmarkSelection-v1"
METHODS = ("all", "brute_force", "vns", "greedy", "random")
ENV_METHODS = ("brute_force", "vns", "greedy", "random")
LABELS = {
    "all": "all 30 landmarks",
    "brute_force": "Brute Force (K = 2)",
    "vns": "VNS (K = 2)",
    "greedy": "greedy (K = 2, extra)",
    "random": "random pair (extra)",
}
COLORS = {
    "all": "black",
    "brute_force": "tab:blue",
    "vns": "tab:red",
    "greedy": "tab:green",
    "random": "tab:gray",
}
STYLES = {"greedy": "--", "random": ":"}
SOLVERS = ("brute_force", "vns", "greedy")
#: Table II of the paper: average duration of one selection (ms); "None" is 4.44 s
PAPER_TABLE_II_MS = {"vns": 1.53, "brute_force": 4.81, "none": 4440.0}
DEFAULT_SEED = 2023
QUICK_RUNS, QUICK_HORIZON = 4, 80
#: the RMSE / CRLB comparison starts after this many seconds (initial transient)
CONVERGED_AFTER_S = 5.0
REPORT_TIMES_S = (0.1, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0)
FIGURE_NAMES = ("soubaras_fig3", "soubaras_fig4", "soubaras_fig5", "soubaras_fig6")


# -- one realisation (runs in a worker process) ---------------------------------------------------
def play_env(env: gym.Env[Any, Any], name: str, seed: int, time_solvers: bool) -> dict[str, Any]:
    """Play one episode with a registered agent; selections, costs and decision times.

    With ``time_solvers``, before each filter step's first pick brute force, greedy and VNS
    (warm-started from the previous played selection, as the agent is) are timed on the env's
    gain state (prior ``P_pred^-1`` and whitened landmarks), and the played selection's
    objective is compared with brute force's.
    """
    obs, info = env.reset(seed=seed)
    agent = make_agent(name, ENV_ID)
    agent.reset(env, seed=seed)
    base = env.unwrapped
    K, T = base.k, base.horizon  # type: ignore[attr-defined]
    sels = np.zeros((T, K), dtype=np.intp)
    objective = np.zeros(T)
    decision = np.zeros(T)
    timing_rng = np.random.default_rng(seed + 7919)
    solve: dict[str, Any] = {s: np.zeros(T) for s in SOLVERS}
    solve.update(
        f_best=np.zeros(T), f_played=np.zeros(T), f_vns_timed=np.zeros(T), vns_evals=np.zeros(T)
    )
    prev: list[int] | None = None
    for k in range(T):
        if time_solvers:
            st = base.state  # type: ignore[attr-defined]
            Q0, G = st.information, np.ascontiguousarray(st.G)
            t0 = time.perf_counter()
            bf = brute_force_whitened(Q0, G, K)
            t1 = time.perf_counter()
            greedy_whitened(Q0, G, K)
            t2 = time.perf_counter()
            warm = list(bf.indices) if prev is None else prev
            vn = vns_whitened(Q0, G, K, initial=warm, rng=timing_rng)
            t3 = time.perf_counter()
            solve["brute_force"][k], solve["greedy"][k], solve["vns"][k] = t1 - t0, t2 - t1, t3 - t2
            solve["f_best"][k], solve["f_vns_timed"][k] = bf.objective, vn.objective
            solve["vns_evals"][k] = vn.evaluations
        for _ in range(K):
            t0 = time.perf_counter()
            action = agent.act(obs, info)
            decision[k] += time.perf_counter() - t0
            obs, _, terminated, truncated, info = env.step(action)
        sels[k] = tuple(j for j in info["last_selection"].tolist() if j >= 0)  # -1: padding
        objective[k] = info["objective"]
        prev = [int(i) for i in sels[k]]
        if time_solvers:
            solve["f_played"][k] = logdet_objective(Q0, G, prev)
    assert terminated and not truncated
    out: dict[str, Any] = {"selections": sels, "env_objective": objective, "decision_s": decision}
    if time_solvers:
        out["solve"] = solve
    return out


def replay(problem: LandmarkProblem, selections: np.ndarray | None) -> dict[str, np.ndarray]:
    """Run the EKF with given selections (``None``: every landmark); per-step records.

    Index 0 is the initial estimate; index ``k + 1`` the posterior after step ``k``. The update
    is timed alone (after :meth:`~LandmarkEKF.predict`, no cached Jacobians).
    """
    T, N = problem.horizon, problem.n_landmarks
    ekf = LandmarkEKF(problem)
    logdet, err2, trace_pos = np.zeros(T + 1), np.zeros(T + 1), np.zeros(T + 1)
    t_predict, t_update = np.zeros(T), np.zeros(T)
    everyone = list(range(N))

    def record(i: int) -> None:
        logdet[i] = logdet_spd(ekf.P, "P")
        d = ekf.x[:3] - problem.states[i, :3]
        err2[i] = float(d @ d)
        trace_pos[i] = float(np.trace(ekf.P[:3, :3]))

    record(0)
    for k in range(T):
        t0 = time.perf_counter()
        ekf.predict()
        t1 = time.perf_counter()
        ekf.update(everyone if selections is None else selections[k])
        t2 = time.perf_counter()
        t_predict[k], t_update[k] = t1 - t0, t2 - t1
        record(k + 1)
    crlb = crlb_reference(problem, None if selections is None else list(selections))
    crlb_pos = np.trace(crlb[:, :3, :3], axis1=1, axis2=2)
    return {
        "logdet": logdet,
        "err2": err2,
        "trace_pos": trace_pos,
        "crlb_pos": crlb_pos,
        "t_predict": t_predict,
        "t_update": t_update,
    }


def run_seed(task: dict[str, Any]) -> dict[str, Any]:
    """Every method on the realisation of ``task["seed"]`` (see the module docstring)."""
    seed, env_kwargs = int(task["seed"]), task["env_kwargs"]
    env = gym.make(ENV_ID, **env_kwargs)
    out: dict[str, Any] = {"seed": seed}
    problem: LandmarkProblem | None = None
    for name in ENV_METHODS:
        played = play_env(env, name, seed, time_solvers=(name == "vns"))
        p = env.unwrapped.problem  # type: ignore[attr-defined]
        if problem is None:
            problem = p
        else:  # the same seed gives the same realisation for every method
            assert np.array_equal(p.measurements, problem.measurements)
        rec = replay(problem, played["selections"])
        gap = np.max(np.abs(rec["logdet"][1:] - played["env_objective"]))
        assert gap < 1e-6, f"replay of {name} differs from the env by {gap} nats"
        out[name] = {**played, **rec, "replay_gap": float(gap)}
    assert problem is not None
    out["all"] = replay(problem, None)
    if task.get("keep_geometry"):
        out["geometry"] = {"landmarks": problem.landmarks.copy(), "states": problem.states.copy()}
    return out


def run_all(tasks: list[dict[str, Any]], pool: Executor) -> list[dict[str, Any]]:
    """Run the seeds on ``pool`` (local, process pool or Ray; in order) with a progress bar."""
    return pool.map(run_seed, tasks, desc="Monte Carlo", unit="run")


# -- aggregation ---------------------------------------------------------------------------------
def aggregate(runs: list[dict[str, Any]], dt: float, n_landmarks: int) -> dict[str, Any]:
    """Means over runs per method and step, paired gaps, solver statistics and timings."""
    R = len(runs)
    stack = {m: {key: np.stack([r[m][key] for r in runs]) for key in runs[0][m]} for m in METHODS}
    T = stack["all"]["logdet"].shape[1] - 1
    t = np.arange(T + 1) * dt
    conv = t >= CONVERGED_AFTER_S
    conv[0] = False
    if not conv.any():  # horizon shorter than the transient: use the second half
        conv = np.arange(T + 1) >= (T + 1) // 2
    out: dict[str, Any] = {"t": t, "runs": R, "converged_mask": conv, "methods": {}}
    out["n_landmarks"], out["k"] = n_landmarks, int(stack["brute_force"]["selections"].shape[2])
    for m in METHODS:
        s = stack[m]
        logdet = s["logdet"]
        out["methods"][m] = {
            "logdet_mean": logdet.mean(axis=0),
            "det_mean": np.exp(logdet).mean(axis=0),
            "cost_mean": float(logdet[:, 1:].mean()),  # mean over runs and steps 1..T
            "crlb_pos": np.sqrt(s["crlb_pos"].mean(axis=0)),  # sqrt of the mean trace
            "crlb_pos_mean_sqrt": np.sqrt(s["crlb_pos"]).mean(axis=0),  # mean of per-run bound
            "rmse": np.sqrt(s["err2"].mean(axis=0)),
            "filter_std": np.sqrt(s["trace_pos"].mean(axis=0)),
            # E||e||^2 = tr P_pos for a consistent filter, so this ratio should be ~1
            "err2_over_trace": float(np.mean(s["err2"][:, conv] / s["trace_pos"][:, conv])),
            "rmse_conv": float(np.sqrt(s["err2"][:, conv].mean())),
            "crlb_conv": float(np.sqrt(s["crlb_pos"][:, conv].mean())),
            "filter_std_conv": float(np.sqrt(s["trace_pos"][:, conv].mean())),
            "t_update_us": 1e6 * s["t_update"],
            "t_predict_us": 1e6 * s["t_predict"],
        }
        if m in ENV_METHODS:
            out["methods"][m]["decision_ms"] = 1e3 * s["decision_s"]
            out["methods"][m]["selections"] = s["selections"]
            out["methods"][m]["replay_gap"] = float(s["replay_gap"].max())
    bf = stack["brute_force"]["logdet"]
    out["paired"] = {}
    for m in ("all", "vns", "greedy", "random"):
        d = stack[m]["logdet"][:, 1:] - bf[:, 1:]  # (R, T) nats, same realisation
        per_run = d.mean(axis=1)
        se = per_run.std(ddof=1) / np.sqrt(R) if R > 1 else float("nan")
        c = np.sqrt(stack[m]["crlb_pos"][:, 1:]) - np.sqrt(stack["brute_force"]["crlb_pos"][:, 1:])
        mse_gap = (stack[m]["err2"] - stack["brute_force"]["err2"])[:, conv].mean(axis=1)
        out["paired"][m] = {
            "logdet_gap_t": d.mean(axis=0),
            "logdet_gap_mean": float(d.mean()),
            "logdet_gap_se": float(se),
            "logdet_gap_max": float(d.max()),
            "logdet_gap_min": float(d.min()),
            "final_gap_mean": float(d[:, -1].mean()),
            "crlb_gap_mean_m": float(c[:, conv[1:]].mean()),
            # paired difference of each run's mean squared position error after convergence
            "mse_gap_mean": float(mse_gap.mean()),
            "mse_gap_se": float(mse_gap.std(ddof=1) / np.sqrt(R)) if R > 1 else float("nan"),
            "crlb_max_rel_diff": float(
                np.max(
                    np.abs(
                        out["methods"][m]["crlb_pos"] / out["methods"]["brute_force"]["crlb_pos"]
                        - 1.0
                    )
                )
            ),
        }
    sv = {key: np.stack([r["vns"]["solve"][key] for r in runs]) for key in runs[0]["vns"]["solve"]}
    played_sel = stack["vns"]["selections"]
    # the played VNS selection is optimal for its step iff its objective equals brute force's
    lost = sv["f_best"] - sv["f_played"]  # >= 0 (nats)
    same = lost <= 1e-9 * np.maximum(1.0, np.abs(sv["f_best"]))
    out["solver"] = {
        "ms": {s: 1e3 * sv[s] for s in SOLVERS},
        "vns_same_as_bf": float(same.mean()),
        "vns_same_first_step": float(same[:, 0].mean()),
        "vns_lost_mean": float(lost.mean()),
        "vns_lost_max": float(lost.max()),
        "vns_timed_same": float((sv["f_best"] - sv["f_vns_timed"] <= 1e-9).mean()),
        "vns_changes": float(
            (np.diff(np.sort(played_sel, axis=2), axis=1) != 0).any(axis=2).mean()
        ),
        "bf_changes": float(
            (np.diff(np.sort(stack["brute_force"]["selections"], axis=2), axis=1) != 0)
            .any(axis=2)
            .mean()
        ),
        "f_best_mean": float(sv["f_best"].mean()),
        "vns_evals_mean": float(sv["vns_evals"].mean()),
    }
    return out


# -- figures -------------------------------------------------------------------------------------
def plot_fig3(geom: dict[str, Any], sels: np.ndarray, dt: float, path: Path) -> None:
    """Fig. 3: true track, landmarks and a few brute-force selections (first run)."""
    fig = Figure(figsize=(8, 7), layout="constrained")
    ax = fig.add_subplot()
    lm, x = geom["landmarks"], geom["states"]
    ax.scatter(lm[:, 0] / 1e3, lm[:, 1] / 1e3, marker="^", color="grey", s=40, label="landmarks")
    for i, p in enumerate(lm):
        ax.annotate(
            str(i), (p[0] / 1e3, p[1] / 1e3), fontsize=6, xytext=(3, 2), textcoords="offset points"
        )
    ax.plot(x[:, 0] / 1e3, x[:, 1] / 1e3, "k-", lw=2, label="true track")
    T = sels.shape[0]
    shown = np.unique(np.linspace(0, T - 1, 7).astype(int))
    cmap = [f"C{i}" for i in range(len(shown))]
    for color, k in zip(cmap, shown, strict=True):
        p = x[k + 1]
        for j in sels[k]:
            ax.plot(
                [p[0] / 1e3, lm[j, 0] / 1e3],
                [p[1] / 1e3, lm[j, 1] / 1e3],
                "-",
                color=color,
                lw=1,
                alpha=0.8,
            )
        ax.plot(
            p[0] / 1e3,
            p[1] / 1e3,
            "o",
            color=color,
            ms=6,
            label=f"t = {(k + 1) * dt:.1f} s: {sorted(int(j) for j in sels[k])}",
        )
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel="East (km)", ylabel="North (km)")
    ax.set_title(
        "Fig. 3: true track (1000 m altitude), landmarks and brute-force selections\n"
        "(first Monte Carlo run)"
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    save_figure(fig, path, dpi=120)


def _time_axis(ax: Any, title: str, ylabel: str) -> None:
    ax.set(xlabel="time (s)", ylabel=ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)


def plot_fig4(agg: dict[str, Any], path: Path) -> None:
    """Fig. 4: cost eq. (11) over time, log det P and det P, and paired gaps to brute force."""
    fig = Figure(figsize=(14, 4.8), layout="constrained")
    ax_l, ax_d, ax_g = fig.subplots(1, 3)
    t, R = agg["t"], agg["runs"]
    for m in METHODS:
        s = agg["methods"][m]
        ls = STYLES.get(m, "-")
        ax_l.plot(t, s["logdet_mean"], ls, color=COLORS[m], lw=1.5, label=LABELS[m])
        ax_d.plot(t, s["det_mean"], ls, color=COLORS[m], lw=1.5, label=LABELS[m])
    ax_d.set_yscale("log")
    _time_axis(ax_l, f"Fig. 4: cost eq. (11) as log det P (mean of {R} runs)", "log det P (nats)")
    _time_axis(ax_d, "Fig. 4 as plotted in the paper: det P (mean of runs)", "det P")
    for m in ("vns", "greedy"):
        ax_g.plot(
            t[1:],
            agg["paired"][m]["logdet_gap_t"],
            color=COLORS[m],
            lw=1.2,
            label=f"{LABELS[m]} − Brute Force",
        )
    ax_g.axhline(0.0, color="k", lw=0.8)
    _time_axis(ax_g, "paired gap to Brute Force (same realisation)", "Δ log det P (nats)")
    save_figure(fig, path, dpi=120)


def plot_fig5(agg: dict[str, Any], path: Path) -> None:
    """Fig. 5: position CRLB on the true trajectory for each method's selections."""
    fig = Figure(figsize=(12, 4.8), layout="constrained")
    ax, ax_r = fig.subplots(1, 2)
    t, R = agg["t"], agg["runs"]
    ref = agg["methods"]["all"]["crlb_pos"]
    for m in METHODS:
        ls = STYLES.get(m, "-")
        ax.plot(t, agg["methods"][m]["crlb_pos"], ls, color=COLORS[m], lw=1.5, label=LABELS[m])
        if m != "all":
            ax_r.plot(
                t, agg["methods"][m]["crlb_pos"] / ref, ls, color=COLORS[m], lw=1.5, label=LABELS[m]
            )
    ax.set_yscale("log")
    _time_axis(
        ax, f"Fig. 5: position CRLB on the true track ({R} runs)", "sqrt(mean trace CRLB_pos) (m)"
    )
    ax_r.axhline(1.0, color="k", lw=0.8)
    _time_axis(ax_r, "ratio to the all-landmark CRLB", "CRLB(K = 2) / CRLB(all)")
    save_figure(fig, path, dpi=120)


def plot_fig6(agg: dict[str, Any], path: Path) -> None:
    """Fig. 6: position RMSE over the runs, with the all-landmark CRLB and sqrt trace P_pos."""
    fig = Figure(figsize=(13, 4.8), layout="constrained")
    ax, ax_z = fig.subplots(1, 2)
    t, R = agg["t"], agg["runs"]
    after = t >= min(CONVERGED_AFTER_S, t[-1] / 2)
    for a, mask in ((ax, slice(None)), (ax_z, after)):
        for m in ("all", "brute_force", "vns"):
            s = agg["methods"][m]
            a.plot(t[mask], s["rmse"][mask], color=COLORS[m], lw=1.5, label=f"RMSE, {LABELS[m]}")
            a.plot(
                t[mask],
                s["filter_std"][mask],
                ":",
                color=COLORS[m],
                lw=1.2,
                label=f"filter sqrt(tr P_pos), {m}",
            )
        a.plot(
            t[mask],
            agg["methods"]["all"]["crlb_pos"][mask],
            "--",
            color="tab:purple",
            lw=2,
            label="CRLB, all 30 landmarks",
        )
        a.plot(
            t[mask],
            agg["methods"]["brute_force"]["crlb_pos"][mask],
            "--",
            color="tab:cyan",
            lw=1.2,
            label="CRLB, brute-force selections",
        )
    ax.set_yscale("log")
    _time_axis(ax, f"Fig. 6: position RMSE over {R} Monte Carlo runs", "position RMSE (m)")
    _time_axis(ax_z, f"zoom, t >= {t[after][0]:.1f} s (linear)", "position RMSE (m)")
    ax_z.legend(fontsize=7)
    save_figure(fig, path, dpi=120)


# -- report --------------------------------------------------------------------------------------
def _at(arr: np.ndarray, t: np.ndarray, ts: float) -> float:
    return float(arr[int(np.argmin(np.abs(t - ts)))])


def table2_rows(agg: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Mean and median ms per selection of each solver and agent decision; EKF update times."""
    rows: dict[str, dict[str, float]] = {}
    for s in SOLVERS:
        ms = agg["solver"]["ms"][s]
        rows[f"{s} solver"] = {"mean": float(ms.mean()), "median": float(np.median(ms))}
        dec = agg["methods"][s]["decision_ms"]
        rows[f"{s} agent"] = {"mean": float(dec.mean()), "median": float(np.median(dec))}
    k2 = np.concatenate([agg["methods"][m]["t_update_us"].ravel() for m in ENV_METHODS])
    a30 = agg["methods"]["all"]["t_update_us"]
    pr = np.concatenate([agg["methods"][m]["t_predict_us"].ravel() for m in METHODS])
    rows["ekf update K = 2"] = {
        "mean": float(k2.mean()) / 1e3,
        "median": float(np.median(k2)) / 1e3,
    }
    rows["ekf update all"] = {
        "mean": float(a30.mean()) / 1e3,
        "median": float(np.median(a30)) / 1e3,
    }
    rows["ekf predict"] = {"mean": float(pr.mean()) / 1e3, "median": float(np.median(pr)) / 1e3}
    return rows


def _mse_gap(P: dict[str, Any], m: str) -> str:
    if m not in P:
        return "0"
    return f"{P[m]['mse_gap_mean']:+.2f} ± {P[m]['mse_gap_se']:.2f}"


def format_tables(agg: dict[str, Any]) -> str:
    """Markdown tables of Figs. 4-6 and Table II."""
    t, M, P = agg["t"], agg["methods"], agg["paired"]
    times = [ts for ts in REPORT_TIMES_S if ts <= t[-1] + 1e-9]
    lines = [
        f"### Fig. 4: mean cost eq. (11), log det P (nats), {agg['runs']} runs",
        "",
        "| t (s) | all | Brute Force | VNS | greedy | random | VNS − BF (paired) | greedy − BF |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for ts in times:
        i = int(np.argmin(np.abs(t - ts)))
        cells = " | ".join(f"{M[m]['logdet_mean'][i]:.3f}" for m in METHODS)
        lines.append(
            f"| {ts:g} | {cells} | {P['vns']['logdet_gap_t'][i - 1]:+.4f} | "
            f"{P['greedy']['logdet_gap_t'][i - 1]:+.4f} |"
        )
    lines += [
        "",
        "| method | mean log det P, steps 1..T | mean gap to BF ± s.e. (nats) | min / max step "
        "gap | final gap | mean det P at the end |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for m in METHODS:
        g = P.get(m)
        gap = (
            f"{g['logdet_gap_mean']:+.4f} ± {g['logdet_gap_se']:.4f} | "
            f"{g['logdet_gap_min']:+.3f} / {g['logdet_gap_max']:+.3f} | {g['final_gap_mean']:+.4f}"
            if g
            else "0 | 0 | 0"
        )
        lines.append(f"| {m} | {M[m]['cost_mean']:.3f} | {gap} | {M[m]['det_mean'][-1]:.3e} |")
    lines += [
        "",
        "### Fig. 5: position CRLB on the true track, sqrt(mean trace) (m)",
        "",
        "| t (s) | all | Brute Force | VNS | greedy | random | BF / all | VNS / all | "
        "random / all |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for ts in [0.0, *times]:
        c = {m: _at(M[m]["crlb_pos"], t, ts) for m in METHODS}
        lines.append(
            f"| {ts:g} | {' | '.join(f'{c[m]:.3f}' for m in METHODS)} | "
            f"{c['brute_force'] / c['all']:.2f} | {c['vns'] / c['all']:.2f} | "
            f"{c['random'] / c['all']:.2f} |"
        )
    lines += [
        "",
        "### Fig. 6: position RMSE over the runs (m); filter sqrt(mean trace P_pos) in brackets",
        "",
        "| t (s) | CRLB all | all | Brute Force | VNS | greedy | random |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for ts in [0.0, *times]:
        cells = " | ".join(
            f"{_at(M[m]['rmse'], t, ts):.3f} ({_at(M[m]['filter_std'], t, ts):.3f})"
            for m in METHODS
        )
        lines.append(f"| {ts:g} | {_at(M['all']['crlb_pos'], t, ts):.3f} | {cells} |")
    conv_t = t[agg["converged_mask"]][0]
    lines += [
        "",
        f"After convergence (t >= {conv_t:.1f} s), pooled over runs and steps:",
        "",
        "| method | RMSE (m) | own CRLB (m) | RMSE / own CRLB | RMSE / CRLB all | filter "
        "sqrt(tr P_pos) (m) | mean ‖e_pos‖² / tr P_pos | MSE − BF, paired (m²) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    c_all = M["all"]["crlb_conv"]
    for m in METHODS:
        s = M[m]
        lines.append(
            f"| {m} | {s['rmse_conv']:.3f} | {s['crlb_conv']:.3f} | "
            f"{s['rmse_conv'] / s['crlb_conv']:.2f} | {s['rmse_conv'] / c_all:.2f} | "
            f"{s['filter_std_conv']:.3f} | {s['err2_over_trace']:.2f} | {_mse_gap(P, m)} |"
        )
    lines += [
        "",
        "Largest relative difference of the mean CRLB curves from brute force's, over all steps: "
        + ", ".join(f"{m} {100 * P[m]['crlb_max_rel_diff']:.2f} %" for m in ("vns", "greedy")),
    ]
    rows = table2_rows(agg)
    sv = agg["solver"]
    n_lm, k_sel = agg["n_landmarks"], agg["k"]
    paper = {"vns": "1.53", "brute_force": "4.81"}
    lines += [
        "",
        "### Table II: time per selection (ms), N = 30, K = 2",
        "",
        "| what | mean | median | paper |",
        "|---|---:|---:|---:|",
    ]
    for key, r in rows.items():
        p = paper.get(key.split()[0], "") if key.endswith("solver") else ""
        if key == "ekf update all":
            p = "'None': 4440 (unexplained)"
        lines.append(f"| {key} | {r['mean']:.3f} | {r['median']:.3f} | {p} |")
    ratio = rows["ekf update all"]["median"] / rows["ekf update K = 2"]["median"]
    upd = rows["ekf update K = 2"]["mean"]
    replay_gap = max(M[m]["replay_gap"] for m in ENV_METHODS)
    lines += [
        "",
        f"EKF update all / K = 2 (medians): {ratio:.1f}x.",
        f"Per filter step (means; the prediction, {rows['ekf predict']['mean']:.3f} ms, is common "
        f"to all): VNS selection + K = 2 update {rows['vns solver']['mean'] + upd:.3f} ms, "
        f"brute force + update {rows['brute_force solver']['mean'] + upd:.3f} ms, all-landmark "
        f"update {rows['ekf update all']['mean']:.3f} ms.",
        f"VNS played the brute-force optimum at {100 * sv['vns_same_as_bf']:.1f} % of the steps "
        f"(objective lost: mean {sv['vns_lost_mean']:.2e}, max {sv['vns_lost_max']:.2e} nats); "
        f"the timed VNS call: {100 * sv['vns_timed_same']:.1f} %, with "
        f"{sv['vns_evals_mean']:.0f} subset evaluations on average vs "
        f"{math.comb(n_lm, k_sel)} for brute force.",
        f"The selection changes from one step to the next at {100 * sv['vns_changes']:.1f} % "
        f"(VNS) / {100 * sv['bf_changes']:.1f} % (BF) of the steps.",
        f"Replays reproduce the env's log det P to {replay_gap:.1e} nats.",
    ]
    return "\n".join(lines)


# -- main ----------------------------------------------------------------------------------------
PROG = "reproduce_soubaras.py"
#: ceilings on the work of one run, checked before anything runs (``--allow-large`` lifts them);
#: far above the documented run (the paper's 100 runs of 300 steps, N = 30, K = 2)
CEILINGS: dict[str, int] = {"--runs": 10_000, "--horizon": 10_000}
#: ceiling on the subsets C(N, K) brute force evaluates at every step (``--allow-large``)
SUBSETS_CEILING = 100_000
#: ceiling on the estimated memory of the kept per-step records (MiB; ``--allow-large``)
MEMORY_CEILING_MIB = 4096


def result_mib(args: argparse.Namespace) -> float:
    """Estimated memory (MiB) of the per-step records a run keeps (and stacks once more).

    Per run and step: each of the four played methods keeps its ``K`` picks and ~8 float64
    records, the ``all`` baseline 6 and the timed solvers 8; the aggregation copies them.
    """
    per_step = 2 * 8 * (4 * (args.k + 8) + 14)
    return float(args.runs) * (args.horizon + 1) * per_step / 2**20


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Command line (see the module docstring); usage errors are one line, exit 2."""
    p = UsageParser(prog=PROG, description=__doc__.split("\n")[0])
    c = CEILINGS
    p.add_argument(
        "--runs", type=int, default=None,
        help=f"Monte Carlo runs (paper: 100; at least 2; ceiling {c['--runs']:,})",
    )  # fmt: skip
    p.add_argument(
        "--horizon", type=int, default=None,
        help=f"filter steps at 10 Hz (300 = 30 s; at least 2; ceiling {c['--horizon']:,})",
    )  # fmt: skip
    p.add_argument(
        "--n-landmarks", type=int, default=30, help=f"landmarks N (1 to {MAX_LANDMARKS})"
    )
    p.add_argument(
        "--k", type=int, default=2,
        help=f"landmarks selected per step (1 to N; brute force evaluates C(N, K) subsets per "
        f"step, ceiling {SUBSETS_CEILING:,})",
    )  # fmt: skip
    add_executor_arguments(p, default="process", workers_alias=True)
    p.add_argument("--seed", type=int, default=DEFAULT_SEED, help="run r uses seed + r (>= 0)")
    p.add_argument("--out", type=Path, default=Path("docs/figures"))
    p.add_argument(
        "--quick",
        action="store_true",
        help=f"{QUICK_RUNS} runs, {QUICK_HORIZON} steps (for the test)",
    )
    p.add_argument(
        "--allow-large",
        action="store_true",
        help="run sizes above the ceilings (--runs, --horizon, C(N, K) as above; "
        f"{MEMORY_CEILING_MIB:,} MiB of kept records), which are there to catch typos",
    )
    args = p.parse_args(argv)
    if args.runs is None:
        args.runs = QUICK_RUNS if args.quick else 100
    if args.horizon is None:
        args.horizon = QUICK_HORIZON if args.quick else 300
    return args


def check_args(args: argparse.Namespace) -> None:
    """Every size and seed checked before any work (:class:`UsageError` naming the option).

    Validity: ``--runs`` >= 2, ``--horizon`` in ``[2, MAX_STEPS]``, ``--n-landmarks`` in
    ``[1, MAX_LANDMARKS]``, ``--k`` in ``[1, N]``, ``C(N, K)`` within brute force's guard,
    ``--seed`` >= 0. Work: ``--runs``, ``--horizon`` (:data:`CEILINGS`), ``C(N, K)``
    (:data:`SUBSETS_CEILING`) and the kept records (:data:`MEMORY_CEILING_MIB`), unless
    ``--allow-large``.
    """
    lifted = args.allow_large
    check_size("--runs", args.runs, low=2, note=" (paired standard errors need two runs)")
    check_size("--horizon", args.horizon, low=2, high=MAX_STEPS)
    check_size("--n-landmarks", args.n_landmarks, low=1, high=MAX_LANDMARKS)
    check_size("--k", args.k, low=1, high=args.n_landmarks, note=" (at most --n-landmarks)")
    subsets = math.comb(args.n_landmarks, args.k)
    what = f"--n-landmarks {args.n_landmarks} --k {args.k}"
    note = f" (C({args.n_landmarks}, {args.k}), brute force evaluates them at every step)"
    check_size(what, subsets, high=MAX_BRUTE_FORCE_SUBSETS, unit=" subsets", note=note)
    check_size(what, subsets, ceiling=SUBSETS_CEILING, lifted=lifted, unit=" subsets", note=note)
    for option in CEILINGS:
        value = getattr(args, option.removeprefix("--"))
        check_size(option, value, ceiling=CEILINGS[option], lifted=lifted)
    check_size(
        "--runs x --horizon",
        round(result_mib(args)),
        ceiling=MEMORY_CEILING_MIB,
        lifted=lifted,
        unit=" MiB",
        note=" (estimated memory of the kept records)",
    )
    check_size("--seed", args.seed, low=0)


def _check_out(folder: Path) -> None:
    """A real write probe of the output folder before any work (usage error: exit 2)."""
    try:
        probe_writable(folder / ".write-probe")
    except OSError as exc:
        raise UsageError(f"--out: {describe_os_error(exc, folder)}") from None


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the Monte Carlo study, write the figures, print the tables; return the numbers."""
    args = parse_args(argv)
    check_args(args)
    try:
        pool = executor_from_args(args)
    except ExecutorError as exc:
        raise UsageError(f"{exc}") from None
    _check_out(args.out)
    t0 = time.perf_counter()
    env_kwargs = {"n_landmarks": args.n_landmarks, "k": args.k, "horizon": args.horizon}
    tasks = [
        {"seed": args.seed + r, "env_kwargs": env_kwargs, "keep_geometry": r == 0}
        for r in range(args.runs)
    ]
    try:
        with pool:
            runs = run_all(tasks, pool)
    except ExecutorError as exc:  # an unreachable --address is found when Ray starts
        raise UsageError(" ".join(str(exc).split())) from None
    dt = float(gym.make(ENV_ID, **env_kwargs).unwrapped.config.dt)  # type: ignore[attr-defined]
    agg = aggregate(runs, dt, args.n_landmarks)
    paths = {name: args.out / f"{name}.png" for name in FIGURE_NAMES}
    plot_fig3(runs[0]["geometry"], runs[0]["brute_force"]["selections"], dt, paths["soubaras_fig3"])
    plot_fig4(agg, paths["soubaras_fig4"])
    plot_fig5(agg, paths["soubaras_fig5"])
    plot_fig6(agg, paths["soubaras_fig6"])
    wall = time.perf_counter() - t0
    agg["table2"] = table2_rows(agg)
    agg["figures"] = {k: str(v) for k, v in paths.items()}
    agg["config"] = {**vars(args), "out": str(args.out), "wall_time_s": wall}
    agg["executor"] = pool.describe()
    print(format_tables(agg))
    print(
        f"\nruns={args.runs} horizon={args.horizon} N={args.n_landmarks} K={args.k} "
        f"executor={args.executor} workers={pool.num_workers} seed={args.seed} "
        f"wall time {wall:.1f} s; figures in {args.out}"
    )
    return agg


if __name__ == "__main__":
    sys.exit(guarded_main(main, PROG))
