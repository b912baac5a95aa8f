"""Reproduce Chen & Kia (2022) Figs. 2, 6 and Table IV: the learned fusion surrogates.

On a fresh test set (simulator beliefs from a seed the checkpoints never saw, labelled by the
exact solvers, :func:`selenv.learned.surrogate_data.generate_dataset`):

* **Fig. 2** -- the PECMV objective eq. (8a), ``log det P_i+`` with ``X = L_i C L_j^T``, for
  the optimum ``C*`` and for each LPECMV output method of Table I (1: tanh + barrier loss,
  2: tanh / D, 3: tanh diagonal), and the gap ``value(C_hat) - value(C*) <= 0``; with two
  references: ``C = 0`` (the naive update) and ``diag(C*)`` (the best any method-3 network can
  do).
* **Fig. 6** -- (a) the fit of LDMV's ``omega_hat`` against ``omega*`` with ``R`` (Pearson
  correlation, the paper's "square root of the coefficient of determination"); (b) the
  histogram of LPECMV's ``C_diag`` errors.
* **Table IV** -- time of one update call (exact vs learned, median of ``--calls`` calls on
  test rows), the prediction alone, and batched predictions per second.

* **Filter accuracy** (``--filter-runs``, default 30) -- the two-pedestrian simulation of
  ``scripts/reproduce_chen_kia.py`` with exact DMV / PECMV and with LDMV / LPECMV on the same
  seeds: position RMSE and horizontal-position NEES per agent, the share of time steps whose
  mean NEES over the runs is inside the 95 % chi-square band, and per-seed paired differences
  (learned - exact) with 95 % t confidence intervals.

``--m 2``: the same with relative range + bearing (``bearing_sigma_deg = 2``, the noise the
m = 2 checkpoints ``checkpoints/ldmv_m2.pt`` / ``lpecmv_m2.pt`` are trained for). There the
exact PECMV is an optimisation and the surrogates pay (Table IV); only method 3 is shipped.

Usage::

    python scripts/reproduce_chen_kia_surrogates.py [--samples 5000] [--seed 2022] [--quick]
                                                    [--m 1|2] [--filter-runs 30]
                                                    [--allow-large]

Sizes are checked before any work (exit 2, one line naming the option): ``--samples`` up to
200,000, ``--calls`` up to 100,000, ``--filter-runs``, ``--filter-steps`` and
``--best-diagonal`` up to 10,000 (:data:`CEILINGS`) and about 4 GiB of kept filter errors and
NEES; ``--allow-large`` lifts these ceilings.

Methods 1 and 2 are read from ``checkpoints/lpecmv_method1.pt`` / ``lpecmv_method2.pt``
(trained with the same data and budget as the shipped method 3, see
``docs/reproductions/chen_kia_surrogates.md``).
Writes ``chen_kia_fig2.png`` and ``chen_kia_fig6.png`` into ``--out``, prints Markdown tables;
``main(argv)`` returns the numbers. The full-run times of Table IV (s per simulated run) come
from ``scripts/reproduce_chen_kia.py``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # tiny matrices: threads only contend

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.figure import Figure
from scipy.stats import t as student_t

from selenv import fusion
from selenv.atomic import describe_os_error, probe_writable, save_figure
from selenv.exits import UsageError, check_size, guarded_main
from selenv.learned.config import UsageParser
from selenv.learned.surrogate_data import (
    MAX_ROWS,
    GenerationConfig,
    SurrogateDataset,
    generate_dataset,
)
from selenv.parallel import Executor, ExecutorError, add_executor_arguments, executor_from_args

sys.path.insert(0, str(Path(__file__).resolve().parent))  # spawned workers inherit sys.path
import reproduce_chen_kia as rck  # the CL simulation runs of Table III / Fig. 8

if TYPE_CHECKING:  # torch loads only once the command line is checked (fast usage errors)
    from selenv.learned.surrogates import Surrogate

ROOT = Path(__file__).resolve().parents[1]
CHECKPOINTS = {
    "ldmv": ROOT / "checkpoints" / "ldmv.pt",
    1: ROOT / "checkpoints" / "lpecmv_method1.pt",
    2: ROOT / "checkpoints" / "lpecmv_method2.pt",
    3: ROOT / "checkpoints" / "lpecmv.pt",
}
#: range + bearing (m = 2): the shipped method-3 LPECMV and LDMV, trained at BEARING_DEG
CHECKPOINTS_M2 = {
    "ldmv": ROOT / "checkpoints" / "ldmv_m2.pt",
    3: ROOT / "checkpoints" / "lpecmv_m2.pt",
}
BEARING_DEG = 2.0
#: the filter study: learned method -> the exact method it replaces (paired on seeds)
PAIRS = {"ldmv": "dmv", "lpecmv": "pecmv", "lpecmv_full": "pecmv", "lpecmv_objective": "pecmv"}
METHOD_LABELS = {1: "method 1 (tanh, barrier)", 2: "method 2 (tanh / D)", 3: "method 3 (diag)"}
#: the paper's Table IV (Intel i5-1135G7): algorithm -> (full run s, single execution ms)
PAPER_TABLE_IV = {
    "DMV": (86.9828, 3.2197),
    "LDMV": (40.1316, 0.2122),
    "PECMV": (189282.6081, 7261.5138),
    "LPECMV": (43.9001, 0.2002),
}


def pecmv_values(ds: SurrogateDataset, C: np.ndarray) -> np.ndarray:
    """Objective eq. (8a), ``log det P_i+(X = L_i C L_j^T)``, per row; C (B, n, n)."""
    return np.array(
        [
            fusion.pecmv_update(
                ds.P_i[k], ds.P_j[k], ds.H_i[k], ds.H_j[k], ds.R, C=C[k], validate=False
            ).log_det
            for k in range(len(ds))
        ]
    )


def dmv_values(ds: SurrogateDataset, omega: np.ndarray) -> np.ndarray:
    """Objective eq. (6), ``log det Pbar(omega)``, per row; omega (B,)."""
    return np.array(
        [
            fusion.dmv_update(
                ds.P_i[k], ds.P_j[k], ds.H_i[k], ds.H_j[k], ds.R, omega=float(omega[k]),
                validate=False,
            ).log_det
            for k in range(len(ds))
        ]
    )  # fmt: skip


def fig2(ds: SurrogateDataset, lpecmv: dict[int, Surrogate]) -> dict[str, np.ndarray]:
    """Objective values of ``C*``, each method's ``C_hat``, ``C = 0`` and ``diag(C*)``."""
    from selenv.learned.surrogates import C_SCALE

    args = (ds.P_i, ds.P_j, ds.H_i, ds.H_j)
    diag = np.zeros_like(ds.C)
    n = ds.C.shape[-1]
    diag[:, np.arange(n), np.arange(n)] = ds.C_diag * C_SCALE
    values = {"optimum": ds.log_det_pecmv}
    for method, sur in sorted(lpecmv.items()):
        values[f"method {method}"] = pecmv_values(ds, sur.predict_C(*args))
    values["C = 0"] = pecmv_values(ds, np.zeros_like(ds.C))
    values["diag(C*)"] = pecmv_values(ds, diag)
    return values


def plot_fig2(values: dict[str, np.ndarray], path: Path) -> None:
    """Left: objective per test sample (sorted by the optimum); right: gap distributions."""
    fig = Figure(figsize=(11, 4.2))
    ax1, ax2 = fig.subplots(1, 2)
    order = np.argsort(values["optimum"])
    show = order[:: max(1, len(order) // 300)]
    for name, v in values.items():
        style = {"lw": 2, "color": "k"} if name == "optimum" else {"lw": 0.8}
        ax1.plot(v[show], label=name, **style)
    ax1.set(xlabel="test sample (sorted by the optimal value)", ylabel="log det P_i+ (eq. 8a)",
            title="objective value")  # fmt: skip
    ax1.legend(fontsize=8)
    names = [k for k in values if k != "optimum"]
    gaps = [values[k] - values["optimum"] for k in names]
    ax2.boxplot(gaps, showfliers=False)
    ax2.set_xticks(range(1, len(names) + 1), names, rotation=15, fontsize=8)
    ax2.axhline(0.0, color="k", lw=0.8)
    ax2.set(ylabel="value - optimal value (nats)", title="difference to the optimum (<= 0)")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


def plot_fig6(
    omega: np.ndarray, omega_hat: np.ndarray, c_err: np.ndarray, r: float, path: Path
) -> None:
    """(a) omega_hat vs omega* with the perfect-fit line; (b) C_diag error histogram."""
    fig = Figure(figsize=(10, 4.2))
    ax1, ax2 = fig.subplots(1, 2)
    ax1.scatter(omega, omega_hat, s=3, alpha=0.3, label="test samples")
    lo = float(min(omega.min(), omega_hat.min()))
    ax1.plot([lo, 1], [lo, 1], color="0.5", label="fit (y = x)")
    ax1.set(
        xlabel="omega* (exact DMV)", ylabel="omega_hat (LDMV)", title=f"(a) LDMV fit, R = {r:.4f}"
    )
    ax1.legend(fontsize=8)
    ax2.hist(c_err.ravel(), bins=80, color="C1")
    ax2.set(xlabel="C_diag_hat - C_diag* (entries)", ylabel="count", yscale="log",
            title="(b) LPECMV (method 3) error histogram")  # fmt: skip
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


def _median_us(fn: Callable[[int], Any], calls: int, rows: int) -> float:
    """Median wall time of ``fn(k)`` over ``calls`` calls cycling through ``rows`` rows."""
    for k in range(min(rows, 50)):  # warm-up: caches, lazy imports, the shipped checkpoints
        fn(k)
    t = np.empty(calls)
    for c in range(calls):
        t0 = time.perf_counter()
        fn(c % rows)
        t[c] = time.perf_counter() - t0
    return float(np.median(t) * 1e6)


def table_iv(
    ds: SurrogateDataset, ldmv: Surrogate, lpecmv: Surrogate, calls: int
) -> dict[str, dict[str, float]]:
    """Per-call times (us): full update and prediction alone; batched predictions per second."""
    rows = len(ds)

    def a(k: int) -> tuple[np.ndarray, ...]:
        return ds.P_i[k], ds.P_j[k], ds.H_i[k], ds.H_j[k]

    R = ds.R
    out = {
        "DMV": {"update_us": _median_us(lambda k: fusion.dmv_update(*a(k), R), calls, rows)},
        "LDMV": {
            "update_us": _median_us(
                lambda k: fusion.ldmv_update(*a(k), R, surrogate=ldmv), calls, rows
            ),
            "predict_us": _median_us(lambda k: ldmv.predict_omega(*a(k)), calls, rows),
        },
        "PECMV": {"update_us": _median_us(lambda k: fusion.pecmv_update(*a(k), R), calls, rows)},
        "LPECMV": {
            "update_us": _median_us(
                lambda k: fusion.lpecmv_update(*a(k), R, surrogate=lpecmv), calls, rows
            ),
            "predict_us": _median_us(lambda k: lpecmv.predict_C(*a(k)), calls, rows),
        },
    }
    args = (ds.P_i, ds.P_j, ds.H_i, ds.H_j)
    for name, fn in (
        ("DMV", lambda: fusion.dmv_omega_batch(*args, R)),
        ("LDMV", lambda: ldmv.predict_omega(*args)),
        ("PECMV", lambda: fusion.pecmv_batch(*args, R)),
        ("LPECMV", lambda: lpecmv.predict_C(*args)),
    ):
        fn()
        t0 = time.perf_counter()
        fn()
        out[name]["batched_per_s"] = rows / (time.perf_counter() - t0)
    return out


def best_diagonal_gaps(ds: SurrogateDataset, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Gap to the optimum of eq. (8a) of ``diag(C*)`` and of the best diagonal ``C`` per row.

    The best diagonal maximises eq. (8a) over ``C = diag(c)``, ``|c_k| < 1`` (L-BFGS-B from
    ``diag(C*)``; the objective is concave in ``X = L_i C L_j^T``, hence in ``c``), on the
    first ``rows`` rows: what a method-3 network trained on the objective could reach.
    """
    from scipy.optimize import minimize

    from selenv.learned.surrogates import C_SCALE

    diag_gap, best_gap = [], []
    for k in range(min(rows, len(ds))):
        args = (ds.P_i[k], ds.P_j[k], ds.H_i[k], ds.H_j[k], ds.R)

        def neg(c: np.ndarray, args: tuple[np.ndarray, ...] = args) -> float:
            return -fusion.pecmv_update(*args, C=np.diag(c), validate=False).log_det

        c0 = ds.C_diag[k] * C_SCALE
        res = minimize(neg, c0, method="L-BFGS-B", bounds=[(-1 + 1e-9, 1 - 1e-9)] * c0.size)
        diag_gap.append(-neg(c0) - ds.log_det_pecmv[k])
        best_gap.append(-min(float(res.fun), neg(c0)) - ds.log_det_pecmv[k])
    return np.asarray(diag_gap), np.asarray(best_gap)


def mean_ci(d: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """Mean of paired differences ``d`` (runs,) and its two-sided t confidence interval."""
    d = np.asarray(d, dtype=float)
    mean = float(d.mean())
    if d.size < 2:
        return mean, float("nan"), float("nan")
    half = float(student_t.ppf(0.5 + level / 2, d.size - 1) * d.std(ddof=1) / np.sqrt(d.size))
    return mean, mean - half, mean + half


def filter_study(
    runs: int, steps: int, pool: Executor, bearing: float | None, methods: Sequence[str]
) -> dict[str, Any]:
    """Exact vs learned fusion in the CL simulation on seeds ``0 .. runs - 1`` (paired).

    Per method and agent: RMSE over runs and steps, per-seed RMSE ``sqrt(mean_t err^2)`` and
    mean NEES, the mean NEES over all runs and steps, and the share of steps whose NEES
    averaged over the runs lies inside (above) the 95 % band of ``runs`` runs, 2 dof. Per
    learned method: paired differences learned - exact of the per-seed RMSE and mean NEES.
    """
    res = rck.run_all(runs, steps, pool, tuple(methods), bearing)
    lo, hi = rck.nees_band(runs)
    out: dict[str, Any] = {"band": (lo, hi), "runs": runs, "steps": steps, "methods": {}}
    for m, r in res.items():
        per_t = r["nees"].mean(axis=0)  # (steps, A): Fig. 8's curve
        out["methods"][m] = {
            "rmse": r["rmse"],
            "seed_rmse": np.sqrt(np.mean(r["err"] ** 2, axis=1)),  # (runs, A)
            "seed_nees": r["nees"].mean(axis=1),  # (runs, A)
            "mean_nees": r["mean_nees"],
            "in_band": np.mean((per_t >= lo) & (per_t <= hi), axis=0),
            "above_band": np.mean(per_t > hi, axis=0),
            "ms_per_update": r["ms_per_update"],
        }
    diffs = {}
    for m, ref in PAIRS.items():
        if m in out["methods"] and ref in out["methods"]:
            a, b = out["methods"][m], out["methods"][ref]
            diffs[f"{m} - {ref}"] = {
                key: [mean_ci(a[key][:, k] - b[key][:, k]) for k in range(a[key].shape[1])]
                for key in ("seed_rmse", "seed_nees")
            }
    out["diffs"] = diffs
    return out


def format_filter(study: dict[str, Any]) -> str:
    """Markdown: RMSE and NEES per method and agent, then the paired differences."""
    lo, hi = study["band"]
    lines = [
        "| method | RMSE agent 1 (m) | RMSE agent 2 (m) | mean NEES agent 1 | mean NEES agent 2 "
        "| steps in band agent 1 | agent 2 | above band agent 1 | agent 2 | ms / rel. update |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for m, r in study["methods"].items():
        lines.append(
            f"| {rck.LABELS[m]} | {r['rmse'][0]:.4f} | {r['rmse'][1]:.4f} | "
            f"{r['mean_nees'][0]:.2f} | {r['mean_nees'][1]:.2f} | {r['in_band'][0]:.0%} | "
            f"{r['in_band'][1]:.0%} | {r['above_band'][0]:.0%} | {r['above_band'][1]:.0%} | "
            f"{r['ms_per_update']:.3f} |"
        )
    lines.append(
        f"\n95 % band of the mean NEES over {study['runs']} runs (2 dof): [{lo:.2f}, {hi:.2f}]; "
        f"{study['steps']} steps of 0.1 s\n"
    )
    lines.append(
        "| paired difference (per seed) | RMSE agent 1 (m) [95 % CI] | RMSE agent 2 (m) "
        "[95 % CI] | mean NEES agent 1 [95 % CI] | mean NEES agent 2 [95 % CI] |"
    )
    lines.append("|---|---:|---:|---:|---:|")

    def f(c: tuple[float, float, float], digits: int) -> str:
        return f"{c[0]:+.{digits}f} [{c[1]:+.{digits}f}, {c[2]:+.{digits}f}]"

    for name, d in study["diffs"].items():
        r, n = d["seed_rmse"], d["seed_nees"]
        lines.append(f"| {name} | {f(r[0], 4)} | {f(r[1], 4)} | {f(n[0], 2)} | {f(n[1], 2)} |")
    return "\n".join(lines)


def _check_out(folder: Path) -> None:
    """A real write probe of the output folder before any work (usage error: exit 2)."""
    try:
        probe_writable(folder / ".write-probe")
    except OSError as exc:
        raise UsageError(f"--out: {describe_os_error(exc, folder)}") from None


PROG = "reproduce_chen_kia_surrogates.py"
#: ceilings on the work of one run, checked before anything runs (``--allow-large`` lifts them);
#: far above the documented runs (5000 rows, 2000 calls, 30 filter runs of 600 steps)
CEILINGS: dict[str, int] = {
    "--samples": MAX_ROWS,
    "--calls": 100_000,
    "--filter-runs": 10_000,
    "--filter-steps": 10_000,
    "--best-diagonal": 10_000,
}


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Command line (see the module docstring); usage errors are one line, exit 2."""
    ap = UsageParser(prog=PROG, description=(__doc__ or "").split("\n")[0])
    c = CEILINGS
    ap.add_argument("--samples", type=int, default=5000,
                    help=f"test rows (paper: 5000; >= 2; ceiling {c['--samples']:,})")  # fmt: skip
    ap.add_argument("--seed", type=int, default=2022, help="test-set seed (>= 0; training used 0)")
    ap.add_argument("--calls", type=int, default=2000,
                    help=f"timed calls per algorithm (ceiling {c['--calls']:,})")  # fmt: skip
    add_executor_arguments(ap, default="process", workers_alias=True)
    ap.add_argument("--out", type=Path, default=Path("docs/figures"))
    ap.add_argument("--quick", action="store_true",
                    help="300 rows, 200 calls, 3 filter runs of 100 steps (for tests)")  # fmt: skip
    ap.add_argument("--m", type=int, choices=(1, 2), default=1,
                    help="1: relative range (default); 2: range + bearing at 2 deg")  # fmt: skip
    ap.add_argument("--filter-runs", type=int, default=30,
                    help="seeds of the exact-vs-learned filter study (0: skip it; ceiling "
                         f"{c['--filter-runs']:,})")  # fmt: skip
    ap.add_argument("--filter-steps", type=int, default=600,
                    help=f"steps of 0.1 s per run (ceiling {c['--filter-steps']:,})")  # fmt: skip
    ap.add_argument("--best-diagonal", type=int, default=0,
                    help="best diagonal C per row on this many test rows (0: none; at most "
                         f"--samples; ceiling {c['--best-diagonal']:,})")  # fmt: skip
    ap.add_argument("--allow-large", action="store_true",
                    help="run sizes above the ceilings (as above; "
                         f"{rck.MEMORY_CEILING_MIB:,} MiB of kept filter errors and NEES), "
                         "which are there to catch typos")  # fmt: skip
    args = ap.parse_args(argv)
    if args.quick:
        args.samples, args.calls = 300, 200
        args.filter_runs, args.filter_steps = min(args.filter_runs, 3), 100
    return args


def filter_methods(m: int) -> tuple[str, ...]:
    """The filter study's methods: exact DMV / PECMV and the learned ones shipped for ``m``."""
    learned = (
        ("ldmv", "lpecmv", "lpecmv_full", "lpecmv_objective") if m == 1 else ("ldmv", "lpecmv")
    )
    return ("dmv", "pecmv", *learned)


def check_args(args: argparse.Namespace) -> None:
    """Every size and seed checked before any work (:class:`UsageError` naming the option).

    Validity: ``--samples`` >= 2, ``--calls`` >= 1, ``--filter-runs`` >= 0,
    ``--filter-steps`` in ``[1, MAX_STEPS]``, ``--best-diagonal`` in ``[0, --samples]``,
    ``--seed`` >= 0. Work: each size's ceiling (:data:`CEILINGS`) and the filter study's
    kept errors and NEES (``reproduce_chen_kia.MEMORY_CEILING_MIB``), unless ``--allow-large``.
    """
    lifted = args.allow_large
    check_size("--samples", args.samples, low=2, note=" (the fit's correlation needs two rows)")
    check_size("--calls", args.calls, low=1)
    check_size("--filter-runs", args.filter_runs, low=0)
    check_size("--filter-steps", args.filter_steps, low=1, high=rck.MAX_STEPS)
    check_size("--best-diagonal", args.best_diagonal, low=0, high=args.samples,
               note=" (at most --samples, the test rows)")  # fmt: skip
    check_size("--seed", args.seed, low=0)
    for option in CEILINGS:
        value = getattr(args, option.removeprefix("--").replace("-", "_"))
        check_size(option, value, ceiling=CEILINGS[option], lifted=lifted)
    n_methods = len(filter_methods(args.m))
    check_size(
        "--filter-runs x --filter-steps",
        round(rck.result_mib(args.filter_runs, args.filter_steps, n_methods)),
        ceiling=rck.MEMORY_CEILING_MIB,
        lifted=lifted,
        unit=" MiB",
        note=f" (estimated memory of the kept errors and NEES of {n_methods} methods)",
    )


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Generate the test set, evaluate, plot, print; return the numbers."""
    args = parse_args(argv)
    check_args(args)
    paths_in = CHECKPOINTS if args.m == 1 else CHECKPOINTS_M2
    missing = [str(p) for p in paths_in.values() if not p.is_file()]
    if missing:
        raise UsageError(
            f"missing checkpoints {missing}: "
            "see docs/reproductions/chen_kia_surrogates.md for the commands"
        )
    try:
        pool = executor_from_args(args)
    except ExecutorError as exc:
        raise UsageError(f"{exc}") from None
    _check_out(args.out)
    t0 = time.perf_counter()
    from selenv.learned.surrogates import Surrogate

    ldmv = Surrogate.load(paths_in["ldmv"])
    lpecmv = {m: Surrogate.load(p) for m, p in paths_in.items() if m != "ldmv"}
    bearing = None if args.m == 1 else BEARING_DEG
    study = None
    try:
        with pool:
            gen = GenerationConfig(bearing_sigma_deg=bearing)
            ds = generate_dataset(args.samples, seed=args.seed, executor=pool, gen=gen)
            if args.filter_runs > 0:
                study = filter_study(
                    args.filter_runs, args.filter_steps, pool, bearing, filter_methods(args.m)
                )
    except ExecutorError as exc:  # an unreachable --address is found when Ray starts
        raise UsageError(" ".join(str(exc).split())) from None

    values = fig2(ds, lpecmv)
    omega_hat = ldmv.predict_omega(ds.P_i, ds.P_j, ds.H_i, ds.H_j)
    r = float(np.corrcoef(omega_hat, ds.omega)[0, 1])
    C3 = lpecmv[3].predict_C(ds.P_i, ds.P_j, ds.H_i, ds.H_j)
    c_err = np.diagonal(C3, axis1=1, axis2=2) - ds.C_diag
    dmv_gap = dmv_values(ds, omega_hat) - dmv_values(ds, ds.omega)  # >= 0: w* minimises (6)
    tag = "" if args.m == 1 else "_m2"
    paths = {
        "fig2": args.out / f"chen_kia_fig2{tag}.png",
        "fig6": args.out / f"chen_kia_fig6{tag}.png",
    }
    plot_fig2(values, paths["fig2"])
    plot_fig6(ds.omega, omega_hat, c_err, r, paths["fig6"])
    times = table_iv(ds, ldmv, lpecmv[3], args.calls)
    wall = time.perf_counter() - t0

    print(f"\nFig. 2 -- objective gap to the optimum on {len(ds)} test rows (nats, <= 0)\n")
    print("| C | mean gap | median gap | 5th percentile | share within 0.01 nats |")
    print("|---|---:|---:|---:|---:|")
    gaps = {}
    for name, v in values.items():
        if name == "optimum":
            continue
        g = v - values["optimum"]
        gaps[name] = g
        print(f"| {name} | {g.mean():.4f} | {np.median(g):.4f} | {np.percentile(g, 5):.4f} | "
              f"{np.mean(g > -0.01):.1%} |")  # fmt: skip
    print(f"\nFig. 6 -- LDMV R = {r:.4f} (R^2 {r * r:.4f}), mean |omega error| "
          f"{np.mean(np.abs(omega_hat - ds.omega)):.2e}; LPECMV C_diag error: mean "
          f"{c_err.mean():.2e}, std {c_err.std():.2e}, 99th pct |err| "
          f"{np.percentile(np.abs(c_err), 99):.3f}")  # fmt: skip
    print(f"\nLDMV -- DMV objective gap log det Pbar(omega_hat) - log det Pbar(omega*) (nats, "
          f">= 0): mean {dmv_gap.mean():.2e}, median {np.median(dmv_gap):.2e}, 99th pct "
          f"{np.percentile(dmv_gap, 99):.2e}, max {dmv_gap.max():.2e}")  # fmt: skip
    print("\nTable IV -- single call (median, us) and batched predictions per second\n")
    print(
        "| algorithm | update call (us) | prediction alone (us) | batched /s | paper single (ms) |"
    )
    print("|---|---:|---:|---:|---:|")
    for name, t in times.items():
        pred = f"{t['predict_us']:.1f}" if "predict_us" in t else ""
        print(f"| {name} | {t['update_us']:.1f} | {pred} | {t['batched_per_s']:,.0f} | "
              f"{PAPER_TABLE_IV[name][1]} |")  # fmt: skip
    best = None
    if args.best_diagonal > 0:
        best = best_diagonal_gaps(ds, args.best_diagonal)
        print(f"\nBest diagonal C per row ({best[0].size} rows): gap to the optimum of eq. (8a), "
              f"diag(C*) {best[0].mean():.4f} nats, optimised diagonal {best[1].mean():.4f} "
              f"nats")  # fmt: skip
    if study is not None:
        print(f"\nFilter accuracy, m = {args.m} -- exact vs learned fusion, paired seeds\n")
        print(format_filter(study))
    print(f"\nm={args.m} samples={len(ds)} seed={args.seed} wall time {wall:.1f} s")
    return {
        "m": args.m,
        "filter": study,
        "best_diagonal": best,
        "gaps": gaps,
        "dmv_gap": dmv_gap,
        "R": r,
        "c_err": c_err,
        "times": times,
        "figures": {k: str(v) for k, v in paths.items()},
        "wall": wall,
    }


if __name__ == "__main__":
    sys.exit(guarded_main(main, PROG))
