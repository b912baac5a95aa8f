r"""A certified bound on a ReceiverClustering episode's return: per-receiver oracle filters.

The reward of filter step ``k`` is ``-J_k`` with ``J = a_G J_G + a_C J_C + a_L J_L`` (Greiff et
al. 2022, eq. (10)), evaluated on the posteriors of the cluster Kalman filters (eqs. (11b),
(12c)); :func:`step_lower_bounds` gives a lower bound on every ``J_k`` that holds for *every*
sequence of feasible clusterings, so ``-sum_k LB_k`` bounds every policy's return
(:func:`return_bound`, the ``FamilySpec.return_bound`` hook). Cost: a few 2x2 Riccati
recursions over the receivers, milliseconds at the defaults.

Why not the centralised filter
------------------------------
The natural reference, one Kalman filter on all receivers and all measurements from ``k = 0``,
is **not** a lower bound here. Algorithm 1 (steps 1-2) builds a new cluster's prior at the window
start ``l = k - tau`` by *dropping* the cross-covariances between the old clusters' unique
blocks and between every unique block and the bias (and averaging the bias variance over the
old clusters). Dropping the cross terms of a covariance is not conservative in the Loewner order
(``[[1, c], [c, 1]]`` vs ``I``), so a re-formed cluster can claim more than the data support:
``preset="multipath"``, ``n_agents=3``, ``n_max_states=10``, ``tau=5``, seed 3, the clusterings
``[0,0,1]`` for steps 18-21 then ``[0,1,1]`` at step 22 give receiver 2 a position variance
0.788 below the centralised filter's 0.825 (``J_L`` 0.788 < 0.825). The centralised filter's
window is also looser than the bound below at the defaults (it ignores the cluster size limit).

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

Invalid actions: with ``invalid_action="noop"`` a positive ``invalid_action_penalty`` can be
collected at every placement (``-v2``: ``n`` per filter step) or filter step (``-v1``); it is
added. ``invalid_action="terminate"`` lets a policy end the episode after one step, so the only
certified value is ``max(penalty, .)``, which says nothing about clustering: ``None``.

What the bound does not capture (why it is loose): the oracle knows the bias and the mates'
positions (a cluster does not: about 1.5x on the position variance of the worst receivers), and
each receiver is credited with the best mates independently, although good mates are shared.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from selenv.core.linalg import FloatArray
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

METHOD = "per-receiver oracle filters (bias and mates known), cluster-size windows"


def measurement_kappa(r: float, s: int) -> float:
    """``kappa_s``: variance factor of one receiver's noise given its ``s - 1`` mates' (eq. 4)."""
    if s <= 1:
        return 1.0
    return float(1.0 - r * r * (s - 1) / (1.0 + (s - 2) * r))


def _levels(problem: Any, horizon: int) -> FloatArray:
    """``(horizon + 1, n, 2)`` noise levels of steps ``0 .. horizon``."""
    path = problem.sigma_path
    if path is None:
        return np.broadcast_to(np.asarray(problem.sigma, dtype=float), (horizon + 1, problem.n, 2))
    return np.asarray(path[: horizon + 1], dtype=float)


def _oracle_step(
    a: FloatArray, b: FloatArray, c: FloatArray, info: FloatArray, h: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """One 2x2 step (11b), (12c) of ``[[a, b], [b, c]]``, measuring ``p`` with information ``info``.

    Prediction with ``F = [[1, h], [0, 1]]``, ``Q = [[h^3/3, h^2/2], [h^2/2, h]]``, then the
    scalar update ``P - P e e' P / (e' P e + 1 / info)`` written entrywise (elementwise arrays).
    """
    m00 = a + h * (2.0 * b + h * c) + h**3 / 3.0
    m01 = b + h * c + h * h / 2.0
    m11 = c + h
    d = 1.0 + info * m00
    return m00 / d, m01 / d, m11 - info * m01 * m01 / d


def _as_matrices(a: FloatArray, b: FloatArray, c: FloatArray) -> FloatArray:
    out = np.empty((*a.shape, 2, 2))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = a, b, b, c
    return out


def oracle_reference(problem: Any, horizon: int, max_size: int) -> FloatArray:
    """``O`` ``(horizon + 1, n, 2, 2)``: the θ-known oracle of every receiver (step 3).

    ``O_0 = diag(sp^2, sv^2)``; step ``t`` measures ``p_a`` in both channels with noise
    variances ``kappa_{max_size} sigma_{a,c}(t)^2``.
    """
    cfg = problem.config
    h = float(cfg.dt)
    kap = measurement_kappa(float(cfg.noise_correlation), max_size)
    sp, sv, _ = (float(v) for v in cfg.prior_std)
    info = (1.0 / _levels(problem, horizon) ** 2).sum(-1) / kap  # (K + 1, n)
    n = problem.n
    A, B, C = (np.empty((horizon + 1, n)) for _ in range(3))
    a, b, c = np.full(n, sp * sp), np.zeros(n), np.full(n, sv * sv)
    A[0], B[0], C[0] = a, b, c
    for t in range(1, horizon + 1):
        a, b, c = _oracle_step(a, b, c, info[t], h)
        A[t], B[t], C[t] = a, b, c
    return _as_matrices(A, B, C)


def windowed_references(
    problem: Any, horizon: int, tau: int, max_size: int, O: FloatArray
) -> FloatArray:
    """``L`` ``(max_size, horizon + 1, n, 2, 2)``: ``L[s - 1]`` bounds a member of a size-``s`` cluster.

    Step 4: ``L^{(s)}(k) = phi^{kappa_s}_{l+1..k}(O_l)`` with ``l = max(0, k - W)``, ``W`` the
    window (``tau``, shortened when the work would exceed :data:`WINDOW_WORK`);
    ``L[max_size - 1] = O``.
    """
    cfg = problem.config
    n, K = problem.n, horizon
    h = float(cfg.dt)
    r = float(cfg.noise_correlation)
    inv_var = (1.0 / _levels(problem, horizon) ** 2).sum(-1)  # (K + 1, n)
    out = np.empty((max_size, K + 1, n, 2, 2))
    out[max_size - 1] = O
    if max_size == 1:
        return out
    W = max(1, min(int(tau), K))
    W = max(1, min(W, WINDOW_WORK // max(1, (max_size - 1) * (K + 1) * n)))
    k = np.arange(K + 1)
    start = np.maximum(k - W, 0)
    for s in range(1, max_size):
        info = inv_var / measurement_kappa(r, s)
        a, b, c = O[start, :, 0, 0], O[start, :, 0, 1], O[start, :, 1, 1]  # (K + 1, n)
        for j in range(1, W + 1):
            t = start + j
            active = (t <= k)[:, None]
            a1, b1, c1 = _oracle_step(a, b, c, info[np.minimum(t, K)], h)
            a, b, c = np.where(active, a1, a), np.where(active, b1, b), np.where(active, c1, c)
        out[s - 1] = _as_matrices(a, b, c)
    return out


def bias_reference(problem: Any, horizon: int, max_size: int) -> FloatArray:
    """``w`` ``(horizon + 1,)``: a lower bound on every cluster's bias variance (step 5)."""
    cfg = problem.config
    h = float(cfg.dt)
    r = float(cfg.noise_correlation)
    levels = _levels(problem, horizon)
    g2 = np.sort(1.0 / levels**2, axis=1)[:, ::-1]  # (K + 1, n, 2), descending
    tops = np.cumsum(g2, axis=1)[:, :max_size]  # (K + 1, max_size, 2)
    factor = np.array([1.0 - r / (1.0 + (s - 1) * r) for s in range(1, max_size + 1)])
    info = ((factor[None, :, None] * tops).max(axis=1)).sum(-1) / (1.0 - r)  # (K + 1,)
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
    base: FloatArray, steps: list[FloatArray], theta: FloatArray, n: int, max_size: int,
    per_cluster: float, denominator: Any,
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
    """``tables[s - 1][a]``: ``(C(n - 1, s - 1), s)`` the clusters of size ``s`` holding ``a``
    (``a`` first)."""
    tables = []
    for s in range(1, max_size + 1):
        per = []
        for a in range(n):
            others = [b for b in range(n) if b != a]
            combos = np.array(list(itertools.combinations(others, s - 1)), dtype=np.int64)
            per.append(np.column_stack([np.full(len(combos), a, dtype=np.int64), combos]))
        tables.append(per)
    return tables


def cluster_windows_count(n: int, max_size: int, candidates: int) -> int:
    """Cluster filters :func:`cluster_window_bounds` runs per step (the cost driver)."""
    q = min(int(candidates), n)
    return q * sum(math.comb(n - 1, s - 1) for s in range(1, max_size + 1))


def cluster_window_bounds(
    problem: Any,
    horizon: int,
    tau: int,
    max_size: int,
    O: FloatArray,
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
    is valid). Captures what the oracle ignores (unknown bias and mates' positions): about
    1.4x on the worst receivers. Cost: :func:`cluster_windows_count` cluster filters over ``W``
    steps per step (~25 s per default episode with 2 candidates).
    """
    from selenv.core.riccati import riccati_step
    from selenv.families.clustering.batched import (
        axis_model,
        axis_prior,
        correlation,
        noise_covariances,
    )

    cfg = problem.config
    n, K = problem.n, horizon
    W = max(1, min(int(tau), K) if window is None else min(int(window), int(tau), K))
    q = max(1, min(int(candidates), n))
    levels = _levels(problem, horizon)
    tables = _cluster_tables(n, max_size)
    dt, r = float(cfg.dt), float(cfg.noise_correlation)
    J_C, J_L = np.zeros(K), np.zeros(K)
    for k in range(1, K + 1):
        l = max(0, k - W)
        cand = np.argsort(-O[k, :, 0, 0], kind="stable")[:q]
        best_L = np.full(q, np.inf)
        best_C = np.full(q, np.inf)
        for s in range(1, max_size + 1):
            blocks = [tables[s - 1][int(a)] for a in cand]
            members = np.concatenate(blocks)  # (M, s), each block's column 0 is its candidate
            M = members.shape[0]
            if M == 0:
                continue
            if l == 0:
                P = np.broadcast_to(axis_prior(cfg.prior_std, s), (M, 2 * s + 1, 2 * s + 1)).copy()
            else:
                P = np.zeros((M, 2 * s + 1, 2 * s + 1))
                for j in range(s):
                    P[:, 2 * j : 2 * j + 2, 2 * j : 2 * j + 2] = O[l, members[:, j]]
                P[:, 2 * s, 2 * s] = w[l]
                P /= s + 1.0
            F, Q, H = axis_model(dt, s)
            rho = correlation(r, s)
            for t in range(l + 1, k + 1):
                P = riccati_step(P, F, Q, H, noise_covariances(levels[t][members], rho))
            pos = np.diagonal(P, axis1=1, axis2=2)[:, 0 : 2 * s : 2]  # (M, s)
            start = 0
            for i, block in enumerate(blocks):
                rows = slice(start, start + block.shape[0])
                best_L[i] = min(best_L[i], float(pos[rows, 0].min()))
                best_C[i] = min(best_C[i], float(pos[rows].mean(axis=1).min()))
                start += block.shape[0]
        J_L[k - 1], J_C[k - 1] = best_L.max(), best_C.max()
    return J_C, J_L


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
    (:func:`cluster_window_bounds`, step 7; slow) for that many receivers per step.
    """
    n = problem.n
    O = oracle_reference(problem, horizon, max_size)
    L = windowed_references(problem, horizon, tau, max_size, O)
    w_all = bias_reference(problem, horizon, max_size)
    w = w_all[1:]
    pos = L[:, 1:, :, 0, 0]  # (S, K, n)
    trace = L[:, 1:, :, 0, 0] + L[:, 1:, :, 1, 1]
    # L^(s') bounds every cluster of size s <= s' too: take the largest valid one per size
    # (a no-op up to rounding, kappa_s decreasing; it makes the steps below >= 0)
    pos = np.maximum.accumulate(pos[::-1], axis=0)[::-1]
    trace = np.maximum.accumulate(trace[::-1], axis=0)[::-1]
    top = max_size - 1
    J_L = pos[top].max(axis=1)
    # J_C, the cluster of each receiver: min over its size s of (own + s-1 smallest others) / s
    per_a = np.full(pos.shape[1:], np.inf)
    rows = np.arange(pos.shape[1])[:, None]
    for s in range(1, max_size + 1):
        x = pos[s - 1]
        if s == 1:
            per_a = np.minimum(per_a, x)
            continue
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
    zero = np.zeros_like(J_L)
    mean_pos = _profile_minimum(
        pos[top].sum(axis=1), steps_pos, zero, n, max_size, 0.0, lambda m: float(n)
    )
    J_C = np.maximum(per_a.max(axis=1), mean_pos)
    if candidates > 0:
        C_ref, L_ref = cluster_window_bounds(
            problem, horizon, tau, max_size, O, w_all, candidates, window
        )
        J_C, J_L = np.maximum(J_C, C_ref), np.maximum(J_L, L_ref)
    J_G = _profile_minimum(
        2.0 * trace[top].sum(axis=1), steps_tr, w, n, max_size, 2.0,
        lambda m: float(4 * n + 2 * m),
    )
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
        problem, int(inner.horizon), int(cfg.tau), int(inner.max_size), cfg.weights,
        candidates=candidates, window=window,
    )
    value = -float(lb.J.sum())
    if rule.penalty > 0.0:
        value += rule.penalty * per_step * int(inner.horizon)
    method = METHOD if candidates <= 0 else f"{METHOD}, exact cluster windows ({candidates}/step)"
    return ReturnBound(value, "bound", method)
