"""Per-call cost of the shipped LDMV / LPECMV surrogates against the exact DMV / PECMV solvers.

Chen & Kia 2022, Table IV: a learned optimiser pays where the exact one is expensive. With a
relative range only (m = 1) our exact DMV and PECMV are closed forms (a cubic, eqs. 6 and
8-12 in closed form), so a network cannot be much faster; with range + bearing (m = 2) the
exact PECMV is an optimisation (the reduced MAXDET problem of eq. 8, milliseconds per call),
and the m = 2 surrogates (``checkpoints/ldmv_m2.pt``, ``lpecmv_m2.pt``, picked automatically
for ``R = diag(0.1^2, (2 deg)^2)``) replace it.

For each m, on real fusion problems from the surrogate data generator (n = 9):

* single call (median over ``--single`` calls, us; the algorithms interleaved in blocks of 25
  calls, so they see the same rows and the same machine load): the full update ``dmv_update`` /
  ``pecmv_update`` vs ``ldmv_update`` / ``lpecmv_update`` (prediction + the exact update with
  the predicted omega / C), and the prediction alone;
* batched over B = 64 and B = 1024 problems: the exact batched solvers
  ``dmv_omega_batch`` / ``pecmv_batch`` (omega*, C*) vs ``predict_omega`` / ``predict_C``
  (best of ``--repeat``), per problem (us) and problems per second;

and prints the ratios exact / learned (> 1: the surrogate is faster).

    .venv/bin/python benchmarks/bench_surrogates.py                 # m = 1 and m = 2
    .venv/bin/python benchmarks/bench_surrogates.py --m 2 --single 300
    .venv/bin/python benchmarks/bench_surrogates.py --m 1 --batches 20000   # the m = 1 rows
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from selenv.core.fusion import (
    dmv_omega_batch,
    dmv_update,
    ldmv_update,
    lpecmv_update,
    pecmv_batch,
    pecmv_update,
)
from selenv.learned.surrogate_data import GenerationConfig, generate_dataset
from selenv.learned.surrogates import shipped

#: bearing noise (deg) of the m = 2 scenarios: the one the shipped m = 2 surrogates are for
BEARING_DEG = 2.0
BATCHES = (64, 1024)


def _best(fn: Callable[[], Any], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def _medians_us(
    fns: dict[str, Callable[[int], Any]], calls: int, rows: int, block: int = 25
) -> dict[str, float]:
    """Median time (us) of each ``fn(i)`` over ``calls`` rows, interleaved by blocks.

    Block ``b`` runs each function in turn on the same ``block`` rows, so all functions see
    the same rows and (to within a block) the same load of the shared machine, while each
    runs ``block`` calls in a row with warm caches, as in a filter that uses one method.
    """
    for i in range(min(rows, 20)):  # warm-up (lazy imports, the checkpoint, caches)
        for fn in fns.values():
            fn(i)
    ts: dict[str, list[float]] = {name: [] for name in fns}
    for start in range(0, calls, block):
        idx = [c % rows for c in range(start, min(start + block, calls))]
        for name, fn in fns.items():
            for i in idx:
                t0 = time.perf_counter()
                fn(i)
                ts[name].append(time.perf_counter() - t0)
    return {name: 1e6 * float(np.median(t)) for name, t in ts.items()}


def run(
    m: int, single: int, repeat: int, batches: tuple[int, ...] = BATCHES, seed: int = 7
) -> dict[str, Any]:
    """Time one m; return ``{"single": {...}, "batched": {B: {...}}}`` in us per problem."""
    gen = GenerationConfig(bearing_sigma_deg=None if m == 1 else BEARING_DEG)
    data = generate_dataset(max(batches), seed=seed, workers=1, gen=gen, progress=False)
    Pi, Pj, Hi, Hj, R = data.P_i, data.P_j, data.H_i, data.H_j, data.R  # R (m, m), shared
    ldmv, lpecmv = shipped("ldmv", R=R, n=9), shipped("lpecmv", R=R, n=9)
    assert ldmv.m == m and lpecmv.m == m, (ldmv.m, lpecmv.m)
    rows = len(data)

    def a(i: int) -> tuple[np.ndarray, ...]:
        return Pi[i], Pj[i], Hi[i], Hj[i]

    out: dict[str, Any] = {"m": m, "R": R.tolist(), "single": {}, "batched": {}}
    fns: dict[str, Callable[[int], Any]] = {
        "DMV update": lambda i: dmv_update(*a(i), R),
        "LDMV update": lambda i: ldmv_update(*a(i), R),
        "LDMV predict_omega": lambda i: ldmv.predict_omega(*a(i)),
        "PECMV update": lambda i: pecmv_update(*a(i), R),
        "LPECMV update": lambda i: lpecmv_update(*a(i), R),
        "LPECMV predict_C": lambda i: lpecmv.predict_C(*a(i)),
    }
    out["single"] = _medians_us(fns, single, rows)
    for B in batches:
        args = (Pi[:B], Pj[:B], Hi[:B], Hj[:B])
        b = {}
        for name, fn in (
            ("DMV dmv_omega_batch", lambda: dmv_omega_batch(*args, R)),  # noqa: B023
            ("LDMV predict_omega", lambda: ldmv.predict_omega(*args)),  # noqa: B023
            ("PECMV pecmv_batch", lambda: pecmv_batch(*args, R)),  # noqa: B023
            ("LPECMV predict_C", lambda: lpecmv.predict_C(*args)),  # noqa: B023
        ):
            fn()
            b[name] = 1e6 * _best(fn, repeat) / B
        out["batched"][B] = b
    return out


def report(res: dict[str, Any]) -> None:
    """Print one m's table and its ratios."""
    m, s = res["m"], res["single"]
    print(f"\n## m = {m} (n = 9, R = {res['R']})\n")
    print("single call, median (us):")
    for name, t in s.items():
        print(f"  {name:<22} {t:10.1f}")
    print(f"  ratio DMV / LDMV update      {s['DMV update'] / s['LDMV update']:8.2f}x")
    print(f"  ratio PECMV / LPECMV update  {s['PECMV update'] / s['LPECMV update']:8.2f}x")
    for B, b in res["batched"].items():
        print(f"batched, B = {B}: us per problem (problems / s)")
        for name, t in b.items():
            print(f"  {name:<22} {t:10.2f} us  ({1e6 / t:12,.0f} /s)")
        print(f"  ratio DMV / LDMV      {b['DMV dmv_omega_batch'] / b['LDMV predict_omega']:8.2f}x")
        print(f"  ratio PECMV / LPECMV  {b['PECMV pecmv_batch'] / b['LPECMV predict_C']:8.2f}x")


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    """Parse the options, time m = 1 and / or m = 2, print; return the numbers."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--m", choices=("1", "2", "both"), default="both", help="measurement size")
    ap.add_argument("--single", type=int, default=300, help="timed single calls per algorithm")
    ap.add_argument("--repeat", type=int, default=3, help="batched runs (best kept)")
    ap.add_argument("--batches", default=",".join(map(str, BATCHES)),
                    help="comma-separated batch sizes (default 64,1024)")  # fmt: skip
    a = ap.parse_args(argv)
    try:
        batches = tuple(int(b) for b in a.batches.split(","))
    except ValueError:
        ap.error(f"--batches must be comma-separated integers, got {a.batches!r}")
    if not batches or min(batches) < 1:
        ap.error(f"--batches must be integers >= 1, got {a.batches!r}")
    torch.set_num_threads(1)
    ms = (1, 2) if a.m == "both" else (int(a.m),)
    results = []
    for m in ms:
        res = run(m, a.single, a.repeat, batches)
        report(res)
        results.append(res)
    return results


if __name__ == "__main__":
    main()
