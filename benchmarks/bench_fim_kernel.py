"""The FIM pick update's refresh, numpy/BLAS against a compiled (numba) kernel.

What a compiled kernel would buy for ``FIMSelection``'s per-step cost: the refresh after a pick
(``Z = G L^-T``, ``Z^T = L^-1 G^T``, the 2x2 grams ``S_k = Z_k Z_k^T`` and the log-det gains
``log det(I + S_k)``, :meth:`selenv.families.fim.batched.FIMBatchState._refresh`) is timed at
the defaults' shape (``N = 200`` candidates of ``m = 2`` rows over ``d = 7`` parameters) and
``B = --batch`` sub-envs against two numba kernels of the same math:

* ``numba, candidate-major``: a loop nest per candidate over ``(N, m, d)`` rows (the naive
  port; ``L^-1`` triangular, so half the products);
* ``numba, parameter-major``: the fused kernel over the ``(d, m, N)`` layout of the batch state,
  the candidate axis innermost so the compiler vectorises it, the gram and the gains in the same
  pass (no ``Z`` in the observation's layout: a lower bound on what a fused kernel costs).

Each kernel's gains are checked against the numpy path (relative difference printed) before
timing. One process, one BLAS thread, interleaved rounds, medians, microseconds per sub-env.
numba is not a dependency of selenv: install it to run this (``pip install numba``).

    .venv/bin/python benchmarks/bench_fim_kernel.py [--rounds 7] [--batch 256]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable

import numpy as np

from selenv.families.fim.batched import FIMBatchState
from selenv.threads import limit_threads


def _kernels() -> tuple[Callable[..., None], Callable[..., None]]:
    import numba

    @numba.njit(cache=False)
    def candidate_major(G, Linv, Z, gains):
        B, N, m, d = G.shape
        for b in range(B):
            L = Linv[b]
            for n in range(N):
                for a in range(m):
                    for i in range(d):
                        s = 0.0
                        for j in range(i + 1):
                            s += G[b, n, a, j] * L[i, j]
                        Z[b, n, a, i] = s
                s00 = 0.0
                s01 = 0.0
                s11 = 0.0
                for i in range(d):
                    z0 = Z[b, n, 0, i]
                    z1 = Z[b, n, 1, i]
                    s00 += z0 * z0
                    s01 += z0 * z1
                    s11 += z1 * z1
                gains[b, n] = np.log1p(s00 + s11 + s00 * s11 - s01 * s01)

    @numba.njit(cache=False)
    def parameter_major(GT, Linv, ZT, gains):
        B, d, m, N = GT.shape
        s00 = np.empty(N)
        s01 = np.empty(N)
        s11 = np.empty(N)
        for b in range(B):
            L = Linv[b]
            s00[:] = 0.0
            s01[:] = 0.0
            s11[:] = 0.0
            for i in range(d):
                z0 = ZT[b, i, 0]
                z1 = ZT[b, i, 1]
                z0[:] = 0.0
                z1[:] = 0.0
                for j in range(i + 1):
                    lij = L[i, j]
                    g0 = GT[b, j, 0]
                    g1 = GT[b, j, 1]
                    for n in range(N):
                        z0[n] += lij * g0[n]
                        z1[n] += lij * g1[n]
                for n in range(N):
                    s00[n] += z0[n] * z0[n]
                    s01[n] += z0[n] * z1[n]
                    s11[n] += z1[n] * z1[n]
            for n in range(N):
                gains[b, n] = np.log1p(s00[n] + s11[n] + s00[n] * s11[n] - s01[n] * s01[n])

    return candidate_major, parameter_major


def main(argv: list[str] | None = None) -> int:
    """Print the table; 2 when numba is missing or an option is bad."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=7, help="interleaved rounds (median)")
    p.add_argument("--batch", type=int, default=256, help="sub-envs B")
    p.add_argument("--calls", type=int, default=20, help="refreshes per timing")
    args = p.parse_args(argv)
    if args.rounds < 1 or args.batch < 1 or args.calls < 1:
        p.error("--rounds, --batch and --calls must be >= 1")
    try:
        candidate_major, parameter_major = _kernels()
    except ImportError:
        print("bench_fim_kernel: needs numba (pip install numba)", file=sys.stderr)
        return 2
    B, N, m, d = args.batch, 200, 2, 7
    rng = np.random.default_rng(0)
    state = FIMBatchState(B, np.eye(d), (N, m, d))
    state.start(np.arange(B), rng.standard_normal((B, N, m, d)))
    for _ in range(5):  # a few picks, so L^-1 is a real triangular factor
        state.add(np.arange(B), rng.choice(N, size=B))
    Z, ZT, g1, g2 = (
        np.empty((B, N, m, d)),
        np.empty((B, d, m, N)),
        np.empty((B, N)),
        np.empty((B, N)),
    )
    assert state._GT is not None
    contenders: dict[str, Callable[[], None]] = {
        "numpy/BLAS (shipped)": lambda: state._refresh(slice(None), state.G, state._GT, state.Linv),
        "numba, candidate-major": lambda: candidate_major(state.G, state.Linv, Z, g1),
        "numba, parameter-major (fused)": lambda: parameter_major(state._GT, state.Linv, ZT, g2),
    }
    for f in contenders.values():
        f()  # compile, warm the caches
    ref = state.gains
    for name, got in (("numba, candidate-major", g1), ("numba, parameter-major (fused)", g2)):
        print(f"{name}: max relative difference of the gains {np.max(np.abs(got - ref) / ref):.1e}")
    times: dict[str, list[float]] = {k: [] for k in contenders}
    with limit_threads(1):
        for _ in range(args.rounds):
            for name, f in contenders.items():
                t0 = time.perf_counter()
                for _ in range(args.calls):
                    f()
                times[name].append((time.perf_counter() - t0) / args.calls / B * 1e6)
    base = statistics.median(times["numpy/BLAS (shipped)"])
    print(
        f"\nrefresh at B = {B}, N = {N}, m = {m}, d = {d} "
        f"(us per sub-env, median of {args.rounds})\n"
    )
    print("| refresh | us per sub-env | speed-up over numpy/BLAS |\n|---|---|---|")
    for name, ts in times.items():
        t = statistics.median(ts)
        print(f"| {name} | {t:.2f} | {base / t:.2f}x |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
