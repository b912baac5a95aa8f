"""Batched core of the receiver-clustering filters, cost and masks (Greiff et al. 2022).

Every function here works on arrays with a leading batch axis and is the *only* implementation
of its equation: the single env (through
:class:`~selenv.families.clustering.filters.ClusterFilterBank`) calls it with the clusters of
one filter bank, the native vector env
(:class:`~selenv.families.clustering.vector.ReceiverClusteringVectorEnv`) with the clusters of
all ``B`` sub-envs at once. Clusters of one size ``s`` share the per-axis model ``(F, Q, H)``,
so they are stacked (``M`` clusters, from any number of sub-envs) and filtered by one call;
the per-cluster quantities (noise levels, priors, statistics) are gathered and scattered with
index arrays: ``owner (M,)`` the sub-env of each cluster and ``members (M, s)`` its receivers.

Seed-independent tables (the per-axis model of a cluster size, the correlation matrix of
eq. (4), the prior) are computed once per configuration (module-level caches keyed by the
configuration values) and handed out read-only (``flags.writeable = False``).

Symbols: ``n`` receivers, ``s`` receivers of a cluster, ``d = 2s + 1`` per-axis states,
``p = 2s`` per-axis measurements, ``T`` steps of a window.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from selenv.core import npfast
from selenv.core.linalg import FloatArray
from selenv.core.riccati import history_overflow_error, riccati_step, singular_step_error
from selenv.families.clustering.labels import IntArray

__all__ = [
    "assignment_masks",
    "axis_model",
    "axis_prior",
    "cluster_statistics",
    "clustering_costs",
    "correlation",
    "edit_masks",
    "filter_step",
    "label_counts",
    "noise_covariances",
    "regime_paths",
    "window_pass",
]

# -- seed-independent tables, cached per configuration ------------------------------------------
_AXIS_MODELS: dict[tuple[float, int], tuple[FloatArray, FloatArray, FloatArray]] = {}
_CORRELATIONS: dict[tuple[float, int], FloatArray] = {}
_PRIORS: dict[tuple[tuple[float, float, float], int], FloatArray] = {}
_SWAP_PAIRS: dict[int, tuple[IntArray, IntArray]] = {}
#: entries kept per cache before it is cleared (a guard for long-lived processes)
_CACHE_LIMIT = 4096


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _remember(cache: dict[Any, Any], key: object, value: object) -> None:
    if len(cache) >= _CACHE_LIMIT:
        cache.clear()
    cache[key] = value


def axis_model(dt: float, s: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(F, Q, H)`` of a cluster of ``s`` receivers, per axis (eqs. 3a-3b), read-only.

    State ``(p_1, v_1, ..., p_s, v_s, theta)`` (``d = 2s + 1``), measurements
    ``(y1_1, y2_1, ..., y1_s, y2_s)`` with ``y1 = p - theta``, ``y2 = p + theta``: ``F`` and
    ``Q`` ``(d, d)``, ``H`` ``(2s, d)``. Cached per ``(dt, s)``.
    """
    key = (float(dt), int(s))
    model = _AXIS_MODELS.get(key)
    if model is None:
        h = float(dt)
        F = np.eye(2 * s + 1)
        Q = np.zeros((2 * s + 1, 2 * s + 1))
        H = np.zeros((2 * s, 2 * s + 1))
        for a in range(s):
            F[2 * a, 2 * a + 1] = h  # p' = p + h v (3a)
            Q[2 * a : 2 * a + 2, 2 * a : 2 * a + 2] = [[h**3 / 3, h**2 / 2], [h**2 / 2, h]]
            H[2 * a, [2 * a, 2 * s]] = [1.0, -1.0]  # y1 = p - theta (3b)
            H[2 * a + 1, [2 * a, 2 * s]] = [1.0, 1.0]  # y2 = p + theta
        Q[2 * s, 2 * s] = h
        model = (_frozen(F), _frozen(Q), _frozen(H))
        _remember(_AXIS_MODELS, key, model)
    return model


def correlation(r: float, s: int) -> FloatArray:
    """``rho`` ``(s, s)`` of eq. (4): 1 on the diagonal, ``r`` elsewhere; cached, read-only."""
    key = (float(r), int(s))
    rho = _CORRELATIONS.get(key)
    if rho is None:
        rho = _frozen(np.full((s, s), float(r)) + (1.0 - float(r)) * np.eye(s))
        _remember(_CORRELATIONS, key, rho)
    return rho


def axis_prior(prior_std: Sequence[float], s: int) -> FloatArray:
    """Initial per-axis covariance ``diag(sp^2, sv^2, ..., sb^2)`` ``(d, d)``; cached, read-only."""
    sp, sv, sb = (float(v) for v in prior_std)
    key = ((sp, sv, sb), int(s))
    P = _PRIORS.get(key)
    if P is None:
        P = _frozen(np.diag([sp**2, sv**2] * s + [sb**2]))
        _remember(_PRIORS, key, P)
    return P


def swap_pairs(n: int) -> tuple[IntArray, IntArray]:
    """The pairs ``i < j`` of the swap edits, ``np.triu_indices(n, k=1)``; cached, read-only."""
    pairs = _SWAP_PAIRS.get(n)
    if pairs is None:
        iu, ju = np.triu_indices(n, k=1)
        pairs = (_frozen(iu.astype(np.int64)), _frozen(ju.astype(np.int64)))
        _remember(_SWAP_PAIRS, n, pairs)
    return pairs


# -- noise, filters, cost -----------------------------------------------------------------------
def noise_covariances(levels: FloatArray, rho: FloatArray) -> FloatArray:
    """Per-axis measurement covariances of clusters from their receivers' noise levels.

    Eq. (4) per axis: ``R[(a, c), (b, c)] = rho_ab sigma_ca sigma_cb`` (channels ``c`` = y1, y2
    uncorrelated, measurement order ``y1_1, y2_1, ..., y1_s, y2_s``).

    Args:
        levels: ``(..., s, 2)`` noise std devs of each cluster's members (any leading axes:
            clusters, or clusters and steps).
        rho: ``(s, s)`` correlation (:func:`correlation`).

    Returns:
        ``(..., 2s, 2s)``.
    """
    s = levels.shape[-2]
    R = np.zeros((*levels.shape[:-2], 2 * s, 2 * s))
    for c in range(2):
        sc = levels[..., c]
        R[..., c::2, c::2] = rho * (sc[..., :, None] * sc[..., None, :])  # as np.outer
    return R


def filter_step(
    P: FloatArray, F: FloatArray, Q: FloatArray, H: FloatArray, R: FloatArray
) -> FloatArray:
    """One prediction and update of ``M`` cluster filters (eqs. 11b, 12a, 12c), ``(M, d, d)``.

    ``P^- = F P F^T + Q``, ``P^+ = P^- - (H P^-)^T S^-1 (H P^-)`` with ``S = H P^- H^T + R``
    (:func:`~selenv.core.riccati.riccati_step`; a solve, never an inverse). ``P`` ``(M, d, d)``
    posteriors at ``k``, ``R`` ``(M, 2s, 2s)`` the noise of step ``k + 1``.
    """
    return riccati_step(P, F, Q, H, R)


def _raise_singular(err: str, flag: int) -> None:
    raise np.linalg.LinAlgError("Singular matrix")


def window_pass(
    P0: FloatArray,
    F: FloatArray,
    Q: FloatArray,
    H: FloatArray,
    R: FloatArray,
    steps: int,
    out: FloatArray | None = None,
) -> FloatArray:
    """Algorithm 1's forward pass (steps 3-9) of ``M`` clusters of one size, batched.

    :func:`~selenv.core.riccati.riccati_pass` for valid float64 arrays: the same operations in
    the same order (bit-identical, tested), without the per-call input validation and with the
    solve's wrapper trimmed. ``P0`` ``(M, d, d)``; ``R`` ``(M, p, p)`` or, per step,
    ``(M, steps, p, p)`` (``R[:, t - 1]`` for step ``t``); returns ``(M, steps + 1, d, d)``,
    written into ``out`` if given (a float64 array or view of that shape). Singular ``S`` and
    overflow raise riccati_pass's ``ValueError``.
    """
    B, n = P0.shape[0], P0.shape[1]
    per_step = R.ndim == 4
    if out is None:
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
                Pp = Pm - np.swapaxes(HP, -1, -2) @ npfast.solve(S, HP)  # (12a) + (12c)
                P = 0.5 * (Pp + np.swapaxes(Pp, -1, -2))
                out[:, t] = P
    except np.linalg.LinAlgError:
        raise singular_step_error(t) from None
    if not np.all(np.isfinite(out)):
        raise history_overflow_error(steps)
    return out


def cluster_statistics(P: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per-cluster terms of eq. (10) from ``M`` per-axis posteriors ``P`` ``(M, d, d)``.

    The full covariance is ``P (x) I_2``, so per cluster: ``2 tr P`` (its total MSE), the mean
    and the largest per-coordinate position variance ``P[2a, 2a]``. Returns three ``(M,)``.
    """
    s = (P.shape[-1] - 1) // 2
    trace2 = 2.0 * np.trace(P, axis1=1, axis2=2)
    pos = np.diagonal(P, axis1=1, axis2=2)[:, 0 : 2 * s : 2]
    return trace2, pos.mean(1), pos.max(1)


def clustering_costs(
    trace2: FloatArray,
    states: FloatArray,
    mean: FloatArray,
    worst: FloatArray,
    owner: IntArray,
    n_envs: int,
    weights: Sequence[float],
) -> FloatArray:
    """Eq. (10) of ``n_envs`` clusterings from their clusters' statistics, ``(n_envs, 4)``.

    Columns ``(J, J_G, J_C, J_L)`` with ``J_G = sum_j 2 tr P_j / sum_j N(C_j)``,
    ``J_C = max_j mean_a P_j[2a, 2a]``, ``J_L = max_j max_a P_j[2a, 2a]`` and
    ``J = a_G J_G + a_C J_C + a_L J_L``. The ``(M,)`` inputs list every cluster of every
    clustering, each clustering's clusters in its cluster order, ``owner`` naming the
    clustering (every one of ``0 .. n_envs - 1`` has a cluster); the sums accumulate in that
    order from 0, as a loop over the clusters does (``np.bincount``: same bits).
    """
    total = np.bincount(owner, weights=trace2, minlength=n_envs)
    count = np.bincount(owner, weights=states, minlength=n_envs)
    J_C = np.full(n_envs, -np.inf)
    J_L = np.full(n_envs, -np.inf)
    np.maximum.at(J_C, owner, mean)
    np.maximum.at(J_L, owner, worst)
    out = np.empty((n_envs, 4))
    out[:, 1] = total / count
    out[:, 2] = J_C
    out[:, 3] = J_L
    a_G, a_C, a_L = (float(w) for w in weights)
    out[:, 0] = a_G * out[:, 1] + a_C * J_C + a_L * J_L
    return out


# -- labels and masks ---------------------------------------------------------------------------
def label_counts(labels: IntArray) -> IntArray:
    """Members per label of each row of ``labels`` ``(B, n)`` (values in ``[0, n)``), ``(B, n)``."""
    n = labels.shape[1]
    return (labels[:, :, None] == np.arange(n)).sum(1)


def edit_masks(labels: IntArray, max_size: int) -> np.ndarray:
    """Allowed edits of ``B`` canonical clusterings ``(B, n)``: ``(B, 1 + n^2 + n(n-1)/2)`` bool.

    Row by row :func:`~selenv.families.clustering.env.edit_mask`: the no-op; ``i`` joins
    ``j``'s cluster (they differ and it has room) or leaves to a singleton (``i == j``, its
    cluster has other members); swaps of pairs ``i < j`` in different clusters, not both
    singletons.
    """
    B, n = labels.shape
    size = np.take_along_axis(label_counts(labels), labels, axis=1)  # (B, n) own cluster size
    same = labels[:, :, None] == labels[:, None, :]
    move = ~same & (size < max_size)[:, None, :]
    diag = np.arange(n)
    move[:, diag, diag] = size > 1
    iu, ju = swap_pairs(n)
    alone = size == 1  # swapping two singletons leaves the partition unchanged
    swap = ~same[:, iu, ju] & ~(alone[:, iu] & alone[:, ju])
    out = np.empty((B, 1 + n * n + iu.size), dtype=np.bool_)
    out[:, 0] = True
    out[:, 1 : 1 + n * n] = move.reshape(B, n * n)
    out[:, 1 + n * n :] = swap
    return out


def assignment_masks(labels: IntArray, max_size: int) -> np.ndarray:
    """Per-receiver label masks of ``B`` clusterings ``(B, n)``: ``(B, n * n)`` bool.

    Row ``i`` of each ``(n, n)`` block: the labels receiver ``i`` may take if every other
    receiver stays (labels with room, and its own).
    """
    B, n = labels.shape
    room = label_counts(labels) < max_size  # (B, n)
    mask = np.broadcast_to(room[:, None, :], (B, n, n)).copy()
    mask[np.arange(B)[:, None], np.arange(n)[None, :], labels] = True  # staying is allowed
    return mask.reshape(B, n * n)


# -- regimes ------------------------------------------------------------------------------------
def regime_paths(start: FloatArray, u: FloatArray, p_enter: float, p_leave: float) -> FloatArray:
    """Paths of ``B`` two-state chains (open sky 0 / degraded 1), ``(B, steps + 1, n)``.

    ``x_0 = start`` ``(B, n)``; ``x_{t+1} = [u_t >= p_leave]`` if ``x_t`` is degraded, else
    ``[u_t < p_enter]``, with the uniforms ``u`` ``(B, steps, n)`` (each sub-env's own draws).
    """
    B, steps, n = u.shape
    out = np.empty((B, steps + 1, n))
    out[:, 0] = start
    for t in range(steps):
        bad = out[:, t] > 0.5
        out[:, t + 1] = np.where(bad, u[:, t] >= p_leave, u[:, t] < p_enter)
    return out
