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
                                         [--allow-large]

``--bearing-sigma-deg``: relative range + bearing (m = 2, the exact PECMV is then an
optimisation); the learned methods use the m = 2 checkpoints (trained at 2 deg), and
``lpecmv_full`` and ``lpecmv_objective`` (no m = 2 checkpoints) are left out unless named in
``--methods``.

Sizes are checked before any work (exit 2, one line naming the option): ``--runs`` and
``--steps`` up to 10,000 and about 4 GiB of kept errors and NEES (:data:`CEILINGS`,
:data:`MEMORY_CEILING_MIB`); ``--allow-large`` lifts these ceilings. A learned method
without a shipped surrogate for the chosen noise is refused up front too.

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
from selenv.exits import UsageError, check_size, guarded_main
from selenv.families.cooperative.scenario import (
    MAX_STEPS,
    RANGES,
    CLConfig,
    CLSimulation,
    check_learned_fusion,
    make_cl_problem,
)
from selenv.learned.config import UsageParser
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


def _legend_below(fig: Figure, ax: Any) -> None:
    """One legend for both panels, below them, so it covers no curve."""
    handles, labels = ax.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=5, fontsize=8, frameon=False)


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
    _legend_below(fig, axes[0])
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
    _legend_below(fig, axes[0])
    save_figure(fig, path, dpi=120)


def format_tables(res: dict[str, dict[str, Any]], runs: int) -> str:
    """Table III (ours next to the paper's), NEES and time per update."""
    lo, hi = nees_band(runs)
    lines = [
        "| method | RMSE agent 1 (m) | RMSE agent 2 (m) | paper agent 1 | paper agent 2 |"
        " mean NEES agent 1 | mean NEES agent 2 | ms per relative update | s per run |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for m in res:
        r = res[m]
        p = PAPER_TABLE_III.get(m, ("", ""))
        lines.append(
            f"| {LABELS[m]} | {r['rmse'][0]:.4f} | {r['rmse'][1]:.4f} | {p[0]} | {p[1]} "
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


PROG = "reproduce_chen_kia.py"
#: ceilings on the work of one run, checked before anything runs (``--allow-large`` lifts them);
#: far above the documented runs (50 runs of 600 steps, 200 runs on a cluster)
CEILINGS: dict[str, int] = {"--runs": 10_000, "--steps": 10_000}
#: ceiling on the estimated memory of the kept errors and NEES (MiB; ``--allow-large``)
MEMORY_CEILING_MIB = 4096


def result_mib(runs: int, steps: int, n_methods: int) -> float:
    """Estimated memory (MiB) of the errors and NEES kept per run, step, method and agent.

    Two float64 arrays per agent (two agents), stacked once more when the runs are gathered.
    """
    return float(runs) * steps * n_methods * 2 * 2 * 8 * 2 / 2**20


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Command line (see the module docstring); usage errors are one line, exit 2."""
    ap = UsageParser(prog=PROG, description=__doc__.split("\n")[0])
    c = CEILINGS
    ap.add_argument("--runs", type=int, default=50,
                    help=f"Monte Carlo runs (paper: 50; ceiling {c['--runs']:,})")  # fmt: skip
    ap.add_argument("--steps", type=int, default=600,
                    help=f"steps of 0.1 s (ceiling {c['--steps']:,})")  # fmt: skip
    add_executor_arguments(ap, default="process", workers_alias=True)
    ap.add_argument("--out", type=Path, default=Path("docs/figures"))
    ap.add_argument("--quick", action="store_true", help="4 runs of 150 steps (for tests)")
    low, high, _ = RANGES["bearing_sigma_deg"]
    ap.add_argument("--bearing-sigma-deg", type=float, default=None,
                    help=f"relative bearing noise (deg, in [{low:g}, {high:g}]): range + "
                         "bearing, m = 2 (default: range only)")  # fmt: skip
    ap.add_argument("--methods", default="",
                    help="comma-separated subset of " + ",".join(METHODS) + " (default: all; "
                         "without " + ", ".join(RANGE_ONLY) + " with bearings)")  # fmt: skip
    ap.add_argument("--allow-large", action="store_true",
                    help="run sizes above the ceilings (--runs, --steps as above; "
                         f"{MEMORY_CEILING_MIB:,} MiB of kept errors and NEES), which are "
                         "there to catch typos")  # fmt: skip
    args = ap.parse_args(argv)
    if args.quick:
        args.runs, args.steps = 4, 150
    args.methods = tuple(x for x in args.methods.split(",") if x) or tuple(
        m for m in METHODS if args.bearing_sigma_deg is None or m not in RANGE_ONLY
    )
    return args


def check_args(args: argparse.Namespace) -> None:
    """Every size, noise and method checked before any work (:class:`UsageError`).

    Validity: ``--runs`` >= 1, ``--steps`` in ``[1, MAX_STEPS]``, ``--bearing-sigma-deg``
    finite in the scenario's range, known ``--methods``. Work: ``--runs``, ``--steps``
    (:data:`CEILINGS`) and the kept results (:data:`MEMORY_CEILING_MIB`), unless
    ``--allow-large``. The learned methods' checkpoints are checked last (see
    :func:`check_methods`).
    """
    lifted = args.allow_large
    check_size("--runs", args.runs, low=1)
    check_size("--steps", args.steps, low=1, high=MAX_STEPS)
    if args.bearing_sigma_deg is not None:
        low, high, _ = RANGES["bearing_sigma_deg"]
        check_size("--bearing-sigma-deg", args.bearing_sigma_deg, low=low, high=high)
    unknown = sorted(set(args.methods) - set(METHODS))
    if unknown:
        raise UsageError(f"--methods: unknown {unknown}; known: {','.join(METHODS)}")
    for option in CEILINGS:
        value = getattr(args, option.removeprefix("--"))
        check_size(option, value, ceiling=CEILINGS[option], lifted=lifted)
    check_size(
        "--runs x --steps",
        round(result_mib(args.runs, args.steps, len(args.methods))),
        ceiling=MEMORY_CEILING_MIB,
        lifted=lifted,
        unit=" MiB",
        note=f" (estimated memory of the kept errors and NEES of {len(args.methods)} methods)",
    )


def check_methods(methods: Sequence[str], bearing_sigma_deg: float | None) -> None:
    """Each learned method of ``methods`` has a shipped surrogate for the relative noise.

    Loads the surrogates (what the runs would do first), so call it after the cheap checks.

    Raises:
        UsageError: naming the method, ``--bearing-sigma-deg`` and the exact alternatives.
    """
    cfg = CLConfig(horizon=1, bearing_sigma_deg=bearing_sigma_deg)
    for m in methods:
        try:
            check_learned_fusion(cfg, m)
        except ValueError:
            noise = (
                "range only (no --bearing-sigma-deg)"
                if bearing_sigma_deg is None
                else f"--bearing-sigma-deg {bearing_sigma_deg:g}"
            )
            raise UsageError(
                f"--methods: {m} has no shipped surrogate for {noise}; "
                "name others with --methods (exact: dead_reckoning,naive,ci,dmv,pecmv)"
            ) from None


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run, plot, print; return the numbers."""
    args = parse_args(argv)
    check_args(args)
    methods = args.methods
    check_methods(methods, args.bearing_sigma_deg)
    try:
        pool = executor_from_args(args)
    except ExecutorError as exc:
        raise UsageError(f"{exc}") from None
    _check_out(args.out)
    t0 = time.perf_counter()
    try:
        with pool:
            res = run_all(args.runs, args.steps, pool, methods, args.bearing_sigma_deg)
    except ExecutorError as exc:  # an unreachable --address is found when Ray starts
        raise UsageError(" ".join(str(exc).split())) from None
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
    sys.exit(guarded_main(main, PROG))
