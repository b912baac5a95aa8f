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

Usage::

    python scripts/reproduce_chen_kia_surrogates.py [--samples 5000] [--seed 2022] [--quick]

Methods 1 and 2 are read from ``checkpoints/lpecmv_method1.pt`` / ``lpecmv_method2.pt``
(trained with the same data and budget as the shipped method 3, see ``docs/REPRODUCTION.md``).
Writes ``chen_kia_fig2.png`` and ``chen_kia_fig6.png`` into ``--out``, prints Markdown tables;
``main(argv)`` returns the numbers. The full-run times of Table IV (s per simulated run) come
from ``scripts/reproduce_chen_kia.py``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # tiny matrices: threads only contend

import argparse
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from selenv import fusion
from selenv.learned.surrogate_data import SurrogateDataset, generate_dataset
from selenv.learned.surrogates import C_SCALE, Surrogate
from selenv.parallel import ExecutorError, add_executor_arguments, executor_from_args

ROOT = Path(__file__).resolve().parents[1]
CHECKPOINTS = {
    "ldmv": ROOT / "checkpoints" / "ldmv.pt",
    1: ROOT / "checkpoints" / "lpecmv_method1.pt",
    2: ROOT / "checkpoints" / "lpecmv_method2.pt",
    3: ROOT / "checkpoints" / "lpecmv.pt",
}
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


def fig2(ds: SurrogateDataset, lpecmv: dict[int, Surrogate]) -> dict[str, np.ndarray]:
    """Objective values of ``C*``, each method's ``C_hat``, ``C = 0`` and ``diag(C*)``."""
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
    fig.savefig(path, dpi=120)


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
    fig.savefig(path, dpi=120)


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


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Generate the test set, evaluate, plot, print; return the numbers."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--samples", type=int, default=5000, help="test rows (paper: 5000)")
    ap.add_argument("--seed", type=int, default=2022, help="test-set seed (training used 0)")
    ap.add_argument("--calls", type=int, default=2000, help="timed single calls per algorithm")
    add_executor_arguments(ap, default="process", workers_alias=True)
    ap.add_argument("--out", type=Path, default=Path("docs/figures"))
    ap.add_argument("--quick", action="store_true", help="300 rows, 200 calls (for tests)")
    args = ap.parse_args(argv)
    if args.quick:
        args.samples, args.calls = 300, 200
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    missing = [str(p) for p in CHECKPOINTS.values() if not p.is_file()]
    if missing:
        raise SystemExit(
            f"missing checkpoints {missing}: see docs/REPRODUCTION.md for the commands"
        )
    ldmv = Surrogate.load(CHECKPOINTS["ldmv"])
    lpecmv = {m: Surrogate.load(CHECKPOINTS[m]) for m in (1, 2, 3)}
    try:
        pool = executor_from_args(args)
    except ExecutorError as exc:
        raise SystemExit(f"reproduce_chen_kia_surrogates: error: {exc}") from None
    with pool:
        ds = generate_dataset(args.samples, seed=args.seed, executor=pool)

    values = fig2(ds, lpecmv)
    omega_hat = ldmv.predict_omega(ds.P_i, ds.P_j, ds.H_i, ds.H_j)
    r = float(np.corrcoef(omega_hat, ds.omega)[0, 1])
    C3 = lpecmv[3].predict_C(ds.P_i, ds.P_j, ds.H_i, ds.H_j)
    c_err = np.diagonal(C3, axis1=1, axis2=2) - ds.C_diag
    paths = {"fig2": args.out / "chen_kia_fig2.png", "fig6": args.out / "chen_kia_fig6.png"}
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
    print("\nTable IV -- single call (median, us) and batched predictions per second\n")
    print(
        "| algorithm | update call (us) | prediction alone (us) | batched /s | paper single (ms) |"
    )
    print("|---|---:|---:|---:|---:|")
    for name, t in times.items():
        pred = f"{t['predict_us']:.1f}" if "predict_us" in t else ""
        print(f"| {name} | {t['update_us']:.1f} | {pred} | {t['batched_per_s']:,.0f} | "
              f"{PAPER_TABLE_IV[name][1]} |")  # fmt: skip
    print(f"\nsamples={len(ds)} seed={args.seed} wall time {wall:.1f} s")
    return {
        "gaps": gaps,
        "R": r,
        "c_err": c_err,
        "times": times,
        "figures": {k: str(v) for k, v in paths.items()},
        "wall": wall,
    }


if __name__ == "__main__":
    main()
