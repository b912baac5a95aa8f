"""Inference speed of the shipped LDMV / LPECMV surrogates against the exact solvers.

Issue-6 targets: batched inference >= 200k predictions/s and a single call <= 100 us. The
inputs are real fusion problems from the surrogate dataset generator (n = 9, m = 1).

    .venv/bin/python benchmarks/bench_surrogates.py [--batch 20000] [--single 300]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import time

import numpy as np
import torch

from selenv.core.fusion import dmv_omega_batch, dmv_update, pecmv_batch, pecmv_update
from selenv.learned.surrogate_data import generate_dataset
from selenv.learned.surrogates import shipped


def _best(fn, repeat: int = 5) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=20_000)
    ap.add_argument("--single", type=int, default=300)
    a = ap.parse_args()
    torch.set_num_threads(1)
    data = generate_dataset(a.batch, seed=7, workers=1, progress=False)
    Pi, Pj, Hi, Hj, R = data.P_i, data.P_j, data.H_i, data.H_j, data.R  # R: (m, m), shared
    ldmv, lpecmv = shipped("ldmv"), shipped("lpecmv")
    rows = []
    B = len(data)
    for name, fn in (
        ("LDMV predict_omega (batched)", lambda: ldmv.predict_omega(Pi, Pj, Hi, Hj)),
        ("exact dmv_omega_batch", lambda: dmv_omega_batch(Pi, Pj, Hi, Hj, R)),
        ("LPECMV predict_C (batched)", lambda: lpecmv.predict_C(Pi, Pj, Hi, Hj)),
        ("exact pecmv_batch", lambda: pecmv_batch(Pi, Pj, Hi, Hj, R)),
    ):
        rows.append((name, B / _best(fn, 3)))
    print(f"batched, B = {B} problems (n = 9, m = 1): predictions per second")
    for name, rate in rows:
        print(f"  {name:<32} {rate:12,.0f} /s")
    k = a.single
    singles = (
        ("LDMV single call", lambda i: ldmv.predict_omega(Pi[i], Pj[i], Hi[i], Hj[i])),
        ("exact dmv_update (m = 1)", lambda i: dmv_update(Pi[i], Pj[i], Hi[i], Hj[i], R)),
        ("LPECMV single call", lambda i: lpecmv.predict_C(Pi[i], Pj[i], Hi[i], Hj[i])),
        ("exact pecmv_update (m = 1)", lambda i: pecmv_update(Pi[i], Pj[i], Hi[i], Hj[i], R)),
    )
    print(f"single calls, median of {k}:")
    for name, fn in singles:
        ts = []
        for i in range(k):
            t0 = time.perf_counter()
            fn(i)
            ts.append(time.perf_counter() - t0)
        print(f"  {name:<32} {1e6 * float(np.median(ts)):9.1f} us")


if __name__ == "__main__":
    main()
