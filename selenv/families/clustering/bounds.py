r"""A certified bound on a ReceiverClustering episode's return: per-receiver oracle filters.

The reward of filter step ``k`` is ``-J_k`` with ``J = a_G J_G + a_C J_C + a_L J_L`` (Greiff et
al. 2022, eq. (10)), evaluated on the posteriors of the cluster Kalman filters (eqs. (11b),
(12c)); :func:`step_lower_bounds` gives a lower bound on every ``J_k`` that holds for *every*
sequence of feasible clusterings, so ``-sum_k LB_k`` bounds every policy's return
(:func:`return_bound`, the ``FamilySpec.return_bound`` hook). Cost: a few 2x2 Riccati
recursions over the receivers, milliseconds at the defaults; an optional refinement (step 7)
runs exact cluster filters over the window, tens of seconds per default episode.

Why not the centralised filter
------------------------------
The natural reference, one Kalman filter on all receivers and all measurements from ``k = 0``,
is **not** a lower bound here. Algorithm 1 (steps 1-2) builds a new cluster's prior at the window
start ``l = k - tau`` by *dropping* the cross-covariances between the old clusters' unique
blocks and between every unique block and the bias (and averaging the bias variance over the
old clusters). Dropping the cross terms of a covariance is not conservative in the Loewner order
(``diag(M) >= M`` fails for ``M = [[1, c], [c, 1]]``), so a re-formed cluster can claim more than
the data support. Counterexample (pinned by the tests): ``preset="paper"``, ``n_agents=3``,
``n_max_states=10``, ``tau=1``, ``horizon=5``, ``weights=(0, 0, 1)``, seed 10, clusterings
``[0,1,1], [0,1,1], [0,1,0], [0,1,1], [0,1,0]``: the return -0.455 beats the centralised
"bound" ``-sum_k max_a P^c_k[p_a] = -0.478``. At the defaults the centralised filter would also
be looser than the oracle below (it ignores the cluster size limit).

The bound (each step holds for this code, not only for the paper's idealisation)
-------------------------------------------------------------------------------
Per axis a cluster ``C`` of ``s`` receivers has state ``(u_1, .., u_s, theta)``,
``u_a = (p_a, v_a)``; channels ``y_{a,c} = p_a -/+ theta + e_{a,c}`` with noise (eq. (4))
``Cov(e_{a,c}, e_{b,c}) = rho_ab sigma_{a,c} sigma_{b,c}`` (channels independent). Write
``Schur_a(P) = Cov(u_a | every other state of the cluster)`` ``= ((P^-1)_{u_a u_a})^-1``.

1. *Step lemma.* For every cluster ``C`` containing ``a`` and every ``P``, the filter step
   ``Phi_C`` (eqs. (11b), (12c), with ``R_t``) satisfies
   ``Schur_a(Phi_C(P)) >= phi_{a,t}^{kappa_s}(Schur_a(P))``, where ``phi`` is the 2x2 Kalman
   step of ``u_a`` alone measuring ``p_a`` in each channel with noise variance
   ``kappa_s sigma_{a,c}(t)^2`` and ``kappa_s = 1 - r^2 (s-1) / (1 + (s-2) r)`` (the variance of
   ``e_{a,c}`` given the ``s - 1`` mates' noise). Proof: ``Schur_a(Phi_C(P)) =
   Cov(u_a' | z', y') >= Cov(u_a' | z, z', y')`` (``z`` the other states; conditioning on more
   lowers a Gaussian conditional covariance); given ``z, z'``, ``u_a'`` has prior
   ``F Schur_a(P) F' + Q`` (``F, Q`` block diagonal) and, ``theta'`` and the mates' positions
   being known, the measurements reveal the mates' noise and leave ``p_a' + e_{a,c}`` with
   conditional variance ``kappa_s sigma_{a,c}^2``. ``kappa_s`` decreases in ``s`` and ``phi`` is
   monotone, so with ``s_max`` (``max_size``) the bound holds for every feasible cluster.
2. *Composition (Algorithm 1, steps 1-2).* The composed prior is block diagonal over the groups
   "members that come from the same old cluster" and the bias, so its ``Schur_a`` is
   ``Cov(u_a | group mates)`` under the old cluster's posterior at ``l``, which is
   ``>= Schur_a`` of that posterior (conditioning on fewer states). Averaging the bias does not
   enter ``Schur_a``.
3. *Oracle invariant.* By induction over the order in which the code creates matrices (the prior
   ``diag(prior_std^2)``, filter steps, window passes from composed priors, whose history rows are
   aligned in time), every matrix a cluster filter holds at time ``t`` has
   ``Schur_a >= O^a_t``, the 2x2 recursion ``O_0 = diag(sp^2, sv^2)``,
   ``O_t = phi_{a,t}^{kappa_{s_max}}(O_{t-1})``: a filter that knows the bias and the other
   receivers' states exactly (the θ-known oracle). The marginal variances dominate the
   conditional ones: ``P[p_a] >= O^a_t[0, 0]``, ``P[v_a] >= O^a_t[1, 1]``.
4. *Window lemma (size-aware).* The cluster ``C`` holding ``a`` at time ``k`` has filtered only
   ``C``'s measurements over ``l+1 .. k``, ``l = max(0, k - tau)``: it was formed at some
   ``k' <= k`` by a window pass from ``max(0, k' - tau)`` and stepped since. So
   ``Schur_a >= L^{(s)}_a(k) = phi^{kappa_s}_{l+1..k}(O^a_l)`` with ``s = |C|`` (any shorter
   window is valid too). ``L^{(s_max)} = O``; singletons (``kappa_1 = 1``) are much worse.
5. *Bias.* Every cluster's bias variance ``P[theta] >= Cov(theta | all u) >= w_t``, with
   ``w_t = 1 / (1 / (w_{t-1} + h) + I_t)``, ``w_0 = sb^2`` and ``I_t`` an upper bound on the bias
   information ``sum_c 1' R_{C,c}^-1 1 = sum_c (sum_C g^2 - beta_s (sum_C g)^2) / (1 - r)``
   (``g = 1 / sigma_c``, ``beta_s = r / (1 + (s-1) r)``) of any feasible cluster; since
   ``(sum g)^2 >= sum g^2``, ``I_t = sum_c max_s (1 - beta_s) top_s(g_c^2) / (1 - r)``. The
   composed prior's bias (a mean of old bias variances) is independent of the ``u``'s, so the
   invariant survives Algorithm 1.
6. *The terms of eq. (10)* at step ``k`` (``m`` clusters, sizes ``s_j <= s_max``):

   * ``J_L = max_j max_a P_j[p_a] >= max_a O^a_k[0, 0]``;
   * ``J_C = max_j mean_{a in C_j} P_j[p_a]`` is at least the mean of the cluster holding any
     ``a``: ``>= max_a min_{s <= s_max} (L^{(s)}_a + (s - 1) smallest L^{(s)}_b, b != a) / s``,
     and at least the size-weighted mean of the cluster means, i.e. the mean over receivers;
   * ``J_G = 2 (sum_a (P[p_a] + P[v_a]) + sum_j P_j[theta]) / (4 n + 2 m)``: for each feasible
     ``m`` at least ``N_j(m) = max(0, m - floor((n - m) / j))`` receivers sit in clusters of
     size ``<= j``, so the numerator is ``>= 2 (sum_a tr O^a_k + sum_{j < s_max}`` (the
     ``N_j(m)`` smallest ``tr L^{(j)}_a - tr L^{(j+1)}_a``) ``+ m w_k)``; minimised over
     ``m in [ceil(n / s_max), n]``. The same relaxation bounds the mean over receivers.

   Weights are ``>= 0``, so ``J_k >= a_G LB_G + a_C LB_C + a_L LB_L``; the bound is shrunk by a
   relative ``1e-9`` for rounding.

7. *Cluster windows (optional, :func:`cluster_window_bounds`).* By step 4 the posterior of the
   cluster ``C`` holding ``a`` is the exact filter of ``C`` over ``l+1 .. k`` from a matrix the
   filters can hold at ``l``, which is the prior when ``l = 0`` and otherwise
   ``>= blockdiag(O^b_l (b in C), w_l) / (s + 1)`` (``P^-1 <= (s + 1)`` times its block
   diagonal over the ``s + 1`` blocks; the diagonal blocks of ``P^-1`` are ``Schur_b^-1`` and
   ``Cov(theta | u)^-1``). Running that filter (the env's own step) from that start bounds the
   whole posterior, and ``J_L >= min_{C ni a} B_C[p_a]``, ``J_C >= min_{C ni a} mean_C B_C[p]``
   over every feasible cluster holding ``a``, for any set of receivers ``a``.

Invalid actions: with ``invalid_action="noop"`` a positive ``invalid_action_penalty`` can be
collected at every placement (``-v2``: ``n`` per filter step) or filter step (``-v1``); it is
added. ``invalid_action="terminate"`` lets a policy end the episode after one step, so the only
certified value is ``max(penalty, .)``, which says nothing about clustering: ``None``.

Where the slack is (defaults, 30 seeds): the oracle knows the bias and the mates' positions (a
cluster does not: about 1.4x on the position variance of the worst receivers, which step 7
recovers for ``J_L`` and ``J_C``); each receiver is credited with the best mates independently,
although good mates are shared; ``J_G`` is bounded with the oracle only.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from selenv.core.linalg import FloatArray
from selenv.families.clustering.batched import axis_model
from selenv.families.clustering.labels import IntArray
from selenv.families.spec import ReturnBound

__all__ = [
    "RELATIVE_SLACK",
    "StepLowerBounds",
    "bias_reference",
    "cluster_window_bounds",
    "cluster_windows_count",
    "measurement_kappa",
    "oracle_reference",
    "return_bound",
    "step_lower_bounds",
    "windowed_references",
]

#: relative safety margin for floating-point rounding of the filters and of the bound
RELATIVE_SLACK = 1e-9
#: largest ``(sizes - 1) * window * horizon * n`` of the size-aware windowed references; above,
#: the window is shortened (still valid, slightly looser)
WINDOW_WORK = 20_000_000
#: elements per array of one time chunk (memory stays bounded at any horizon)
CHUNK_ELEMENTS = 1 << 20

METHOD = "per-receiver oracle filters (bias and mates known), cluster-size windows"


def measurement_kappa(r: float, s: int) -> float:
    """``kappa_s``: variance factor of one receiver's noise given its ``s - 1`` mates' (eq. 4)."""
    if s <= 1:
        return 1.0
    return float(1.0 - r * r * (s - 1) / (1.0 + (s - 2) * r))


def _levels(problem: Any, t0: int, t1: int) -> FloatArray:
    """``(t1 - t0, n, 2)`` noise levels of steps ``t0 .. t1 - 1`` (a view when possible)."""
    path = problem.sigma_path
    if path is None:
        return np.broadcast_to(np.asarray(problem.sigma, dtype=float), (t1 - t0, problem.n, 2))
    return np.asarray(path[t0:t1], dtype=float)


def _inv_var(problem: Any, t0: int, t1: int) -> FloatArray:
    """``(t1 - t0, n)``: ``sum_c 1 / sigma_{a,c}(t)^2`` of steps ``t0 .. t1 - 1``."""
    return (1.0 / _levels(problem, t0, t1) ** 2).sum(-1)


def _oracle_step(
    a: FloatArray, b: FloatArray, c: FloatArray, info: FloatArray, h: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One 2x2 step (11b), (12c) of ``[[a, b], [b, c]]``, measuring ``p`` with information ``info``.

    Prediction with a receiver's block of the cluster model (:func:`axis_model`, eq. 3a:
    ``F = [[1, f], [0, 1]]``, ``Q``), then the scalar update ``P - P e e' P / (e' P e + 1 / info)``
    written entrywise (elementwise arrays).
    """
    F, Q, _ = axis_model(h, 1)
    f = F[0, 1]
    m00 = a + f * (2.0 * b + f * c) + Q[0, 0]
    m01 = b + f * c + Q[0, 1]
    m11 = c + Q[1, 1]
    d = 1.0 + info * m00
    return m00 / d, m01 / d, m11 - info * m01 * m01 / d


def _as_matrices(a: FloatArray, b: FloatArray, c: FloatArray) -> FloatArray:
    out = np.empty((*a.shape, 2, 2))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = a, b, b, c
    return out


def _oracle_run(
    state: tuple[FloatArray, FloatArray, FloatArray], inv_var: FloatArray, kappa: float, h: float
) -> FloatArray:
    """``(T, 3, n)``: the oracle ``(a, b, c)`` after each of the ``T`` steps of ``inv_var``."""
    a, b, c = state
    out = np.empty((inv_var.shape[0], 3, inv_var.shape[1]))
    for i, row in enumerate(inv_var / kappa):
        a, b, c = _oracle_step(a, b, c, row, h)
        out[i, 0], out[i, 1], out[i, 2] = a, b, c
    return out


def _prior_state(problem: Any) -> FloatArray:
    sp, sv, _ = (float(v) for v in problem.config.prior_std)
    n = problem.n
    return np.stack([np.full(n, sp * sp), np.zeros(n), np.full(n, sv * sv)])  # (3, n)


def oracle_reference(problem: Any, horizon: int, max_size: int) -> FloatArray:
    """``O`` ``(horizon + 1, n, 2, 2)``: the θ-known oracle of every receiver (step 3).

    ``O_0 = diag(sp^2, sv^2)``; step ``t`` measures ``p_a`` in both channels with noise
    variances ``kappa_{max_size} sigma_{a,c}(t)^2``.
    """
    cfg = problem.config
    kap = measurement_kappa(float(cfg.noise_correlation), max_size)
    first = _prior_state(problem)
    run = _oracle_run(
        (first[0], first[1], first[2]), _inv_var(problem, 1, horizon + 1), kap, float(cfg.dt)
    )
    abc = np.concatenate([first[None], run])  # (K + 1, 3, n)
    return _as_matrices(abc[:, 0], abc[:, 1], abc[:, 2])


def _window_length(tau: int, horizon: int, max_size: int, n: int) -> int:
    W = max(1, min(int(tau), horizon))
    return max(1, min(W, WINDOW_WORK // max(1, (max_size - 1) * (horizon + 1) * n)))


def _windowed(
    abc: FloatArray,
    t_off: int,
    inv_var: FloatArray,
    ks: IntArray,
    W: int,
    kappa: float,
    h: float,
) -> FloatArray:
    """``(len(ks), 3, n)``: ``phi^{kappa}_{l+1..k}(O_l)``, ``l = max(0, k - W)``, for each ``k``.

    ``abc[t - t_off]`` is the oracle at time ``t`` and ``inv_var[t - t_off]`` step ``t``'s
    information (both cover ``min(l) .. max(k)``).
    """
    start = np.maximum(ks - W, 0)
    a, b, c = (abc[start - t_off, i] for i in range(3))
    for j in range(1, W + 1):
        t = start + j
        active = (t <= ks)[:, None]
        if not active.any():
            break
        rows = inv_var[np.minimum(t, ks) - t_off] / kappa
        a1, b1, c1 = _oracle_step(a, b, c, rows, h)
        a, b, c = np.where(active, a1, a), np.where(active, b1, b), np.where(active, c1, c)
    return np.stack([a, b, c], axis=1)


def windowed_references(
    problem: Any, horizon: int, tau: int, max_size: int, ref: FloatArray
) -> FloatArray:
    """``L`` ``(max_size, horizon + 1, n, 2, 2)``: ``L[s - 1]`` bounds size-``s`` clusters.

    Step 4: ``L^{(s)}(k) = phi^{kappa_s}_{l+1..k}(O_l)`` with ``l = max(0, k - W)``, ``W`` the
    window (``tau``, shortened when the work would exceed :data:`WINDOW_WORK`); ``ref`` is ``O``
    (:func:`oracle_reference`) and ``L[max_size - 1] = O``.
    """
    cfg = problem.config
    n, K = problem.n, horizon
    out = np.empty((max_size, K + 1, n, 2, 2))
    out[max_size - 1] = ref
    W = _window_length(tau, K, max_size, n)
    abc = np.stack([ref[..., 0, 0], ref[..., 0, 1], ref[..., 1, 1]], axis=1)
    inv_var = _inv_var(problem, 0, K + 1)
    ks = np.arange(K + 1)
    for s in range(1, max_size):
        kap = measurement_kappa(float(cfg.noise_correlation), s)
        got = _windowed(abc, 0, inv_var, ks, W, kap, float(cfg.dt))
        out[s - 1] = _as_matrices(got[:, 0], got[:, 1], got[:, 2])
    return out


def bias_reference(problem: Any, horizon: int, max_size: int) -> FloatArray:
    """``w`` ``(horizon + 1,)``: a lower bound on every cluster's bias variance (step 5)."""
    cfg = problem.config
    h = float(cfg.dt)
    r = float(cfg.noise_correlation)
    factor = np.array([1.0 - r / (1.0 + (s - 1) * r) for s in range(1, max_size + 1)])
    info = np.empty(horizon + 1)
    step = max(1, CHUNK_ELEMENTS // (2 * problem.n))
    for t0 in range(0, horizon + 1, step):
        t1 = min(horizon + 1, t0 + step)
        g2 = -np.sort(-1.0 / _levels(problem, t0, t1) ** 2, axis=1)  # descending over receivers
        tops = np.cumsum(g2, axis=1)[:, :max_size]  # (T, max_size, 2)
        info[t0:t1] = (factor[None, :, None] * tops).max(axis=1).sum(-1) / (1.0 - r)
    w = np.empty(horizon + 1)
    w[0] = float(cfg.prior_std[2]) ** 2
    for t in range(1, horizon + 1):
        w[t] = 1.0 / (1.0 / (w[t - 1] + h) + info[t])
    return w


@dataclass(frozen=True)
class StepLowerBounds:
    """Lower bounds ``(K,)`` on the cost terms of filter steps ``k = 1 .. K`` (eq. (10)).

    Attributes:
        J, J_G, J_C, J_L: per step; ``J = a_G J_G + a_C J_C + a_L J_L`` of the bounds.
    """

    J: FloatArray
    J_G: FloatArray
    J_C: FloatArray
    J_L: FloatArray


def _smallest_sums(x: FloatArray) -> FloatArray:
    """``(K, n + 1)``: the sum of the ``q`` smallest entries of each row of ``x`` ``(K, n)``."""
    srt = np.sort(x, axis=1)
    return np.concatenate([np.zeros((x.shape[0], 1)), np.cumsum(srt, axis=1)], axis=1)


def _profile_minimum(
    base: FloatArray,
    steps: list[FloatArray],
    theta: FloatArray,
    n: int,
    max_size: int,
    per_cluster: float,
    denominator: Any,
) -> FloatArray:
    """``min_m (base + sum_j smallest_{N_j(m)}(steps[j-1]) + per_cluster m theta) / den(m)``."""
    sums = [_smallest_sums(d) for d in steps]
    m_lo = -(-n // max_size)
    best = np.full(base.shape, np.inf)
    for m in range(m_lo, n + 1):
        num = base + per_cluster * m * theta
        for j, S in enumerate(sums, start=1):
            need = max(0, m - (n - m) // j)
            num = num + S[:, need]
        best = np.minimum(best, num / denominator(m))
    return best


def _cluster_tables(n: int, max_size: int) -> list[list[np.ndarray]]:
    """``tables[s - 1][a]``: ``(C(n - 1, s - 1), s)``, the size-``s`` clusters holding ``a``.

    Receiver ``a`` is in column 0.
    """
    tables = []
    for s in range(1, max_size + 1):
        per = []
        for a in range(n):
            others = [b for b in range(n) if b != a]
            rows = list(itertools.combinations(others, s - 1))
            combos = np.array(rows, dtype=np.int64).reshape(len(rows), s - 1)
            per.append(np.column_stack([np.full(len(combos), a, dtype=np.int64), combos]))
        tables.append(per)
    return tables


def cluster_windows_count(n: int, max_size: int, candidates: int) -> int:
    """Cluster filters :func:`cluster_window_bounds` runs per step (the cost driver)."""
    q = min(int(candidates), n)
    return q * sum(math.comb(n - 1, s - 1) for s in range(1, max_size + 1))


def _cluster_window_range(
    problem: Any,
    max_size: int,
    abc: FloatArray,
    t_off: int,
    w: FloatArray,
    q: int,
    W: int,
    ks: range,
    tables: list[list[np.ndarray]],
) -> tuple[FloatArray, FloatArray]:
    """:func:`cluster_window_bounds` for the steps ``ks``.

    ``abc[t - t_off]`` ``(3, n)`` is the oracle ``(a, b, c)`` at time ``t`` (times
    ``max(0, min(ks) - W) .. max(ks)``).
    """
    from selenv.core.riccati import riccati_step
    from selenv.families.clustering.batched import (
        axis_model,
        axis_prior,
        correlation,
        noise_covariances,
    )

    cfg = problem.config
    dt, r = float(cfg.dt), float(cfg.noise_correlation)
    J_C, J_L = np.zeros(len(ks)), np.zeros(len(ks))
    for i, k in enumerate(ks):
        l0 = max(0, k - W)
        cand = np.argsort(-abc[k - t_off, 0], kind="stable")[:q]
        best_L = np.full(len(cand), np.inf)
        best_C = np.full(len(cand), np.inf)
        start_blocks = None
        if l0 > 0:
            row = abc[l0 - t_off]
            start_blocks = _as_matrices(row[0], row[1], row[2])  # (n, 2, 2)
        for s in range(1, max_size + 1):
            blocks = [tables[s - 1][int(a)] for a in cand]
            members = np.concatenate(blocks)  # (M, s), each block's column 0 is its candidate
            M = members.shape[0]
            if M == 0:
                continue
            d = 2 * s + 1
            if start_blocks is None:
                P = np.broadcast_to(axis_prior(cfg.prior_std, s), (M, d, d)).copy()
            else:
                P = np.zeros((M, d, d))
                for j in range(s):
                    P[:, 2 * j : 2 * j + 2, 2 * j : 2 * j + 2] = start_blocks[members[:, j]]
                P[:, 2 * s, 2 * s] = w[l0]
                P /= s + 1.0
            F, Q, H = axis_model(dt, s)
            rho = correlation(r, s)
            for t in range(l0 + 1, k + 1):
                levels = _levels(problem, t, t + 1)[0]
                P = riccati_step(P, F, Q, H, noise_covariances(levels[members], rho))
            pos = np.diagonal(P, axis1=1, axis2=2)[:, 0 : 2 * s : 2]  # (M, s)
            row = 0
            for j, block in enumerate(blocks):
                rows = slice(row, row + block.shape[0])
                best_L[j] = min(best_L[j], float(pos[rows, 0].min()))
                best_C[j] = min(best_C[j], float(pos[rows].mean(axis=1).min()))
                row += block.shape[0]
        J_L[i], J_C[i] = best_L.max(), best_C.max()
    return J_C, J_L


def cluster_window_bounds(
    problem: Any,
    horizon: int,
    tau: int,
    max_size: int,
    ref: FloatArray,
    w: FloatArray,
    candidates: int,
    window: int | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Step 7 (optional, slow): ``(J_C, J_L)`` lower bounds ``(K,)`` from exact cluster filters.

    By step 4 the cluster ``C`` holding ``a`` at time ``k`` is ``P_C(k) =
    Phi_C^{(l+1..k)}(P_C(l))``, ``l = max(0, k - W)``, ``W <= tau``, with ``P_C(l)`` a matrix the
    filters can hold at ``l``: the prior ``diag(prior_std^2)`` exactly when ``l = 0``, else
    ``P_C(l) >= X_C(l) = blockdiag(O^b_l (b in C), w_l) / (s + 1)`` (``Lambda = P^-1 <= (s + 1)
    blockdiag(Lambda_bb, Lambda_thth)`` for ``s + 1`` blocks, ``Lambda_bb^-1 = Schur_b >= O^b``,
    ``Lambda_thth^-1 = Cov(theta | u) >= w``). The Riccati map is monotone, so
    ``P_C(k) >= B_C(k) = Phi_C^{(l+1..k)}(X_C(l))`` (the env's own filter step). Then
    ``J_L >= min_{C ni a} B_C(k)[p_a]`` and ``J_C >= min_{C ni a} mean_C B_C(k)[p]`` for every
    ``a`` (minimum over every feasible cluster holding ``a``); the maximum is taken over the
    ``candidates`` receivers with the largest oracle position variance at ``k`` (any subset
    is valid). ``ref`` is ``O`` (:func:`oracle_reference`), ``w`` the bias bound
    (:func:`bias_reference`). Captures what the oracle ignores (unknown bias and mates'
    positions). Cost: :func:`cluster_windows_count` cluster filters over ``W`` steps per step
    (~20 s per default episode with 2 candidates).
    """
    K = horizon
    W = max(1, min(int(tau), K) if window is None else min(int(window), int(tau), K))
    q = max(1, min(int(candidates), problem.n))
    abc = np.stack([ref[..., 0, 0], ref[..., 0, 1], ref[..., 1, 1]], axis=1)
    tables = _cluster_tables(problem.n, max_size)
    return _cluster_window_range(problem, max_size, abc, 0, w, q, W, range(1, K + 1), tables)


def _step_terms(
    pos: FloatArray, trace: FloatArray, w: FloatArray, n: int, max_size: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(J_G, J_C, J_L)`` bounds of ``T`` steps (step 6).

    ``pos[s - 1]``, ``trace[s - 1]`` ``(S, T, n)``: the size-``s`` bounds on each receiver's
    position variance and ``p + v`` variance; ``w`` ``(T,)`` the bias bound.
    """
    # L^(s') bounds every cluster of size s <= s' too: take the largest valid one per size
    # (a no-op up to rounding, kappa_s decreasing; it makes the steps below >= 0)
    for s in range(max_size - 2, -1, -1):
        np.maximum(pos[s], pos[s + 1], out=pos[s])
        np.maximum(trace[s], trace[s + 1], out=trace[s])
    top = max_size - 1
    J_L = pos[top].max(axis=1)
    # J_C, the cluster of each receiver: min over its size s of (own + s-1 smallest others) / s
    per_a = pos[0].copy()
    rows = np.arange(pos.shape[1])[:, None]
    for s in range(2, max_size + 1):
        x = pos[s - 1]
        order = np.argsort(x, axis=1, kind="stable")
        srt = x[rows, order]
        rank = np.empty_like(order)
        rank[rows, order] = np.arange(n)[None, :]
        low = srt[:, : s - 1].sum(axis=1)[:, None]
        low_incl = srt[:, :s].sum(axis=1)[:, None] - x
        others = np.where(rank < s - 1, low_incl, low)
        per_a = np.minimum(per_a, (x + others) / s)
    steps_pos = [pos[j - 1] - pos[j] for j in range(1, max_size)]
    steps_tr = [2.0 * (trace[j - 1] - trace[j]) for j in range(1, max_size)]
    mean_pos = _profile_minimum(
        pos[top].sum(axis=1), steps_pos, np.zeros_like(J_L), n, max_size, 0.0, lambda m: float(n)
    )
    J_C = np.maximum(per_a.max(axis=1), mean_pos)
    J_G = _profile_minimum(
        2.0 * trace[top].sum(axis=1),
        steps_tr,
        w,
        n,
        max_size,
        2.0,
        lambda m: float(4 * n + 2 * m),
    )
    return J_G, J_C, J_L


def step_lower_bounds(
    problem: Any,
    horizon: int,
    tau: int,
    max_size: int,
    weights: Any,
    candidates: int = 0,
    window: int | None = None,
) -> StepLowerBounds:
    """Lower bounds on ``J_G``, ``J_C``, ``J_L`` and ``J`` of every filter step (step 6).

    ``candidates > 0`` adds the cluster-window refinement of ``J_C`` and ``J_L``
    (:func:`cluster_window_bounds`, step 7; slow) for that many receivers per step, over
    ``window`` steps (``None``: ``tau``). Runs over time chunks: memory is bounded at any
    horizon.
    """
    cfg = problem.config
    n, K = problem.n, int(horizon)
    h, r = float(cfg.dt), float(cfg.noise_correlation)
    kappas = [measurement_kappa(r, s) for s in range(1, max_size + 1)]
    W = _window_length(tau, K, max_size, n)
    w = bias_reference(problem, K, max_size)
    J_G, J_C, J_L = np.empty(K), np.empty(K), np.empty(K)
    chunk = max(1, CHUNK_ELEMENTS // (n * max_size))
    refine = candidates > 0
    if refine:
        W7 = max(1, min(int(tau), K) if window is None else min(int(window), int(tau), K))
        q = max(1, min(int(candidates), n))
        tables = _cluster_tables(n, max_size)
    keep = max(W, W7) if refine else W  # oracle rows kept before a chunk (window starts)
    abc = _prior_state(problem)[None]  # (T, 3, n): oracle at times t_off .. t_off + T - 1
    t_off = 0
    for k0 in range(1, K + 1, chunk):
        k1 = min(K, k0 + chunk - 1)
        new = _oracle_run(
            (abc[-1, 0], abc[-1, 1], abc[-1, 2]), _inv_var(problem, k0, k1 + 1), kappas[-1], h
        )
        abc = np.concatenate([abc, new])
        ks = np.arange(k0, k1 + 1)
        inv_var = _inv_var(problem, t_off, k1 + 1)
        pos = np.empty((max_size, ks.size, n))
        trace = np.empty((max_size, ks.size, n))
        top = abc[ks - t_off]
        pos[-1], trace[-1] = top[:, 0], top[:, 0] + top[:, 2]
        for s in range(1, max_size):
            got = _windowed(abc, t_off, inv_var, ks, W, kappas[s - 1], h)
            pos[s - 1], trace[s - 1] = got[:, 0], got[:, 0] + got[:, 2]
        g, c, l_ = _step_terms(pos, trace, w[k0 : k1 + 1], n, max_size)
        if refine:
            C7, L7 = _cluster_window_range(
                problem, max_size, abc, t_off, w, q, W7, range(k0, k1 + 1), tables
            )
            c, l_ = np.maximum(c, C7), np.maximum(l_, L7)
        J_G[k0 - 1 : k1], J_C[k0 - 1 : k1], J_L[k0 - 1 : k1] = g, c, l_
        drop = max(0, abc.shape[0] - keep - 1)  # keep times k1 - keep .. k1
        abc, t_off = abc[drop:], t_off + drop
    a_G, a_C, a_L = (float(v) for v in weights)
    shrink = 1.0 - RELATIVE_SLACK
    J_G, J_C, J_L = J_G * shrink, J_C * shrink, J_L * shrink
    return StepLowerBounds(J=a_G * J_G + a_C * J_C + a_L * J_L, J_G=J_G, J_C=J_C, J_L=J_L)


def _assignment_env(env: Any) -> tuple[Any, Any, int]:
    """``(assignment env, invalid rule, invalid actions per filter step)`` of a clustering env."""
    base = getattr(env, "unwrapped", env)
    inner = getattr(base, "inner", None)
    if inner is not None:  # -v2: one placement per env step, n per filter step
        return inner, base.invalid_rule, int(base.n)
    return base, base.invalid_rule, 1


def return_bound(env: Any, *, candidates: int = 0, window: int | None = None) -> ReturnBound | None:
    """A certified upper bound on the return of the episode ``env`` plays from its reset.

    ``env``: a ``ReceiverClustering`` env (``-v0``, ``-v1`` or ``-v2``, wrapped or not) after
    ``reset(seed=s)``. ``None`` with ``invalid_action="terminate"`` (an episode may be cut
    short; see the module docstring). The default (the bench's hook) takes milliseconds;
    ``candidates=q`` adds the exact cluster-window refinement of ``J_C`` and ``J_L`` for ``q``
    receivers per step (:func:`cluster_window_bounds`: tighter, tens of seconds at the
    defaults; ``window`` shortens its window below ``tau``).
    """
    inner, rule, per_step = _assignment_env(env)
    if rule.terminates:
        return None
    problem = inner.problem
    if problem is None:
        raise RuntimeError("call reset() before return_bound(env)")
    cfg = problem.config
    lb = step_lower_bounds(
        problem,
        int(inner.horizon),
        int(cfg.tau),
        int(inner.max_size),
        cfg.weights,
        candidates=candidates,
        window=window,
    )
    value = -float(lb.J.sum())
    if rule.penalty > 0.0:
        value += rule.penalty * per_step * int(inner.horizon)
    method = METHOD if candidates <= 0 else f"{METHOD}, exact cluster windows ({candidates}/step)"
    return ReturnBound(value, "bound", method)
