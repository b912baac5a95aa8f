"""Cluster Kalman filters and the cost of candidate clusterings (Greiff et al. 2022, Alg. 1).

:class:`ClusterFilterBank` holds the (per-axis, covariance-only) filters of the clusters in use
and the last ``tau + 1`` posteriors of each. :meth:`ClusterFilterBank.evaluate` costs candidate
clusterings by Algorithm 1:

1. compose the prior at the window start ``l = k - tau`` from the current clusters' posteriors
   at ``l``: each receiver's unique block (with the cross-covariances to receivers of its old
   cluster) and the bias block averaged over the old clusters, cross terms to the bias dropped
   (steps 1-2, ``P_l = sum_i M^ui' P^i M^ui + |C|^-1 M^si' P^i M^si``; read per new cluster);
2. run the Kalman recursion (11b)/(12c) over the window for every cluster that is new, and keep
   the current posterior ``P_k|k`` for every cluster that is unchanged (steps 3-9);
3. evaluate eq. (10) on the resulting posteriors (step 10).

Speed: clusters are keyed by their member tuple and cached for the current time step, so a
cluster shared by several candidates (or re-proposed by the GA) is filtered once; all new
clusters of one size are stacked and filtered together by :func:`selenv.core.riccati.riccati_pass`
(one batched solve per step instead of one Python loop per candidate). Re-clustering (Algorithm 2,
lines 17-19) re-initialises the filters with the moments computed for the evaluation.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import numpy as np

from selenv.core.linalg import FloatArray
from selenv.core.riccati import riccati_pass, riccati_step
from selenv.scenarios.clustering import ClusteringProblem, CostBreakdown, clustering_cost, n_states

__all__ = ["ClusterFilterBank", "cluster_keys"]

Key = tuple[int, ...]


def cluster_keys(canon: np.ndarray) -> list[Key]:
    """Member tuples of the clusters of a canonical labelling, in label order."""
    order = np.argsort(canon, kind="stable")
    bounds = np.flatnonzero(np.diff(canon[order])) + 1
    return [tuple(int(i) for i in part) for part in np.split(order, bounds)]


class ClusterFilterBank:
    """Per-cluster covariance filters of the current clustering, with Algorithm 1 costs.

    Args:
        problem: the scenario realisation.
        labels: initial clustering (n,), validated by ``problem.check_clustering``.

    Attributes:
        k: current time step (0 after construction: the posteriors are the prior).
        labels: current clustering, canonical (n,).
        n_cost_evaluations: candidate clusterings costed by :meth:`evaluate` so far.
        n_cluster_passes: cluster forward passes run by Algorithm 1 so far (cache misses).
    """

    def __init__(self, problem: ClusteringProblem, labels: Any) -> None:
        self.problem = problem
        self.tau = int(problem.config.tau)
        self.weights = tuple(float(w) for w in problem.config.weights)
        self.labels = problem.check_clustering(labels, "labels")
        self.k = 0
        self._R: dict[Key, FloatArray] = {}
        self._hist: dict[Key, FloatArray] = {
            key: problem.axis_prior(len(key))[None] for key in cluster_keys(self.labels)
        }
        self.n_cost_evaluations = 0
        self.n_cluster_passes = 0
        self._new_time_step()

    # -- state ------------------------------------------------------------------------------
    @property
    def clusters(self) -> list[Key]:
        """Member tuples of the current clusters (canonical order)."""
        return cluster_keys(self.labels)

    def posteriors(self) -> list[FloatArray]:
        """Per-axis ``P_k|k`` of each current cluster, (2s+1, 2s+1) each."""
        return [self._hist[key][-1] for key in self.clusters]

    def history(self, key: Key) -> FloatArray:
        """Stored posteriors ``P_l|l .. P_k|k`` of current cluster ``key``, (L, 2s+1, 2s+1)."""
        return self._hist[key]

    def cost(self) -> CostBreakdown:
        """Eq. (10) of the current clustering at time ``k``."""
        return clustering_cost(self.posteriors(), self.weights)

    def receiver_position_variance(self) -> FloatArray:
        """(n,) per-axis position variance of each receiver in its cluster's posterior."""
        out = np.empty(self.problem.n)
        for key in self.clusters:
            P = self._hist[key][-1]
            out[list(key)] = np.diagonal(P)[0 : 2 * len(key) : 2]
        return out

    # -- time update ------------------------------------------------------------------------
    def step(self) -> None:
        """Advance every cluster filter one step (11b, 12c), batched over equal sizes."""
        by_size: dict[int, list[Key]] = defaultdict(list)
        for key in self._hist:
            by_size[len(key)].append(key)
        for keys in by_size.values():
            F, Q, H = self.problem.axis_model(keys[0])
            P = np.stack([self._hist[key][-1] for key in keys])
            R = np.stack([self._noise(key) for key in keys])
            P_new = riccati_step(P, F, Q, H, R)
            for key, Pk in zip(keys, P_new, strict=True):
                hist = np.concatenate([self._hist[key], Pk[None]])
                self._hist[key] = hist[-(self.tau + 1) :]
        self.k += 1
        self._new_time_step()

    # -- Algorithm 1 ------------------------------------------------------------------------
    def evaluate(self, candidates: Any) -> FloatArray:
        """Cost eq. (10) of each candidate clustering at time ``k`` (Algorithm 1), (B,).

        Args:
            candidates: (B, n) or (n,) integer labels; each must be feasible.

        Raises:
            TypeError / ValueError: non-integer, wrong shape or infeasible candidate (named by
            its row).
        """
        arr = np.asarray(candidates)
        single = arr.ndim == 1
        arr = arr[None] if single else arr
        if arr.ndim != 2 or arr.shape[1] != self.problem.n:
            raise ValueError(
                f"candidates must have shape (B, {self.problem.n}) or ({self.problem.n},), "
                f"got {np.shape(candidates)}"
            )
        keysets = [
            cluster_keys(self.problem.check_clustering(row, f"candidates[{b}]"))
            for b, row in enumerate(arr)
        ]
        self._ensure({key for keys in keysets for key in keys})
        out = np.array([self._cost_from_stats(keys) for keys in keysets])
        self.n_cost_evaluations += len(keysets)
        return out[0:1] if single else out

    def evaluate_breakdown(self, labels: Any) -> CostBreakdown:
        """:class:`CostBreakdown` of one candidate at time ``k`` (Algorithm 1)."""
        keys = cluster_keys(self.problem.check_clustering(labels, "labels"))
        self._ensure(set(keys))
        return clustering_cost([self._window[key][-1] for key in keys], self.weights)

    def recluster(self, labels: Any) -> bool:
        """Switch to ``labels``; new clusters start from the moments of their evaluation.

        Algorithm 2, lines 17-19: unchanged clusters keep their filters; every new cluster's
        history becomes its Algorithm 1 forward pass over the window. Returns whether the
        partition changed.
        """
        canon = self.problem.check_clustering(labels, "labels")
        if np.array_equal(canon, self.labels):
            return False
        keys = cluster_keys(canon)
        self._ensure(set(keys))
        self._hist = {key: self._window[key] for key in keys}
        self.labels = canon
        return True

    # -- internals --------------------------------------------------------------------------
    def _noise(self, key: Key) -> FloatArray:
        R = self._R.get(key)
        if R is None:
            if len(self._R) > 100_000:
                self._R.clear()
            R = self._R[key] = self.problem.axis_noise(key)
        return R

    def _new_time_step(self) -> None:
        """Reset the per-step caches: current clusters are known, the rest is computed lazily."""
        self._window: dict[Key, FloatArray] = dict(self._hist)
        self._stats: dict[Key, tuple[float, int, float, float]] = {}
        self._prior_parts: tuple[FloatArray, float] | None = None

    def _composed_prior(self, key: Key) -> FloatArray:
        """Steps 1-2 of Algorithm 1: prior of cluster ``key`` at the window start."""
        if self._prior_parts is None:
            n = self.problem.n
            U = np.zeros((2 * n, 2 * n))  # per-axis unique covariance of all receivers at l
            theta = []
            for old, hist in self._hist.items():
                P = hist[0]
                s = len(old)
                idx = np.ravel([[2 * i, 2 * i + 1] for i in old])
                U[np.ix_(idx, idx)] = P[: 2 * s, : 2 * s]
                theta.append(P[2 * s, 2 * s])
            self._prior_parts = (U, float(np.mean(theta)))  # bias: mean over old clusters
        U, theta_var = self._prior_parts
        s = len(key)
        idx = np.ravel([[2 * i, 2 * i + 1] for i in key])
        P0 = np.zeros((2 * s + 1, 2 * s + 1))
        P0[: 2 * s, : 2 * s] = U[np.ix_(idx, idx)]
        P0[2 * s, 2 * s] = theta_var
        return P0

    def _ensure(self, keys: set[Key]) -> None:
        """Forward passes (steps 3-9) for the clusters not in the window cache, by size."""
        missing = [key for key in keys if key not in self._window]
        if missing:
            steps = next(iter(self._hist.values())).shape[0] - 1  # k - l
            by_size: dict[int, list[Key]] = defaultdict(list)
            for key in missing:
                by_size[len(key)].append(key)
            for group in by_size.values():
                F, Q, H = self.problem.axis_model(group[0])
                P0 = np.stack([self._composed_prior(key) for key in group])
                R = np.stack([self._noise(key) for key in group])
                hist = riccati_pass(P0, F, Q, H, R, steps)
                for key, h in zip(group, hist, strict=True):
                    self._window[key] = h
            self.n_cluster_passes += len(missing)
        for key in keys:
            if key not in self._stats:
                P = self._window[key][-1]
                s = len(key)
                pos = np.diagonal(P)[0 : 2 * s : 2]
                self._stats[key] = (2.0 * float(np.trace(P)), n_states(s), pos.mean(), pos.max())

    def _cost_from_stats(self, keys: list[Key]) -> float:
        """Eq. (10) from cached per-cluster statistics (same formula as ``clustering_cost``)."""
        stats = [self._stats[key] for key in keys]
        J_G = sum(st[0] for st in stats) / sum(st[1] for st in stats)
        J_C = max(st[2] for st in stats)
        J_L = max(st[3] for st in stats)
        a_G, a_C, a_L = self.weights
        return float(a_G * J_G + a_C * J_C + a_L * J_L)
