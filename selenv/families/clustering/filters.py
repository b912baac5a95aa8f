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

**Time-varying noise.** Step ``t`` of every recursion uses the noise ``R_t`` of that step
(:meth:`~selenv.families.clustering.scenario.ClusteringProblem.axis_noise_steps`): the window pass
of
Algorithm 1 at time ``k`` uses ``R_{l+1} .. R_k``, the past and the current step only, and
:meth:`ClusterFilterBank.step` uses ``R_{k+1}``. The per-cluster ``R`` cache is used only when
the noise is fixed (it is keyed by the members alone).

Speed: clusters are keyed by their member tuple and cached for the current time step, so a
cluster shared by several candidates (or re-proposed by the GA) is filtered once; all new
clusters of one size are stacked and filtered together by :func:`window_pass` (the arithmetic of
:func:`selenv.core.riccati.riccati_pass`, bit for bit, without its per-call validation: one
batched solve per step instead of one Python loop per candidate). Candidate label vectors are
validated as one batch; their cluster keys are cached across steps and their costs within a
step (the GA re-proposes its population every generation).
:meth:`ClusterFilterBank.evaluate_changes` costs local edits (a few clusters replaced) without
building label vectors. Re-clustering (Algorithm 2, lines 17-19) re-initialises the filters with
the moments computed for the evaluation.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from typing import Any

import numpy as np

from selenv.core import npfast
from selenv.core.linalg import FloatArray
from selenv.core.riccati import history_overflow_error, riccati_step, singular_step_error
from selenv.families.clustering.labels import canonicalize
from selenv.families.clustering.scenario import (
    ClusteringProblem,
    CostBreakdown,
    clustering_cost,
    n_states,
)

__all__ = ["ClusterFilterBank", "cluster_keys", "window_pass"]

Key = tuple[int, ...]


def _raise_singular(err: str, flag: int) -> None:
    raise np.linalg.LinAlgError("Singular matrix")


def _solve(S: FloatArray, HP: FloatArray) -> FloatArray:
    """``np.linalg.solve(S, HP)`` for float64 stacks ``(B, p, p)``, ``(B, p, n)``: same bits.

    Call it inside ``np.errstate(call=_raise_singular, invalid="call", ...)`` (as
    ``np.linalg.solve`` sets it) so that a singular ``S`` raises ``LinAlgError``.
    """
    return npfast.solve(S, HP)


def window_pass(
    P0: FloatArray, F: FloatArray, Q: FloatArray, H: FloatArray, R: FloatArray, steps: int
) -> FloatArray:
    """:func:`~selenv.core.riccati.riccati_pass` for the bank's own (valid, float64) arrays.

    The same operations in the same order (bit-identical, tested), without the per-call input
    validation and with the solve's wrapper trimmed: Algorithm 1's hot path runs it for every
    group of new clusters. ``R`` is ``(B, p, p)`` or, per step, ``(B, steps, p, p)``; returns
    ``(B, steps + 1, n, n)``. Singular ``S`` and overflow raise riccati_pass's ``ValueError``.
    """
    B, n = P0.shape[0], P0.shape[1]
    per_step = R.ndim == 4
    out = np.empty((B, steps + 1, n, n))
    out[:, 0] = P0
    P, Ft, Ht = P0, F.T, H.T
    # np.linalg.solve's error state, set once per pass (an invalid result anywhere in a step
    # is then reported as singular; riccati_pass would report it as an overflow at the end)
    errstate = np.errstate(
        call=_raise_singular, invalid="call", over="ignore", divide="ignore", under="ignore"
    )
    t = 0
    try:
        with errstate:
            for t in range(1, steps + 1):
                R_t = R[:, t - 1] if per_step else R
                Pm = F @ P @ Ft + Q  # (11b)
                HP = H @ Pm
                S = HP @ Ht + R_t
                Pp = Pm - np.swapaxes(HP, -1, -2) @ _solve(S, HP)  # (12a) + (12c)
                P = 0.5 * (Pp + np.swapaxes(Pp, -1, -2))
                out[:, t] = P
    except np.linalg.LinAlgError:
        raise singular_step_error(t) from None
    if not np.all(np.isfinite(out)):
        raise history_overflow_error(steps)
    return out


def cluster_keys(canon: np.ndarray) -> list[Key]:
    """Member tuples of the clusters of a canonical labelling, in label order.

    Members in increasing index order (one Python pass; equal to splitting a stable argsort).
    """
    groups: dict[int, list[int]] = {}
    for i, label in enumerate(np.asarray(canon).tolist()):
        groups.setdefault(label, []).append(i)
    return [tuple(groups[label]) for label in sorted(groups)]


class ClusterFilterBank:
    """Per-cluster covariance filters of the current clustering, with Algorithm 1 costs.

    Args:
        problem: the scenario realisation.
        labels: initial clustering (n,), validated by ``problem.check_clustering``.

    Attributes:
        k: current time step (0 after construction: the posteriors are the prior).
        labels: current clustering, canonical (n,).
        n_cost_evaluations: candidate clusterings costed by :meth:`evaluate` and
            :meth:`evaluate_changes` so far.
        n_cluster_passes: cluster forward passes run by Algorithm 1 so far (cache misses).
    """

    # per-time-step caches (reset by _new_time_step)
    _window: dict[Key, FloatArray]
    _stats: dict[Key, tuple[float, int, float, float]]
    _costs: dict[Key, float]  # labels (as a tuple) -> eq. (10) at this step
    _prior_parts: tuple[FloatArray, float] | None
    _cost: CostBreakdown | None

    def __init__(self, problem: ClusteringProblem, labels: Any) -> None:
        self.problem = problem
        self.tau = int(problem.config.tau)
        self.weights = tuple(float(w) for w in problem.config.weights)
        self.labels = problem.check_clustering(labels, "labels")
        self.k = 0
        self._R: dict[Key, FloatArray] = {}
        self._key_cache: dict[Key, list[Key]] = {}  # labels (as a tuple) -> cluster keys
        self._keys = cluster_keys(self.labels)
        self._hist: dict[Key, FloatArray] = {
            key: problem.axis_prior(len(key))[None] for key in self._keys
        }
        self.n_cost_evaluations = 0
        self.n_cluster_passes = 0
        self._new_time_step()

    def fork(self, problem: ClusteringProblem | None = None) -> ClusterFilterBank:
        """An independent copy at the same time step, optionally on another ``problem``.

        For simulations (rollout): ``problem`` must agree with this bank's on the noise of
        steps ``<= k`` (the current step's Algorithm 1 caches are shared); it decides the noise
        of the steps the copy runs. Counters start at 0; this bank is never changed.
        """
        new = object.__new__(ClusterFilterBank)
        new.problem = self.problem if problem is None else problem
        new.tau, new.weights, new.k = self.tau, self.weights, self.k
        new.labels = self.labels.copy()
        new._R = self._R if problem is None else {}
        new._key_cache = self._key_cache if problem is None else {}
        new._keys = list(self._keys)
        new._hist = dict(self._hist)  # arrays are never written in place
        new.n_cost_evaluations = new.n_cluster_passes = 0
        new._new_time_step()
        new._window.update(self._window)
        new._stats.update(self._stats)
        return new

    # -- state ------------------------------------------------------------------------------
    @property
    def clusters(self) -> list[Key]:
        """Member tuples of the current clusters (canonical order)."""
        return list(self._keys)

    def current_sigma(self) -> FloatArray:
        """(n, 2) noise levels of the current step ``k`` (what the receivers observe now)."""
        return self.problem.sigma_at(self.k)

    def posteriors(self) -> list[FloatArray]:
        """Per-axis ``P_k|k`` of each current cluster, (2s+1, 2s+1) each."""
        return [self._hist[key][-1] for key in self._keys]

    def history(self, key: Key) -> FloatArray:
        """Stored posteriors ``P_l|l .. P_k|k`` of current cluster ``key``, (L, 2s+1, 2s+1)."""
        return self._hist[key]

    def cost(self) -> CostBreakdown:
        """Eq. (10) of the current clustering at time ``k`` (cached until it changes)."""
        if self._cost is None:
            self._cost = clustering_cost(self.posteriors(), self.weights)
        return self._cost

    def receiver_position_variance(self) -> FloatArray:
        """(n,) per-axis position variance of each receiver in its cluster's posterior."""
        out = np.empty(self.problem.n)
        members = [i for key in self._keys for i in key]
        out[members] = np.concatenate(
            [np.diagonal(self._hist[key][-1])[0 : 2 * len(key) : 2] for key in self._keys]
        )
        return out

    # -- time update ------------------------------------------------------------------------
    def step(self) -> None:
        """Advance every cluster filter one step (11b, 12c) with ``R_{k+1}``, batched by size."""
        by_size: dict[int, list[Key]] = defaultdict(list)
        for key in self._hist:
            by_size[len(key)].append(key)
        for keys in by_size.values():
            F, Q, H = self.problem.axis_model(keys[0])
            P = np.stack([self._hist[key][-1] for key in keys])
            R = self._noise(keys, self.k + 1, self.k + 2)
            R = R[:, 0] if R.ndim == 4 else R  # R_{k+1}
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
        keysets = self._keysets(arr)
        self._ensure({key for keys in keysets for key in keys})
        costs = self._costs
        out = np.empty(len(keysets))
        for b, (row, keys) in enumerate(zip(arr.tolist(), keysets, strict=True)):
            tag = tuple(row)
            J = costs.get(tag)
            if J is None:
                J = costs[tag] = self._cost_from_stats(keys)
            out[b] = J
        self.n_cost_evaluations += len(keysets)
        return out[0:1] if single else out

    def _keysets(self, arr: np.ndarray) -> list[list[Key]]:
        """Validated cluster keys of each row of ``arr`` (B, n), via a cache of known rows.

        The whole batch is checked at once (integers, values in ``[0, n)``); rows seen before
        (the GA re-proposes its population) are looked up by their labels; any row failing a
        check is re-validated by ``problem.check_clustering``, whose error names it.
        """
        problem = self.problem
        n = problem.n
        if arr.dtype.kind == "f":
            ok = bool(np.all(np.isfinite(arr)) and np.all(arr == np.round(arr)))
        else:
            ok = arr.dtype.kind in "iu"
        if ok and arr.size:
            ok = bool(arr.min() >= 0 and arr.max() < n)
        if not ok:  # the slow path names the first bad row
            for b, row in enumerate(arr):
                problem.check_clustering(row, f"candidates[{b}]")
        cache, cap = self._key_cache, problem.max_cluster_size
        keysets = []
        for b, row in enumerate(arr.astype(np.int64, copy=False).tolist()):
            tag = tuple(row)
            keys = cache.get(tag)
            if keys is None:
                keys = cluster_keys(canonicalize(np.array(row, dtype=np.int64)))
                if max(len(key) for key in keys) > cap:
                    problem.check_clustering(arr[b], f"candidates[{b}]")  # raises
                if len(cache) > 100_000:
                    cache.clear()
                cache[tag] = keys
            keysets.append(keys)
        return keysets

    def evaluate_changes(
        self, removed: Any, added: Sequence[Sequence[Key]]
    ) -> tuple[FloatArray, float]:
        """Cost eq. (10) of local changes of the current clustering (Algorithm 1), and ``J``.

        Candidate ``e`` drops the current clusters ``removed[e]`` (indices into
        :attr:`clusters`, ``-1`` for none) and adds the clusters ``added[e]`` (sorted member
        tuples). The caller guarantees that the result is a feasible partition (this is not
        checked; :func:`~selenv.families.clustering.env.edit_cost_changes` builds them from
        masked edits). Returns ``(J (E,), J_now)``, both by the same vectorised formula (their
        difference is what a local search compares). Counts ``E`` evaluations.
        """
        self._ensure(set(self._keys))
        cur = np.array([self._stats[key] for key in self._keys])  # (m, 4)
        a_G, a_C, a_L = self.weights
        J_now = a_G * cur[:, 0].sum() / cur[:, 1].sum() + a_C * cur[:, 2].max()
        J_now += a_L * cur[:, 3].max()
        if not added:
            return np.zeros(0), float(J_now)
        rem = np.asarray(removed, dtype=np.int64).reshape(len(added), -1)
        m = cur.shape[0]
        width = max((len(a) for a in added), default=0)
        new_keys = sorted({key for keys in added for key in keys})
        self._ensure(set(new_keys))
        index = {key: i for i, key in enumerate(new_keys)}
        stats = np.array([self._stats[key] for key in new_keys]).reshape(-1, 4)
        stats = np.vstack([stats, [0.0, 0.0, -np.inf, -np.inf]])  # row -1: no cluster
        add = np.full((len(added), width), -1, dtype=np.int64)
        for e, keys in enumerate(added):
            add[e, : len(keys)] = [index[key] for key in keys]
        keep = np.ones((len(added), m), dtype=bool)
        rows = np.repeat(np.arange(len(added)), rem.shape[1])
        valid = rem.reshape(-1) >= 0
        keep[rows[valid], rem.reshape(-1)[valid]] = False
        a = stats[add]  # (E, width, 4)
        trace = np.where(keep, cur[:, 0], 0.0).sum(1) + a[..., 0].sum(1)
        size = np.where(keep, cur[:, 1], 0.0).sum(1) + a[..., 1].sum(1)
        J_C = np.maximum(
            np.where(keep, cur[:, 2], -np.inf).max(1), a[..., 2].max(1, initial=-np.inf)
        )
        J_L = np.maximum(
            np.where(keep, cur[:, 3], -np.inf).max(1), a[..., 3].max(1, initial=-np.inf)
        )
        J = a_G * trace / size + a_C * J_C + a_L * J_L
        self.n_cost_evaluations += len(added)
        return J, float(J_now)

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
        self._keys = keys
        self._cost = None
        return True

    # -- internals --------------------------------------------------------------------------
    def _noise(self, keys: list[Key], k0: int, k1: int) -> FloatArray:
        """``R`` of clusters ``keys`` (one size) for steps ``k0 .. k1 - 1``.

        Fixed noise: ``(B, p, p)`` from the per-cluster cache (keyed by the members, so it is
        used only then); time-varying noise: ``(B, k1 - k0, p, p)``, one per step.
        """
        if self.problem.time_varying:
            return self.problem.axis_noise_steps(np.array(keys, dtype=np.int64), k0, k1)
        Rs = []
        for key in keys:
            R = self._R.get(key)
            if R is None:
                if len(self._R) > 100_000:
                    self._R.clear()
                R = self._R[key] = self.problem.axis_noise(key)
            Rs.append(R)
        return np.stack(Rs)

    def _new_time_step(self) -> None:
        """Reset the per-step caches: current clusters are known, the rest is computed lazily."""
        self._window = dict(self._hist)
        self._stats = {}
        self._costs = {}
        self._prior_parts = None
        self._cost = None

    def _composed_priors(self, keys: list[Key]) -> FloatArray:
        """Steps 1-2 of Algorithm 1: priors ``(B, 2s+1, 2s+1)`` of clusters ``keys`` (one size)."""
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
        members = np.array(keys, dtype=np.int64)  # (B, s)
        B, s = members.shape
        rows = np.stack([2 * members, 2 * members + 1], axis=2).reshape(B, 2 * s)
        P0 = np.zeros((B, 2 * s + 1, 2 * s + 1))
        P0[:, : 2 * s, : 2 * s] = U[rows[:, :, None], rows[:, None, :]]
        P0[:, 2 * s, 2 * s] = theta_var
        return P0

    def _composed_prior(self, key: Key) -> FloatArray:
        """Steps 1-2 of Algorithm 1: prior of cluster ``key`` at the window start."""
        return self._composed_priors([key])[0]

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
                P0 = self._composed_priors(group)
                R = self._noise(group, self.k - steps + 1, self.k + 1)  # R_{l+1} .. R_k
                hist = window_pass(P0, F, Q, H, R, steps)
                self._store(group, hist)
            self.n_cluster_passes += len(missing)
        for key in keys:
            if key not in self._stats:
                self._store([key], self._window[key][None])

    def _store(self, keys: list[Key], hist: FloatArray) -> None:
        """Cache the windows ``hist`` (B, L, d, d) of ``keys`` (one size) and their statistics."""
        s = len(keys[0])
        P = hist[:, -1]
        trace = 2.0 * np.trace(P, axis1=1, axis2=2)
        pos = np.diagonal(P, axis1=1, axis2=2)[:, 0 : 2 * s : 2]
        rows = zip(trace.tolist(), pos.mean(1).tolist(), pos.max(1).tolist(), strict=True)
        for key, h, (tr, mean, worst) in zip(keys, hist, rows, strict=True):
            self._window[key] = h
            self._stats[key] = (tr, n_states(s), mean, worst)

    def _cost_from_stats(self, keys: list[Key]) -> float:
        """Eq. (10) from cached per-cluster statistics (same formula as ``clustering_cost``)."""
        stats = [self._stats[key] for key in keys]
        J_G = sum(st[0] for st in stats) / sum(st[1] for st in stats)
        J_C = max(st[2] for st in stats)
        J_L = max(st[3] for st in stats)
        a_G, a_C, a_L = self.weights
        return float(a_G * J_G + a_C * J_C + a_L * J_L)
