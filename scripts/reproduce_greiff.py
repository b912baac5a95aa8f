"""Reproduce Sec. IV of Greiff, Di Cairano & Berntorp (2022): Fig. 3, Table II and Fig. 4.

Every run plays ``selenv/ReceiverClustering-v1`` with ``preset="paper"`` (fixed ``sigma`` per
realisation, as in the paper) with the registered agents (the same code as ``selenv bench``):

* **Fig. 3** (n = 30, N_max = 14, one noise realisation): cost over K steps of singletons,
  a fixed random clustering (Monte Carlo over initial clusterings, mean and 2-sigma band), the
  GA (Algorithm 2, switched on at k = 50) from the same initial clusterings, and the single
  cluster (the unconstrained lower bound); plus the J_G, J_C, J_L components.
* **Table II**: the GA with each operator removed (the O vector), Monte Carlo over noise
  realisations and initial clusterings (paired: the same seeds for every O); ``k*_eps`` for
  eps = 0.1, 0.05, 0.01 and ``E[J(I_K)]``, ``Var[J(I_K)]``.
* **Fig. 4** (N_max = 42, initial 15 clusters of 2): number of clusters, cost and the best
  assignment over time.

``--ga-variant`` picks the GA's Table I operators (``GAConfig.variant``): ``improved`` (default,
ours: aligned crossovers, O1M may open a singleton), ``literal`` (Table I as printed) or
``both``: Table II and Fig. 4 for each variant on the same seeds (Fig. 3 with ``improved``),
printed one after the other; the literal figures get a ``_literal`` suffix.

Usage::

    python scripts/reproduce_greiff.py [--runs 100] [--table-runs 50] [--steps 500]
                                       [--workers 2] [--seed 2022] [--out docs/figures] [--quick]
                                       [--ga-variant improved|literal|both] [--allow-large]
    # the paper's 1000 runs per setting, on a Ray cluster (`ray start --head` on the head node):
    python scripts/reproduce_greiff.py --runs 1000 --table-runs 1000 \
        --executor ray --address HOST:6379

Runs are spread over ``--workers`` local processes (``--executor process``, the default), this
process (``--executor local``) or Ray tasks (``--executor ray [--address ADDR]``), with a progress
bar; run ``i`` is seeded from ``--seed`` and ``i`` only, so the numbers do not depend on the
executor. ``main(argv)`` returns the
numbers as a dict and prints Markdown tables. Results: ``docs/reproductions/greiff.md``.

Sizes are checked before any work (exit 2, one line naming the option): ``--runs`` and
``--table-runs`` up to 10,000, ``--steps`` up to 10,000 (the env allows 100,000) and about
4 GiB of kept cost curves (:data:`CEILINGS`, :data:`MEMORY_CEILING_MIB`); ``--allow-large``
lifts these ceilings.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from matplotlib.figure import Figure

import selenv  # noqa: F401  (registers the env and the agents)
from selenv.agents import make as make_agent
from selenv.atomic import describe_os_error, probe_writable, save_figure
from selenv.exits import UsageError, check_size, guarded_main
from selenv.families.clustering.env import MAX_STEPS
from selenv.families.clustering.ga import align_labels
from selenv.families.clustering.labels import random_feasible_clustering
from selenv.families.clustering.scenario import ClusteringConfig, make_clustering_problem
from selenv.learned.config import UsageParser
from selenv.parallel import Executor, ExecutorError, add_executor_arguments, executor_from_args
from selenv.parallel.store import ResultStore, resumable_map

ENV_ID = "selenv/ReceiverClustering-v1"
#: the paper's noise model: ``sigma`` fixed per realisation (the env's default is time-varying)
PAPER_PRESET = {"preset": "paper"}
GA_START = 50  #: the paper switches the GA on at k = 50
GA_VARIANTS = ("improved", "literal")  #: GAConfig.variant values; ``--ga-variant both`` runs each
OPERATOR_SETS: tuple[tuple[int, ...], ...] = (
    (0, 1, 1, 1, 1),
    (1, 0, 1, 1, 1),
    (1, 1, 0, 1, 1),
    (1, 1, 1, 0, 1),
    (1, 1, 1, 1, 0),
    (1, 1, 1, 1, 1),
)
#: the paper's Table II: O -> (k*_0.1, k*_0.05, k*_0.01, E[J(I_K)])
PAPER_TABLE_II = {
    (0, 1, 1, 1, 1): (71, 94, 203, 0.1775),
    (1, 0, 1, 1, 1): (73, 99, 201, 0.1775),
    (1, 1, 0, 1, 1): (77, 107, 248, 0.1780),
    (1, 1, 1, 0, 1): (70, 91, 194, 0.1774),
    (1, 1, 1, 1, 0): (71, 93, 182, 0.1776),
    (1, 1, 1, 1, 1): (72, 94, 203, 0.1773),
}
EPSILONS = (0.1, 0.05, 0.01)


# -- one episode (runs in a worker process) ------------------------------------------------------
def run_episode(task: dict[str, Any]) -> dict[str, np.ndarray]:
    """Play one episode; return the cost components per step and optionally the labels.

    ``task``: ``env_kwargs``, ``seed``, ``agent`` (``"keep"`` or a registry name),
    ``agent_kwargs``, ``clustering`` (initial labels or None), ``record_labels``.
    """
    env = gym.make(ENV_ID, **{**PAPER_PRESET, **task["env_kwargs"]})
    options = None if task.get("clustering") is None else {"clustering": task["clustering"]}
    obs, info = env.reset(seed=task["seed"], options=options)
    agent = None
    if task["agent"] != "keep":
        agent = make_agent(task["agent"], ENV_ID, **task.get("agent_kwargs", {}))
        agent.reset(env, seed=task["seed"])
    rows = [(info["objective"], info["J_G"], info["J_C"], info["J_L"], info["n_clusters"])]
    labels = [obs["assignment"].copy()]
    done = False
    while not done:
        action = obs["assignment"] if agent is None else agent.act(obs, info)
        obs, _, terminated, truncated, info = env.step(action)
        rows.append((info["objective"], info["J_G"], info["J_C"], info["J_L"], info["n_clusters"]))
        if task.get("record_labels"):
            labels.append(obs["assignment"].copy())
        done = terminated or truncated
    arr = np.array(rows)
    out = {"J": arr[:, 0], "J_G": arr[:, 1], "J_C": arr[:, 2], "J_L": arr[:, 3], "m": arr[:, 4]}
    if task.get("record_labels"):
        out["labels"] = np.array(labels)
    return out


def run_all(
    tasks: list[dict[str, Any]], pool: Executor, desc: str, store: ResultStore | None = None
) -> list[dict[str, np.ndarray]]:
    """Run tasks on ``pool`` (local, process pool or Ray; results in task order) with a bar.

    With ``store`` (``--store``), runs it already holds are read back instead of run and new
    runs are written to it as they finish, so an interrupted command resumes where it stopped.
    """
    return resumable_map(pool, run_episode, tasks, store, desc=desc, unit="run")


# -- experiments ---------------------------------------------------------------------------------
def ga_kwargs(variant: str, **extra: Any) -> dict[str, Any]:
    """The GA's agent keywords: on at ``GA_START``, ``variant`` only when not the default."""
    kwargs = {"start_step": GA_START, **extra}
    return kwargs if variant == "improved" else {**kwargs, "variant": variant}


def fig3_experiment(
    args: argparse.Namespace, sigma: np.ndarray, variant: str = "improved"
) -> dict[str, Any]:
    """Singletons, fixed random (MC), GA from the same starts (MC), single cluster."""
    base = {"sigma": sigma, "horizon": args.steps}
    rng = np.random.default_rng(args.seed)
    starts = [random_feasible_clustering(30, 3, rng) for _ in range(args.runs)]
    tasks = [
        {"env_kwargs": base, "seed": r, "agent": "keep", "clustering": s}
        for r, s in enumerate(starts)
    ]
    tasks += [
        {
            "env_kwargs": base,
            "seed": r,
            "agent": "ga",
            "agent_kwargs": ga_kwargs(variant),
            "clustering": s,
        }
        for r, s in enumerate(starts)
    ]
    tasks.append({"env_kwargs": base, "seed": 0, "agent": "keep", "clustering": np.arange(30)})
    tasks.append(
        {
            "env_kwargs": {**base, "n_max_states": None},
            "seed": 0,
            "agent": "keep",
            "clustering": np.zeros(30, int),
        }
    )
    res = run_all(tasks, args.pool, "Fig. 3", args.result_store)
    R = args.runs
    stack = lambda rs, key: np.stack([r[key] for r in rs])  # noqa: E731
    out: dict[str, Any] = {}
    for name, rs in (("fixed_random", res[:R]), ("ga", res[R : 2 * R])):
        out[name] = {key: stack(rs, key) for key in ("J", "J_G", "J_C", "J_L")}
    out["singletons"] = res[2 * R]
    out["single_cluster"] = res[2 * R + 1]
    return out


def k_star(J: np.ndarray, eps: float) -> int:
    """``min{k : E[(J_k - J_K) / J_K] <= eps}`` over runs (rows), k counted from 0."""
    gap = np.mean((J - J[:, -1:]) / J[:, -1:], axis=0)
    return int(np.flatnonzero(gap <= eps)[0])


def k_star_bootstrap(
    Js: dict[tuple[int, ...], np.ndarray],
    eps: float,
    reference: tuple[int, ...],
    n_boot: int = 2000,
    seed: int = 0,
) -> dict[tuple[int, ...], dict[str, tuple[float, float]]]:
    """Percentile bootstrap 95 % intervals of ``k*_eps`` and of its paired difference.

    The difference is to ``reference`` (the all-operators row).

    ``Js`` maps each O vector to its ``(runs, K + 1)`` cost curves; row ``r`` of every set is the
    same realisation (seed ``10000 + r``), so one resample of the row indices is applied to all
    sets (a paired bootstrap). Returns ``{O: {"k": (lo, hi), "diff": (lo, hi)}}``.
    """
    runs = next(iter(Js.values())).shape[0]
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, runs, size=(n_boot, runs))
    ks = {ops: np.array([k_star(J[i], eps) for i in idx]) for ops, J in Js.items()}
    out = {}
    for ops, k in ks.items():
        diff = k - ks[reference]
        out[ops] = {
            "k": tuple(float(v) for v in np.percentile(k, [2.5, 97.5])),
            "diff": tuple(float(v) for v in np.percentile(diff, [2.5, 97.5])),
        }
    return out


def paired_final_cost(J: np.ndarray, J_ref: np.ndarray) -> tuple[float, float, float]:
    """Mean and 95 % t interval of the per-realisation difference ``J_K - J_ref,K``."""
    from scipy import stats

    d = J[:, -1] - J_ref[:, -1]
    if d.size < 2:
        return float(d.mean()), float("nan"), float("nan")
    half = float(stats.t.ppf(0.975, d.size - 1) * d.std(ddof=1) / np.sqrt(d.size))
    return float(d.mean()), float(d.mean() - half), float(d.mean() + half)


def table2_experiment(
    args: argparse.Namespace, variant: str = "improved"
) -> dict[tuple[int, ...], dict[str, Any]]:
    """GA with each operator set; the same realisations (seeds) for every set and variant."""
    base = {"horizon": args.steps}
    tasks = [
        {
            "env_kwargs": base,
            "seed": 10_000 + r,
            "agent": "ga",
            "agent_kwargs": ga_kwargs(variant, operators=ops),
        }
        for ops in OPERATOR_SETS
        for r in range(args.table_runs)
    ]
    label = "Table II" + ("" if variant == "improved" else f" ({variant})")
    res = run_all(tasks, args.pool, label, args.result_store)
    out = {}
    for i, ops in enumerate(OPERATOR_SETS):
        J = np.stack([r["J"] for r in res[i * args.table_runs : (i + 1) * args.table_runs]])
        out[ops] = {
            "J": J,
            "k_star": tuple(k_star(J, e) for e in EPSILONS),
            "mean_JK": float(J[:, -1].mean()),
            "var_JK": float(J[:, -1].var()),
        }
    all_ops = OPERATOR_SETS[-1]
    boot = k_star_bootstrap({ops: r["J"] for ops, r in out.items()}, EPSILONS[-1], all_ops)
    for ops, r in out.items():
        r["k_star_ci"] = boot[ops]["k"]
        r["k_star_diff_ci"] = boot[ops]["diff"]
        r["JK_diff"] = paired_final_cost(r["J"], out[all_ops]["J"])
    return out


def fig4_experiment(
    args: argparse.Namespace, sigma: np.ndarray, variant: str = "improved"
) -> dict[str, Any]:
    """N_max = 42 from 15 clusters of 2, GA on from k = 50; one run with the labels."""
    rng = np.random.default_rng(args.seed + 1)
    start = random_feasible_clustering(30, 2, rng)  # 15 clusters of 2
    task = {
        "env_kwargs": {"sigma": sigma, "horizon": args.steps, "n_max_states": 42},
        "seed": 0,
        "agent": "ga",
        "agent_kwargs": ga_kwargs(variant),
        "clustering": start,
        "record_labels": True,
    }
    return run_episode(task)


# -- figures -------------------------------------------------------------------------------------
def plot_fig3(res: dict[str, Any], path: Path) -> None:
    """Cost over time (left) and its three components (right), as the paper's Fig. 3."""
    fig = Figure(figsize=(13, 5.5), constrained_layout=True)
    grid = fig.add_gridspec(3, 2, width_ratios=(1.6, 1))
    ax = fig.add_subplot(grid[:, 0])
    comps = [fig.add_subplot(grid[i, 1]) for i in range(3)]
    k = np.arange(res["singletons"]["J"].size)
    styles = (
        ("singletons", "tab:blue", "singletons (m = n)"),
        ("fixed_random", "black", "fixed random clustering (mean, 2σ band)"),
        ("ga", "tab:red", f"GA from the same starts, on at k = {GA_START} (mean, 2σ band)"),
        ("single_cluster", "tab:green", "single cluster (no constraint): lower bound"),
    )
    for key, color, label in styles:
        for a, comp in zip([ax, *comps], ("J", "J_G", "J_C", "J_L"), strict=True):
            data = res[key][comp]
            if data.ndim == 2:
                mean, std = data.mean(axis=0), data.std(axis=0)
                a.fill_between(k, mean - 2 * std, mean + 2 * std, color=color, alpha=0.2, lw=0)
                data = mean
            a.plot(k, data, color=color, lw=1.5, label=label if a is ax else None)
    runs = res["ga"]["J"].shape[0]
    ax.set(xlabel="time step k", ylabel="J (eq. 10)", yscale="log")
    ax.set_title(f"Fig. 3: n = 30, N_max = 14, {runs} Monte Carlo runs")
    ax.legend(fontsize=8)
    for a, comp in zip(comps, ("J_G", "J_C", "J_L"), strict=True):
        a.set(ylabel=comp, yscale="log")
        a.grid(alpha=0.3)
    comps[-1].set_xlabel("time step k")
    ax.grid(alpha=0.3, which="both")
    save_figure(fig, path, dpi=120)


def plot_table2(res: dict[tuple[int, ...], dict[str, Any]], path: Path) -> None:
    """Mean relative gap to the final cost per operator set (the convergence behind Table II)."""
    fig = Figure(figsize=(8, 4.5), constrained_layout=True)
    ax = fig.add_subplot()
    for ops, r in res.items():
        J = r["J"]
        gap = np.mean((J - J[:, -1:]) / J[:, -1:], axis=0)
        ax.plot(gap, lw=1.2, label=f"O = {ops}")
    for e in EPSILONS:
        ax.axhline(e, color="grey", lw=0.8, ls=":")
    ax.set(xlabel="time step k", ylabel="E[(J_k - J_K) / J_K]", yscale="log", ylim=(1e-3, None))
    runs = next(iter(res.values()))["J"].shape[0]
    ax.set_title(f"Table II: convergence by GA operator set ({runs} realisations each)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    save_figure(fig, path, dpi=120)


def plot_fig4(res: dict[str, Any], path: Path) -> None:
    """Cluster count, cost and the assignment image over time (the paper's Fig. 4)."""
    labels = res["labels"].copy()
    for t in range(1, len(labels)):  # keep colours stable: align each step to the previous one
        labels[t] = align_labels(labels[t - 1], labels[t])
    fig = Figure(figsize=(10, 8), constrained_layout=True)
    ax1, ax2, ax3 = fig.subplots(3, 1, sharex=True, height_ratios=(1, 1, 1.6))
    k = np.arange(len(res["J"]))
    ax1.plot(k, res["m"], color="tab:blue")
    ax1.set(ylabel="number of clusters")
    ax2.plot(k, res["J"], color="tab:red")
    ax2.set(ylabel="J (eq. 10)", yscale="log")
    order = np.argsort(labels[-1], kind="stable")  # receivers grouped by their final cluster
    ax3.imshow(
        labels[:, order].T, aspect="auto", interpolation="nearest", cmap="tab20", origin="lower"
    )
    ax3.set(xlabel="time step k", ylabel="receiver (sorted by final cluster; colour: cluster)")
    ax1.set_title(f"Fig. 4: N_max = 42, GA on at k = {GA_START}; final J = {res['J'][-1]:.4f}")
    for a in (ax1, ax2):
        a.grid(alpha=0.3)
    save_figure(fig, path, dpi=120)


# -- main ----------------------------------------------------------------------------------------
def format_tables(results: dict[str, Any]) -> str:
    """Markdown tables of the three experiments."""
    f3 = results["fig3"]
    v3 = results.get("fig3_variant", "improved")
    lines = [
        "### Fig. 3: J at k = K" + ("" if v3 == "improved" else f" (GA variant: {v3})"),
        "",
        "| clustering | E[J(I_K)] | Var[J(I_K)] |",
        "|---|---:|---:|",
    ]
    for key in ("singletons", "fixed_random", "ga", "single_cluster"):
        J = np.atleast_2d(f3[key]["J"])[:, -1]
        lines.append(f"| {key} | {J.mean():.4f} | {J.var():.2e} |")
    for variant, res in results["by_variant"].items():
        lines += format_variant(res, "" if variant == "improved" else f" (GA variant: {variant})")
    return "\n".join(lines)


def format_variant(results: dict[str, Any], title: str) -> list[str]:
    """Markdown Table II and Fig. 4 lines of one GA variant; ``title`` ends each heading."""
    lines = [
        "",
        f"### Table II{title}",
        "",
        "| O | k*_0.1 | k*_0.05 | k*_0.01 [95 % CI] | k*_0.01 - all [95 % CI] | E[J(I_K)] "
        "| J_K - all, paired [95 % CI] | Var[J(I_K)] | paper k* | paper E[J] |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|---:|",
    ]
    for ops, r in results["table2"].items():
        p = PAPER_TABLE_II[ops]
        k1, k2, k3 = r["k_star"]
        (lo, hi), (dlo, dhi) = r["k_star_ci"], r["k_star_diff_ci"]
        jd, jlo, jhi = r["JK_diff"]
        ref = ops == OPERATOR_SETS[-1]
        kdiff = "reference" if ref else f"[{dlo:+.0f}, {dhi:+.0f}]"
        jdiff = "reference" if ref else f"{jd:+.4f} [{jlo:+.4f}, {jhi:+.4f}]"
        lines.append(
            f"| {ops} | {k1} | {k2} | {k3} [{lo:.0f}, {hi:.0f}] | {kdiff} | "
            f"{r['mean_JK']:.4f} | {jdiff} | {r['var_JK']:.2e} | "
            f"{p[0]} / {p[1]} / {p[2]} | {p[3]} |"
        )
    f4 = results["fig4"]
    first3 = np.flatnonzero(f4["m"] <= 3)
    lines += [
        "",
        f"### Fig. 4 (N_max = 42){title}",
        "",
        f"final J = {f4['J'][-1]:.4f}; clusters at k = K: {int(f4['m'][-1])}; "
        f"sizes {sorted(np.bincount(f4['labels'][-1]).tolist(), reverse=True)}; "
        f"first k with <= 3 clusters: {int(first3[0]) if first3.size else 'never'}",
    ]
    return lines


PROG = "reproduce_greiff.py"
#: ceilings on the work of one run, checked before anything runs (``--allow-large`` lifts them);
#: far above the documented runs (the paper's 1000 runs per setting, K = 500)
CEILINGS: dict[str, int] = {"--runs": 10_000, "--table-runs": 10_000, "--steps": 10_000}
#: ceiling on the estimated memory of the kept cost curves (MiB; ``--allow-large`` lifts it)
MEMORY_CEILING_MIB = 4096


def result_mib(args: argparse.Namespace) -> float:
    """Estimated memory (MiB) of the cost curves a run keeps: float64 per run and step.

    Fig. 3 keeps 2 x ``runs`` episodes (five series each, four stacked again), Table II
    6 x ``table_runs`` episodes per GA variant (five series, ``J`` stacked again).
    """
    variants = 2 if args.ga_variant == "both" else 1
    per_step = 18 * args.runs + 36 * args.table_runs * variants + 30 * variants
    return 8.0 * (args.steps + 1) * per_step / 2**20


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Command line (see the module docstring); usage errors are one line, exit 2."""
    p = UsageParser(prog=PROG, description=__doc__.split("\n")[0])
    c = CEILINGS
    p.add_argument(
        "--runs", type=int, default=100,
        help=f"Fig. 3 Monte Carlo runs (paper: 1000; ceiling {c['--runs']:,})",
    )  # fmt: skip
    p.add_argument(
        "--table-runs", type=int, default=50,
        help=f"Table II runs per O (paper: 1000; ceiling {c['--table-runs']:,})",
    )  # fmt: skip
    p.add_argument(
        "--steps", type=int, default=500,
        help=f"K (paper: 500; at most {MAX_STEPS:,}, ceiling {c['--steps']:,})",
    )  # fmt: skip
    add_executor_arguments(p, default="process", workers_alias=True)
    p.add_argument("--seed", type=int, default=2022, help="master seed (>= 0)")
    p.add_argument("--out", type=Path, default=Path("docs/figures"))
    p.add_argument("--quick", action="store_true", help="4 runs, 3 per O, K = 120 (for tests)")
    p.add_argument(
        "--save",
        type=Path,
        default=None,
        help="also write the Table II cost curves J (runs, K + 1) per variant and O to this .npz",
    )
    p.add_argument(
        "--ga-variant",
        choices=(*GA_VARIANTS, "both"),
        default="improved",
        help="GA operators: improved (ours, default), literal (Table I as printed) or both "
        "(Table II and Fig. 4 for each)",
    )
    p.add_argument(
        "--store",
        type=Path,
        default=None,
        metavar="DIR",
        help="keep every finished run in DIR and skip the runs it already holds: a stopped "
        "command resumes where it stopped when run again with the same options (the wall time "
        "printed then covers every run that wrote to DIR)",
    )
    p.add_argument(
        "--allow-large",
        action="store_true",
        help="run sizes above the ceilings (--runs, --table-runs, --steps as above; "
        f"{MEMORY_CEILING_MIB:,} MiB of kept cost curves), which are there to catch typos",
    )
    args = p.parse_args(argv)
    if args.save is not None and not args.save.parent.is_dir():
        p.error(f"--save: folder {args.save.parent} does not exist")
    if args.quick:
        args.runs, args.table_runs, args.steps = 4, 3, 120
    return args


def check_args(args: argparse.Namespace) -> None:
    """Every size and seed checked before any work (:class:`UsageError` naming the option).

    ``--runs``, ``--table-runs`` >= 1 and ``--steps`` in ``[1, MAX_STEPS]`` (the env's
    horizon); each at most its ceiling (:data:`CEILINGS`) and the estimated memory of the
    kept curves (:func:`result_mib`) at most :data:`MEMORY_CEILING_MIB`, unless
    ``--allow-large``; ``--seed`` >= 0.
    """
    lifted = args.allow_large
    check_size("--runs", args.runs, low=1)
    check_size("--table-runs", args.table_runs, low=1)
    check_size("--steps", args.steps, low=1, high=MAX_STEPS, note=" (the env's horizon)")
    for option in CEILINGS:
        value = getattr(args, option.removeprefix("--").replace("-", "_"))
        check_size(option, value, ceiling=CEILINGS[option], lifted=lifted)
    check_size(
        "--runs x --table-runs x --steps",
        round(result_mib(args)),
        ceiling=MEMORY_CEILING_MIB,
        lifted=lifted,
        unit=" MiB",
        note=" (estimated memory of the kept cost curves)",
    )
    check_size("--seed", args.seed, low=0)


def _check_out(folder: Path) -> None:
    """A real write probe of the output folder before any work (usage error: exit 2)."""
    try:
        probe_writable(folder / ".write-probe")
    except OSError as exc:
        raise UsageError(f"--out: {describe_os_error(exc, folder)}") from None


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the three experiments, write the figures, print the tables; return the numbers."""
    args = parse_args(argv)
    check_args(args)
    try:
        pool = executor_from_args(args)
    except ExecutorError as exc:
        raise UsageError(f"{exc}") from None
    try:
        args.result_store = None if args.store is None else ResultStore(args.store)
    except (OSError, ValueError) as exc:
        raise UsageError(f"--store: {exc}") from None
    _check_out(args.out)
    t0 = time.perf_counter()
    sigma = make_clustering_problem(ClusteringConfig(), np.random.default_rng(args.seed)).sigma
    variants = GA_VARIANTS if args.ga_variant == "both" else (args.ga_variant,)
    try:
        with pool:
            args.pool = pool
            results: dict[str, Any] = {
                "fig3": fig3_experiment(args, np.asarray(sigma), variants[0])
            }
            results["by_variant"] = {
                v: {
                    "table2": table2_experiment(args, v),
                    "fig4": fig4_experiment(args, np.asarray(sigma), v),
                }
                for v in variants
            }
            del args.pool
    except ExecutorError as exc:  # an unreachable --address is found when Ray starts
        raise UsageError(" ".join(str(exc).split())) from None
    results.update(results["by_variant"][variants[0]])  # "table2", "fig4": the first variant
    results["fig3_variant"] = variants[0]
    results["executor"] = pool.describe()
    suffix = {v: "" if v == "improved" else f"_{v}" for v in variants}
    paths = {"greiff_fig3": args.out / f"greiff_fig3{suffix[variants[0]]}.png"}
    plot_fig3(results["fig3"], paths["greiff_fig3"])
    for v in variants:
        for name, plot in (("greiff_table2", plot_table2), ("greiff_fig4", plot_fig4)):
            paths[name + suffix[v]] = args.out / f"{name}{suffix[v]}.png"
            plot(results["by_variant"][v][name.removeprefix("greiff_")], paths[name + suffix[v]])
    if args.save is not None:
        np.savez_compressed(
            args.save,
            **{
                f"{v}_{''.join(map(str, ops))}": r["J"]
                for v, res in results["by_variant"].items()
                for ops, r in res["table2"].items()
            },
        )
    wall = time.perf_counter() - t0
    store = args.result_store
    del args.result_store
    results["figures"] = {k: str(v) for k, v in paths.items()}
    config = {**vars(args), "out": str(args.out), "wall_time_s": wall}
    config["store"] = None if args.store is None else str(args.store)
    results["config"] = config
    print(format_tables(results))
    line = f"\nruns={args.runs} table_runs={args.table_runs} K={args.steps} wall time {wall:.1f} s"
    if store is not None:
        config["stored_wall_time_s"] = store.compute_seconds()
        line += f" (the runs held in --store cost {store.compute_seconds():.1f} s of wall time)"
    print(line)
    return results


if __name__ == "__main__":
    sys.exit(guarded_main(main, PROG))
