"""Small Kalman updates: ``kf_update`` (validated and ``validate=False``) against FilterPy.

Workload (overhead ratios): constant-velocity model in 2-D, state ``n = 4`` (x, y, vx, vy), position
measurement ``m = 2``; ``P`` a random SPD covariance (exactly symmetric, as a filter produces
it), ``R = diag(0.5^2, 0.5^2)``. Each case is timed on the same inputs for every column.

Timing: one process, interleaved rounds (ours, FilterPy, ours-unvalidated, ours, FilterPy,
...), each round ``--number`` calls; the reported time per call is the median over
``--rounds`` rounds, so machine load affects every column alike. FilterPy's
``KalmanFilter.update()`` is timed with its state reset to the same prior before each call
(two attribute assignments, negligible). FilterPy is not a dependency of selenv: when it is
missing the FilterPy column is skipped with a message (``pip install filterpy==1.4.5``).

    .venv/bin/python benchmarks/bench_kalman.py [--rounds 41] [--number 2000] [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from selenv.core.kalman import kf_update

N, M = 4, 2


def make_case(rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """``(x, P, z, H, R)`` of a constant-velocity filter with a position measurement."""
    x = rng.normal(size=N) * np.array([10.0, 10.0, 1.0, 1.0])
    A = rng.normal(size=(N, N))
    P = A @ A.T + 0.5 * np.eye(N)
    P = 0.5 * (P + P.T)  # exactly symmetric, as kf_update / kf_predict return it
    H = np.zeros((M, N))
    H[0, 0] = H[1, 1] = 1.0
    R = np.diag([0.25, 0.25])
    z = H @ x + rng.normal(size=M) * 0.5
    return x, P, z, H, R


def filterpy_call(case: tuple[np.ndarray, ...]) -> tuple[Callable[[], Any], Any] | None:
    """A closure doing FilterPy's ``update()`` on ``case`` and its filter, or ``None``."""
    try:
        from filterpy.kalman import KalmanFilter
    except ImportError:
        return None
    x, P, z, H, R = case
    f = KalmanFilter(dim_x=N, dim_z=M)
    f.H, f.R = H.copy(), R.copy()
    x_col, z_col = x[:, None].copy(), z[:, None].copy()

    def run() -> None:
        f.x, f.P = x_col, P
        f.update(z_col)

    return run, f


def per_call(fn: Callable[[], Any], number: int) -> float:
    t = time.perf_counter()
    for _ in range(number):
        fn()
    return (time.perf_counter() - t) / number


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rounds", type=int, default=41)
    ap.add_argument("--number", type=int, default=2000)
    ap.add_argument("--profile", action="store_true", help="cProfile of the validated path")
    a = ap.parse_args()
    case = make_case(np.random.default_rng(0))
    fp = filterpy_call(case)
    cols: dict[str, Callable[[], Any]] = {"kf_update": lambda: kf_update(*case)}
    if fp is not None:
        run, kf = fp
        cols["filterpy"] = run
        ours = kf_update(*case)
        run()
        same = np.allclose(ours.x, kf.x[:, 0]) and np.allclose(ours.P, kf.P)
        print(f"FilterPy gives the same posterior: {same}")
    else:
        print("FilterPy not installed: its column is skipped (pip install filterpy==1.4.5)")
    cols["kf_update(validate=False)"] = lambda: kf_update(*case, validate=False)
    times: dict[str, list[float]] = {k: [] for k in cols}
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < 1.0:  # warm-up: let the clock settle
        for fn in cols.values():
            fn()
    for _ in range(a.rounds):  # interleaved: A, B, C, A, B, C, ...
        for k, fn in cols.items():
            times[k].append(per_call(fn, a.number))
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"n = {N}, m = {M}; median over {a.rounds} interleaved rounds of {a.number} calls")
    for k, t in med.items():
        line = f"  {k:28} {t * 1e6:8.2f} us"
        if "filterpy" in med and k != "filterpy":
            line += f"   {t / med['filterpy']:5.2f}x FilterPy"
        print(line)
    if a.profile:
        pr = cProfile.Profile()
        pr.enable()
        for _ in range(20000):
            kf_update(*case)
        pr.disable()
        pstats.Stats(pr).sort_stats("tottime").print_stats(12)


if __name__ == "__main__":
    main()
