"""Reproduce Chen & Kia (2022) Table III and Fig. 8 in simulation: CL with unknown correlation.

Two pedestrians with 9-state INS (agent 1 accurate and ranging to beacons, agent 2 less
accurate), relative ranges both ways every 0.5 s, each agent processing them with
``dead_reckoning`` (no updates: the paper's "ZUPT-only"), ``naive``, ``ci``, ``dmv`` or
``pecmv`` (:mod:`selenv.families.cooperative.scenario`). Monte Carlo over seeds (the same noise for
every method), position RMSE per agent (Table III) and the horizontal-position NEES with its
95 % chi-square band (Fig. 8).

Usage::

    python scripts/reproduce_chen_kia.py [--runs 50] [--steps 600] [--workers 2] [--quick]
                                         [--executor local|process|ray] [--address ADDR]
                                         [--bearing-sigma-deg 2] [--methods dmv,pecmv,...]

``--bearing-sigma-deg``: relative range + bearing (m = 2, the exact PECMV is then an
optimisation); the learned methods use the m = 2 checkpoints (trained at 2 deg), and
``lpecmv_full`` and ``lpecmv_objective`` (no m = 2 checkpoints) are left out unless named in
``--methods``.

Writes ``chen_kia_fig8.png`` and ``chen_kia_rmse.png`` into ``--out`` and prints Markdown
tables; ``main(argv)`` returns the numbers. Results: ``docs/reproductions/chen_kia.md``.
"""

from __future__ import annotations

import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # tiny matrices: threads only contend

import argparse
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from scipy.stats import chi2

from selenv.atomic import describe_os_error, probe_writable, save_figure
from selenv.exits import UsageError, guarded_main
from selenv.families.cooperative.scenario import CLConfig, CLSimulation, make_cl_problem
from selenv.parallel import Executor, ExecutorError, add_executor_arguments, executor_from_args

METHODS = (
    "dead_reckoning", "naive", "ci", "dmv", "pecmv", "ldmv", "lpecmv", "lpecmv_full",
    "lpecmv_objective",
)  # fmt: skip
#: methods without an m = 2 (range + bearing) checkpoint, left out with --bearing-sigma-deg
RANGE_ONLY = ("lpecmv_full", "lpecmv_objective")
LABELS = {
    "dead_reckoning": "dead reckoning (ZUPT-only)",
    "naive": "naive EKF",
    "ci": "CI",
    "dmv": "DMV",
    "pecmv": "PECMV",
    "ldmv": "LDMV (learned)",
    "lpecmv": "LPECMV (learned, method 3)",
    "lpecmv_full": "LPECMV (learned, method 1)",
    "lpecmv_objective": "LPECMV (learned, method 3, objective loss)",
}
#: the paper's Table III (real experiment, 10 runs): method -> (agent 1, agent 2) RMSE (m)
PAPER_TABLE_III = {
    "dead_reckoning": (0.4732, 0.4902),
    "dmv": (0.1050, 0.3221),
    "pecmv": (0.1035, 0.2950),
    "ldmv": (0.1158, 0.3528),
    "lpecmv": (0.1125, 0.3027),
}


def run_one(task: tuple[Any, ...]) -> dict[str, Any]:
    """One Monte Carlo run of one method: errors, NEES and relative-update time per step.

    ``task``: ``(seed, steps, method)`` or ``(seed, steps, method, bearing_sigma_deg)``.
    """
    seed, steps, method = task[:3]
    bearing = task[3] if len(task) > 3 else None
    t_run = time.perf_counter()
    cfg = CLConfig(horizon=steps, bearing_sigma_deg=bearing)
    sim = CLSimulation(make_cl_problem(cfg, np.random.default_rng(seed)), method)
    err, nees = np.empty((steps, cfg.n_agents)), np.empty((steps, cfg.n_agents))
    t_rel, n_rel = 0.0, 0
    for k in range(steps):
        sim.predict()
        sim.zupt_updates()
        sim.beacon_updates()
        if method != "dead_reckoning":
            for p in sim.available():
                t0 = time.perf_counter()
                sim.relative_update(p)
                t_rel += time.perf_counter() - t0
                n_rel += 1
        err[k], nees[k] = sim.position_errors(), sim.nees_position()
    t_run = time.perf_counter() - t_run
    return {"err": err, "nees": nees, "t_rel": t_rel, "n_rel": n_rel, "t_run": t_run}


def run_all(
    runs: int,
    steps: int,
    pool: Executor,
    methods: Sequence[str] = METHODS,
    bearing_sigma_deg: float | None = None,
) -> dict[str, dict[str, Any]]:
    """Every method on seeds ``0 .. runs - 1`` (paired), on ``pool`` (local, processes, Ray).

    Per method: ``err``, ``nees`` (runs, steps, A), ``rmse`` and ``mean_nees`` (A,), the time
    per relative update and per run.
    """
    tasks = [(seed, steps, m, bearing_sigma_deg) for m in methods for seed in range(runs)]
    out = pool.map(run_one, tasks, desc="CL runs", unit="run")
    res: dict[str, dict[str, Any]] = {}
    for i, m in enumerate(methods):
        chunk = out[i * runs : (i + 1) * runs]
        err = np.stack([c["err"] for c in chunk])  # (runs, steps, A)
        nees = np.stack([c["nees"] for c in chunk])
        n_rel = sum(c["n_rel"] for c in chunk)
        res[m] = {
            "err": err,
            "nees": nees,
            "rmse": np.sqrt(np.mean(err**2, axis=(0, 1))),
            "mean_nees": nees.mean(axis=(0, 1)),
            "ms_per_update": 1e3 * sum(c["t_rel"] for c in chunk) / n_rel if n_rel else 0.0,
            "s_per_run": float(np.mean([c["t_run"] for c in chunk])),
        }
    return res


def nees_band(runs: int, dof: int = 2) -> tuple[float, float]:
    """Two-sided 95 % band of the mean NEES over ``runs`` runs (Bar-Shalom)."""
    return (
        float(chi2.ppf(0.025, dof * runs) / runs),
        float(chi2.ppf(0.975, dof * runs) / runs),
    )


def plot_nees(res: dict[str, dict[str, Any]], runs: int, dt: float, path: Path) -> None:
    """Fig. 8: mean NEES over the runs per agent, with the 95 % band."""
    lo, hi = nees_band(runs)
    fig = Figure(figsize=(12, 4.5), constrained_layout=True)
    axes = fig.subplots(1, 2, sharey=True)
    for a, ax in enumerate(axes):
        for m in res:
            nees = res[m]["nees"][:, :, a].mean(axis=0)
            ax.plot(np.arange(nees.size) * dt, nees, lw=1, label=LABELS[m])
        ax.axhspan(lo, hi, color="grey", alpha=0.25, label=f"95 % band [{lo:.2f}, {hi:.2f}]")
        ax.set(yscale="log", xlabel="time (s)", title=f"agent {a + 1}: position NEES, {runs} runs")
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("mean NEES (2 dof)")
    axes[0].legend(fontsize=8)
    save_figure(fig, path, dpi=120)


def plot_rmse(res: dict[str, dict[str, Any]], dt: float, path: Path) -> None:
    """Position RMSE over time per agent (Fig. 9's accuracy, as curves)."""
    fig = Figure(figsize=(12, 4.5), constrained_layout=True)
    axes = fig.subplots(1, 2, sharey=True)
    for a, ax in enumerate(axes):
        for m in res:
            rmse = np.sqrt(np.mean(res[m]["err"][:, :, a] ** 2, axis=0))
            ax.plot(np.arange(rmse.size) * dt, rmse, lw=1, label=LABELS[m])
        ax.set(yscale="log", xlabel="time (s)", title=f"agent {a + 1}: position RMSE")
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("RMSE (m)")
    axes[0].legend(fontsize=8)
    save_figure(fig, path, dpi=120)


def format_tables(res: dict[str, dict[str, Any]], runs: int) -> str:
    """Table III (ours next to the paper's), NEES and time per update."""
    lo, hi = nees_band(runs)
    lines = [
        "| method | RMSE agent 1 (m) | RMSE agent 2 (m) | paper agent 1 | paper agent 2 |"
        " | mean NEES agent 1 | mean NEES agent 2 | ms per relative update | s per run |",
        "|---|---:|---:|---:|---:|---|---:|---:|---:|---:|",
    ]
    for m in res:
        r = res[m]
        p = PAPER_TABLE_III.get(m, ("", ""))
        lines.append(
            f"| {LABELS[m]} | {r['rmse'][0]:.4f} | {r['rmse'][1]:.4f} | {p[0]} | {p[1]} | "
            f"| {r['mean_nees'][0]:.2f} | {r['mean_nees'][1]:.2f} | {r['ms_per_update']:.3f} "
            f"| {r['s_per_run']:.2f} |"
        )
    lines.append(f"\n95 % NEES band for {runs} runs, 2 dof: [{lo:.2f}, {hi:.2f}]")
    return "\n".join(lines)


def _check_out(folder: Path) -> None:
    """A real write probe of the output folder before any work (usage error: exit 2)."""
    try:
        probe_writable(folder / ".write-probe")
    except OSError as exc:
        raise UsageError(f"--out: {describe_os_error(exc, folder)}") from None


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run, plot, print; return the numbers."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=50, help="Monte Carlo runs (paper Fig. 8: 50)")
    ap.add_argument("--steps", type=int, default=600, help="steps of 0.1 s")
    add_executor_arguments(ap, default="process", workers_alias=True)
    ap.add_argument("--out", type=Path, default=Path("docs/figures"))
    ap.add_argument("--quick", action="store_true", help="4 runs of 150 steps (for tests)")
    ap.add_argument("--bearing-sigma-deg", type=float, default=None,
                    help="relative bearing noise (deg): range + bearing, m = 2 (default: range "
                         "only)")  # fmt: skip
    ap.add_argument("--methods", default="",
                    help="comma-separated subset of " + ",".join(METHODS) + " (default: all; "
                         "without " + ", ".join(RANGE_ONLY) + " with bearings)")  # fmt: skip
    args = ap.parse_args(argv)
    if args.quick:
        args.runs, args.steps = 4, 150
    methods = tuple(x for x in args.methods.split(",") if x) or tuple(
        m for m in METHODS if args.bearing_sigma_deg is None or m not in RANGE_ONLY
    )
    unknown = sorted(set(methods) - set(METHODS))
    if unknown:
        raise UsageError(f"unknown --methods {unknown}")
    try:
        pool = executor_from_args(args)
    except ExecutorError as exc:
        raise UsageError(f"{exc}") from None
    _check_out(args.out)
    t0 = time.perf_counter()
    with pool:
        res = run_all(args.runs, args.steps, pool, methods, args.bearing_sigma_deg)
    dt = CLConfig().dt
    tag = "" if args.bearing_sigma_deg is None else "_m2"
    paths = {
        "fig8": args.out / f"chen_kia_fig8{tag}.png",
        "rmse": args.out / f"chen_kia_rmse{tag}.png",
    }
    plot_nees(res, args.runs, dt, paths["fig8"])
    plot_rmse(res, dt, paths["rmse"])
    wall = time.perf_counter() - t0
    print(format_tables(res, args.runs))
    print(f"\nruns={args.runs} steps={args.steps} wall time {wall:.1f} s")
    return {
        "results": res,
        "figures": {k: str(v) for k, v in paths.items()},
        "wall": wall,
        "band": nees_band(args.runs),
        "runs": args.runs,
        "executor": pool.describe(),
    }


if __name__ == "__main__":
    sys.exit(guarded_main(main, "reproduce_chen_kia.py"))
