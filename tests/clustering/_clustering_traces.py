"""Helpers shared by the clustering GA tests (a plain module, so no test module imports another).

The traces split a run into *decisions* (integer data: populations, labels, counters), which are
compared exactly, and float *values*, which callers compare with ``np.testing.assert_allclose``
(``rtol=1e-9``): BLAS kernels differ in the last bits of a float, never in a robust decision.
"""

from __future__ import annotations

import hashlib

import numpy as np

from selenv.families.clustering.ga import GAConfig, GeneticClustering, random_feasible_clustering


class ToyCost:
    """J = sum over same-cluster pairs i<j of (W_ij - beta): joining dissimilar agents costs.

    Batched like the real cost; counts calls and candidates; ``drift`` is added per call.
    """

    def __init__(self, n: int, seed: int, beta: float = 0.5, drift: float = 0.0):
        r = np.random.default_rng(seed)
        W = r.uniform(0.0, 1.0, size=(n, n))
        self.M = (W + W.T) / 2 - beta
        np.fill_diagonal(self.M, 0.0)
        self.drift = drift
        self.calls = 0
        self.candidates = 0
        self.batch_shapes: list[tuple[int, ...]] = []

    def base(self, labels: np.ndarray) -> np.ndarray:
        c = np.atleast_2d(labels)
        same = c[:, :, None] == c[:, None, :]  # (B, n, n)
        return 0.5 * np.sum(same * self.M[None], axis=(1, 2))

    def __call__(self, candidates: np.ndarray) -> np.ndarray:
        self.calls += 1
        self.candidates += len(candidates)
        self.batch_shapes.append(candidates.shape)
        return self.base(candidates) + self.drift * self.calls


def ga_trace(seed: int, n: int = 12, max_size: int = 3, gens: int = 12, **cfg):
    """(sha256 prefix of every int64 population, final best labels, final best cost) of a GA run.

    The hash covers integer data only, so it is exact on any machine; the cost is a float value.
    """
    cost = ToyCost(n, seed)
    x0 = random_feasible_clustering(n, max_size, np.random.default_rng(seed))
    ga = GeneticClustering(cost, x0, max_size, GAConfig(**cfg), rng=seed)
    h = hashlib.sha256(ga.population.astype(np.int64).tobytes())
    for _ in range(gens):
        ga.generation()
        h.update(ga.population.astype(np.int64).tobytes())
    return h.hexdigest()[:16], ga.best.tolist(), float(ga.best_cost)


def assert_trace_matches(got: tuple, want: tuple) -> None:
    """Decisions (population hash, best labels) exactly; the best cost to ``rtol=1e-9``."""
    assert (got[0], got[1]) == (want[0], want[1])
    np.testing.assert_allclose(got[2], want[2], rtol=1e-9)
