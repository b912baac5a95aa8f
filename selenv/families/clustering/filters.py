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
from dataclasses import dataclass
from typing import Any

import numpy as np

from selenv.core.linalg import FloatArray
from selenv.families.clustering.batched import (
    axis_model,
    cluster_statistics,
    clustering_costs,
    correlation,
    filter_step,
    noise_covariances,
    window_pass,
)
from selenv.families.clustering.labels import IntArray, canonicalize
from selenv.families.clustering.scenario import (
    ClusteringProblem,
    CostBreakdown,
    n_states,
)

__all__ = [
    "BankStep",
    "ClusterFilterBank",
    "bank_costs",
    "cluster_keys",
    "ensure_windows",
    "recluster_banks",
    "step_banks",
    "window_pass",
]

Key = tuple[int, ...]


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
        self._ring: dict[Key, tuple[FloatArray, int, FloatArray]] = {}
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
        new._hist = dict(self._hist)  # handed-out rows are never written
        new._ring = {}  # the buffers stay this bank's: the fork copies on its first step
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
        """Eq. (10) of the current clustering at time ``k`` (cached until it changes).

        Computed by :func:`bank_costs` (the batched cost the vector env uses, one bank).
        """
        cost = self._cost
        if cost is None:
            cost = self._cost = CostBreakdown(*bank_costs([self])[0].tolist())
        return cost

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
        """Advance every cluster filter one step (11b, 12c) with ``R_{k+1}``: :func:`step_banks`."""
        step_banks([self])

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
        history becomes its Algorithm 1 forward pass over the window (:func:`recluster_banks`).
        Returns whether the partition changed.
        """
        canon = self.problem.check_clustering(labels, "labels")
        return bool(recluster_banks([self], [canon])[0])

    # -- internals --------------------------------------------------------------------------
    def _append(self, key: Key, hist: FloatArray, P: FloatArray) -> FloatArray:
        """History ``hist`` of cluster ``key`` with ``P`` appended, its last ``tau + 1`` rows.

        Histories live in buffers owned by one bank (``_ring``: buffer, rows used, the view
        handed out): while ``hist`` is this bank's latest view of its buffer and the buffer has
        room, ``P`` is written into the next, never handed-out row (no copy; every view ever
        handed out stays valid). Otherwise (a new cluster's window, a fork's shared history,
        a full buffer) the kept rows move to a new buffer (:func:`_capacity` rows).
        """
        tau1 = self.tau + 1
        ring = self._ring.get(key)
        if ring is not None and ring[2] is hist and ring[1] < ring[0].shape[0]:
            buf, end = ring[0], ring[1]
        else:
            L = hist.shape[0]
            keep = min(L, self.tau)
            buf = np.empty((_capacity(self.tau), *hist.shape[1:]))
            buf[:keep] = hist[L - keep :]
            end = keep
        buf[end] = P
        end += 1
        view = buf[max(0, end - tau1) : end]
        self._ring[key] = (buf, end, view)
        return view

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
        if len(self._ring) > len(self._hist):  # buffers of windows not adopted
            self._ring = {key: ring for key, ring in self._ring.items() if key in self._hist}
        self._stats = {}
        self._costs = {}
        self._prior_parts = None
        self._cost = None

    def _composed_priors(self, keys: list[Key]) -> FloatArray:
        """Steps 1-2 of Algorithm 1: priors ``(B, 2s+1, 2s+1)`` of clusters ``keys`` (one size)."""
        _prior_parts([self])
        return _compose_priors([self], np.zeros(len(keys), dtype=np.int64), keys)

    def _composed_prior(self, key: Key) -> FloatArray:
        """Steps 1-2 of Algorithm 1: prior of cluster ``key`` at the window start."""
        return self._composed_priors([key])[0]

    def _ensure(self, keys: set[Key]) -> None:
        """Forward passes (steps 3-9) of the clusters not in the window cache (batched core)."""
        ensure_windows([self], [keys])

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


# -- the filters of several banks at once (the vector env; a bank alone is the B = 1 case) -----
@dataclass(frozen=True, eq=False)
class BankStep:
    """What :func:`step_banks` computed for ``B`` banks after their step.

    Attributes:
        costs: ``(B, 4)`` eq. (10) ``(J, J_G, J_C, J_L)`` of each bank at its new time.
        position_var: ``(B, n)`` per-axis position variance of each receiver in its cluster.
    """

    costs: FloatArray
    position_var: FloatArray


def _shared_model(banks: Sequence[ClusterFilterBank]) -> tuple[float, float, int]:
    """``(dt, r, tau)`` of the banks, which must agree (``ValueError`` otherwise)."""
    cfg = banks[0].problem.config
    key = (float(cfg.dt), float(cfg.noise_correlation), int(cfg.tau), banks[0].problem.n)
    for bank in banks[1:]:
        c = bank.problem.config
        if c is not cfg and (c.dt, c.noise_correlation, c.tau, bank.problem.n) != key:
            raise ValueError(
                "banks must share n_agents, dt, noise_correlation and tau to be filtered together"
            )
    return key[0], key[1], key[2]


def _flatten(banks: Sequence[ClusterFilterBank]) -> tuple[list[Key], IntArray, IntArray]:
    """Every current cluster of every bank in (bank, cluster) order: keys, owners, sizes."""
    keys: list[Key] = []
    owner: list[int] = []
    for b, bank in enumerate(banks):
        keys.extend(bank._keys)
        owner.extend([b] * len(bank._keys))
    sizes = np.fromiter(map(len, keys), dtype=np.int64, count=len(keys))
    return keys, np.array(owner, dtype=np.int64), sizes


def _capacity(tau: int) -> int:
    """Rows of a history buffer: the ``tau + 1`` kept and ``min(tau + 1, 32)`` to grow into."""
    return tau + 1 + min(tau + 1, 32)


def step_banks(banks: Sequence[ClusterFilterBank]) -> BankStep:
    """Advance every cluster filter of every bank one step (eqs. 11b, 12c) with its ``R_{k+1}``.

    The clusters of one size, across all banks, are stacked ``(M, d, d)`` and advanced by one
    :func:`~selenv.families.clustering.batched.filter_step`, their noise
    ``R_{k+1}`` ``(M, 2s, 2s)`` built by one
    :func:`~selenv.families.clustering.batched.noise_covariances` from the levels of each
    bank's step ``k + 1``; each history keeps its last ``tau + 1`` posteriors. The new
    posteriors' eq. (10) statistics are cached (the current clusters' Algorithm 1 costs need no
    further pass) and every bank's cost is computed by
    :func:`~selenv.families.clustering.batched.clustering_costs`. Banks may be at different
    times; they must share the model (``n_agents``, ``dt``, ``noise_correlation``, ``tau``).
    """
    dt, r, _ = _shared_model(banks)
    B, n = len(banks), banks[0].problem.n
    keys, owner, sizes = _flatten(banks)
    M = len(keys)
    levels = np.stack([bank.problem.sigma_at(bank.k + 1) for bank in banks])  # (B, n, 2)
    trace2, mean, worst = np.empty(M), np.empty(M), np.empty(M)
    position_var = np.empty((B, n))
    hists = [banks[o]._hist[key] for o, key in zip(owner.tolist(), keys, strict=True)]
    stats: list[dict[Key, tuple[float, int, float, float]]] = [{} for _ in banks]
    for s in np.unique(sizes).tolist():
        sel = np.flatnonzero(sizes == s)
        own = owner[sel]
        members = np.array([keys[m] for m in sel.tolist()], dtype=np.int64)  # (M_s, s)
        P = np.stack([hists[m][-1] for m in sel.tolist()])
        F, Q, H = axis_model(dt, s)
        R = noise_covariances(levels[own[:, None], members], correlation(r, s))  # R_{k+1}
        P_new = filter_step(P, F, Q, H, R)
        tr, mn, wr = cluster_statistics(P_new)
        trace2[sel], mean[sel], worst[sel] = tr, mn, wr
        position_var[own[:, None], members] = np.diagonal(P_new, axis1=1, axis2=2)[:, 0 : 2 * s : 2]
        ns = n_states(s)
        rows = zip(
            sel.tolist(), own.tolist(), P_new, tr.tolist(), mn.tolist(), wr.tolist(), strict=True
        )
        for m, o, Pk, tr_m, mn_m, wr_m in rows:
            key = keys[m]
            bank = banks[o]
            bank._hist[key] = bank._append(key, hists[m], Pk)
            stats[o][key] = (tr_m, ns, mn_m, wr_m)
    states = (4 * sizes + 2).astype(np.float64)  # N(C) = 4s + 2
    costs = clustering_costs(trace2, states, mean, worst, owner, B, banks[0].weights)
    for bank, c, st in zip(banks, costs.tolist(), stats, strict=True):
        bank.k += 1
        bank._new_time_step()
        bank._stats = st
        bank._cost = CostBreakdown(*c)
    return BankStep(costs=costs, position_var=position_var)


def bank_costs(banks: Sequence[ClusterFilterBank]) -> FloatArray:
    """Eq. (10) ``(J, J_G, J_C, J_L)`` of each bank's current clustering, ``(B, 4)``.

    Cached costs are reused; the others come from the current clusters' statistics
    (computed for those not cached, by size across the banks) through one
    :func:`~selenv.families.clustering.batched.clustering_costs`. Sets each bank's cost cache.
    """
    out = np.empty((len(banks), 4))
    todo = [b for b, bank in enumerate(banks) if bank._cost is None]
    for b, bank in enumerate(banks):
        if bank._cost is not None:
            c = bank._cost
            out[b] = (c.J, c.J_G, c.J_C, c.J_L)
    if todo:
        sub = [banks[b] for b in todo]
        _ensure_stats(sub, [bank._keys for bank in sub])
        stats = np.array([bank._stats[key] for bank in sub for key in bank._keys])  # (M, 4)
        owner = np.repeat(np.arange(len(sub)), [len(bank._keys) for bank in sub])
        costs = clustering_costs(
            stats[:, 0], stats[:, 1], stats[:, 2], stats[:, 3], owner, len(sub), sub[0].weights
        )
        for bank, c in zip(sub, costs.tolist(), strict=True):
            bank._cost = CostBreakdown(*c)
        out[todo] = costs
    return out


def _ensure_stats(banks: Sequence[ClusterFilterBank], keysets: Sequence[Any]) -> None:
    """Cache the eq. (10) statistics of the windowed clusters ``keysets[b]`` of bank ``b``."""
    by_size: dict[int, list[tuple[int, Key]]] = defaultdict(list)
    for b, (bank, keys) in enumerate(zip(banks, keysets, strict=True)):
        stats = bank._stats
        for key in keys:
            if key not in stats:
                by_size[len(key)].append((b, key))
    for s, items in by_size.items():
        P = np.stack([banks[b]._window[key][-1] for b, key in items])
        rows = zip(*(a.tolist() for a in cluster_statistics(P)), strict=True)
        for (b, key), (tr, mn, wr) in zip(items, rows, strict=True):
            banks[b]._stats[key] = (tr, n_states(s), mn, wr)


def _prior_parts(banks: Sequence[ClusterFilterBank]) -> None:
    """Steps 1-2 of Algorithm 1, the parts of every bank lacking them (cached per time step).

    Per bank: ``U`` ``(2n, 2n)``, the per-axis unique covariance of all receivers at the
    window start ``l`` (each current cluster's block of ``P_l|l``, no cross terms between
    clusters), and the bias variance averaged over the current clusters. The blocks of one
    cluster size are scattered into the ``(B, 2n, 2n)`` stack at once.
    """
    need = [bank for bank in banks if bank._prior_parts is None]
    if not need:
        return
    n = need[0].problem.n
    U = np.zeros((len(need), 2 * n, 2 * n))
    keys, owner, sizes = _flatten(need)
    firsts = [need[o]._hist[key][0] for o, key in zip(owner.tolist(), keys, strict=True)]
    theta = np.empty(len(keys))  # bias variance of each old cluster at l
    for s in np.unique(sizes).tolist():
        sel = np.flatnonzero(sizes == s)
        own = owner[sel]
        members = np.array([keys[m] for m in sel.tolist()], dtype=np.int64)
        rows = np.stack([2 * members, 2 * members + 1], axis=2).reshape(sel.size, 2 * s)
        P_l = np.stack([firsts[m] for m in sel.tolist()])  # (M_s, 2s+1, 2s+1)
        U[own[:, None, None], rows[:, :, None], rows[:, None, :]] = P_l[:, : 2 * s, : 2 * s]
        theta[sel] = P_l[:, 2 * s, 2 * s]
    # the mean over each bank's clusters: banks with as many clusters as rows of one array
    # (a row's mean has the bits of np.mean of that bank's list)
    counts = np.bincount(owner, minlength=len(need))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    mean_theta = np.empty(len(need))
    for c in np.unique(counts).tolist():
        which = np.flatnonzero(counts == c)
        mean_theta[which] = theta[starts[which][:, None] + np.arange(c)].mean(axis=1)
    for j, (bank, t) in enumerate(zip(need, mean_theta.tolist(), strict=True)):
        bank._prior_parts = (U[j], t)  # bias: mean over old clusters


def _compose_priors(
    banks: Sequence[ClusterFilterBank], owner: IntArray, keys: Sequence[Key]
) -> FloatArray:
    """Priors ``(M, 2s+1, 2s+1)`` at the window start of clusters ``keys`` (one size ``s``).

    Algorithm 1 steps 1-2, ``P_l = sum_i M^ui' P^i M^ui + |C|^-1 M^si' P^i M^si`` read per new
    cluster: its members' rows and columns of bank ``owner[m]``'s ``U`` and the mean bias
    variance (needs :func:`_prior_parts`).
    """
    members = np.array(keys, dtype=np.int64).reshape(len(keys), -1)  # (M, s)
    M, s = members.shape
    used = np.unique(owner)
    U = np.stack([banks[b]._prior_parts[0] for b in used.tolist()])
    theta = np.array([banks[b]._prior_parts[1] for b in used.tolist()])
    local = np.searchsorted(used, owner)
    rows = np.stack([2 * members, 2 * members + 1], axis=2).reshape(M, 2 * s)
    P0 = np.zeros((M, 2 * s + 1, 2 * s + 1))
    P0[:, : 2 * s, : 2 * s] = U[local[:, None, None], rows[:, :, None], rows[:, None, :]]
    P0[:, 2 * s, 2 * s] = theta[local]
    return P0


def _window_noise(
    banks: Sequence[ClusterFilterBank], owner: IntArray, members: IntArray, steps: int
) -> FloatArray:
    """``R_{l+1} .. R_k`` of clusters ``members`` ``(M, s)`` of banks ``owner`` ``(M,)``.

    Time-varying noise: ``(M, steps, 2s, 2s)``, the levels of each step of each bank's own
    window; fixed noise: ``(M, 2s, 2s)``.
    """
    s = members.shape[1]
    rho = correlation(banks[0].problem.config.noise_correlation, s)
    used = np.unique(owner)
    local = np.searchsorted(used, owner)
    if not banks[0].problem.time_varying:
        levels = np.stack([banks[b].problem.sigma for b in used.tolist()])  # (G, n, 2)
        return noise_covariances(levels[local[:, None], members], rho)
    paths = []
    for b in used.tolist():
        problem, k = banks[b].problem, banks[b].k
        k0 = k - steps + 1
        problem._check_step(k0, "k0")
        problem._check_step(k, "k1 - 1")
        paths.append(problem.sigma_path[k0 : k + 1])
    W = np.stack(paths)  # (G, steps, n, 2)
    t = np.arange(steps)
    return noise_covariances(W[local[:, None, None], t[None, :, None], members[:, None, :]], rho)


def ensure_windows(banks: Sequence[ClusterFilterBank], keysets: Sequence[Any]) -> None:
    """Algorithm 1 (steps 1-9) for the clusters ``keysets[b]`` of bank ``b`` not yet windowed.

    The new clusters of one size and window length, across all banks, start from their
    composed priors (steps 1-2) and run one
    :func:`~selenv.families.clustering.batched.window_pass` over ``R_{l+1} .. R_k`` of their
    bank; windows and eq. (10) statistics are cached per bank for the current time step.
    """
    if not banks:
        return
    dt, _, tau = _shared_model(banks)
    groups: dict[tuple[int, int, bool], list[tuple[int, Key]]] = defaultdict(list)
    passes = [0] * len(banks)
    for b, (bank, keys) in enumerate(zip(banks, keysets, strict=True)):
        window = bank._window
        missing = [key for key in keys if key not in window]
        if missing:
            steps = next(iter(bank._hist.values())).shape[0] - 1  # k - l
            tv = bank.problem.time_varying
            for key in missing:
                groups[(len(key), steps, tv)].append((b, key))
            passes[b] = len(missing)
    if groups:
        _prior_parts([banks[b] for b, n_new in enumerate(passes) if n_new])
    for (s, steps, _), items in groups.items():
        owner = np.array([b for b, _ in items], dtype=np.int64)
        keys = [key for _, key in items]
        members = np.array(keys, dtype=np.int64)
        F, Q, H = axis_model(dt, s)
        P0 = _compose_priors(banks, owner, keys)
        R = _window_noise(banks, owner, members, steps)
        # the windows are the first rows of history buffers with room to grow (_append)
        block = np.empty((len(items), _capacity(tau), 2 * s + 1, 2 * s + 1))
        hist = window_pass(P0, F, Q, H, R, steps, out=block[:, : steps + 1])
        rows = zip(*(a.tolist() for a in cluster_statistics(hist[:, -1])), strict=True)
        for (b, key), buf, h, (tr, mn, wr) in zip(items, block, hist, rows, strict=True):
            bank = banks[b]
            bank._window[key] = h
            bank._ring[key] = (buf, steps + 1, h)
            bank._stats[key] = (tr, n_states(s), mn, wr)
    for bank, n_new in zip(banks, passes, strict=True):
        bank.n_cluster_passes += n_new
    _ensure_stats(banks, keysets)


def recluster_banks(banks: Sequence[ClusterFilterBank], labels: Sequence[IntArray]) -> np.ndarray:
    """Switch bank ``b`` to the canonical, feasible clustering ``labels[b]`` (not re-checked).

    Algorithm 2, lines 17-19, for all banks at once: the new clusters' forward passes run in
    one :func:`ensure_windows`; unchanged clusters keep their filters. Returns ``(B,)`` bool,
    whether each partition changed.
    """
    changed = np.zeros(len(banks), dtype=np.bool_)
    todo: list[tuple[int, IntArray, list[Key]]] = []
    for b, (bank, canon) in enumerate(zip(banks, labels, strict=True)):
        if not np.array_equal(canon, bank.labels):
            todo.append((b, canon, cluster_keys(canon)))
    if todo:
        ensure_windows([banks[b] for b, _, _ in todo], [keys for _, _, keys in todo])
    for b, canon, keys in todo:
        bank = banks[b]
        bank._hist = {key: bank._window[key] for key in keys}
        bank.labels = np.array(canon, dtype=np.int64)
        bank._keys = keys
        bank._cost = None
        changed[b] = True
    return changed
