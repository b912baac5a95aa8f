"""Exact FIM selection: branch and bound on the continuous relaxation, with certified bounds.

Maximise the D-optimal objective of Kirchner et al. (2020), eq. (8)/(9),

    f(S) = log det(Q0 + sum_{k in S} G_k^T G_k) - log det Q0,

over the subsets with ``|S cap P_a| <= K_a`` for disjoint pools ``P_a`` (one pool holding every
candidate with budget ``K``: the single-agent problem; several: the centralised problem of the
multi-agent module, a partition matroid). ``f`` is monotone, so an optimum uses every budget.

**Relaxation (the bound).** With ``w in [0, 1]^N``, ``sum_{k in P_a} w_k = K_a`` and
``F(w) = log det(Q0 + sum_k w_k G_k^T G_k)``, the relaxed problem is concave (log det is concave
and ``A(w)`` affine in ``w``; Joshi & Boyd 2009, "Sensor selection via convex optimization").
Its value bounds every subset's, and any ``w`` gives a *certified* bound on it without solving
it exactly: ``F`` lies below its tangent at ``w``, whose maximum over the polytope is a sum of
the ``K_a`` largest gradient entries per pool (the Frank-Wolfe duality gap):

    max_S f(S) <= F(w) + sum_a top_{K_a}(g_{P_a}) - g^T w - log det Q0,
    g_k = dF/dw_k = tr(A(w)^-1 G_k^T G_k) = ||G_k L^-T||_F^2,  A(w) = L L^T.

:func:`relaxation_bound_whitened` drives ``w`` towards the relaxed optimum by a log-barrier
Newton method (Newton steps on ``t F(w) + sum log w_k + log(1 - w_k)`` under the pool
equalities, ``t`` raised tenfold per centring; Boyd & Vandenberghe 2004, Sec. 11.3), and
returns the tangent bound above, valid whatever the accuracy reached.

**Branch and bound** (:func:`branch_and_bound_whitened`): a node fixes some candidates in and
some out; its bound is the relaxation over the free ones. Nodes are explored best bound first;
a node is pruned once its certified bound is at most the incumbent (plus ``rtol`` relative),
and branched on its most fractional candidate (in / out) once its relaxed value exceeds the
incumbent. The incumbent starts from ``greedy`` + ``swap`` (or ``initial``) and improves by
rounding each node's relaxed point (the ``K_a`` largest ``w`` per pool). When every node is
closed the incumbent is optimal to ``rtol``; at the node limit (or time limit) the incumbent
is returned with the largest open bound, so ``gap = (bound - objective) / |bound|`` is
certified either way. The node limit is deterministic; a ``time_limit`` makes the result depend
on the machine's speed.
"""

from __future__ import annotations

import heapq
import itertools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from selenv.agents.fim_solvers import (
    Selection,
    _check_budget,
    _check_partition,
    int_indices,
    partition_swap_whitened,
    swap_whitened,
)
from selenv.core.information import logdet_objective, whitened_pool
from selenv.core.linalg import FloatArray, logdet_spd
from selenv.families.clustering.labels import check_int
from selenv.threads import small_blas

__all__ = [
    "DEFAULT_NODE_LIMIT",
    "ExactSelection",
    "RelaxationBound",
    "branch_and_bound_whitened",
    "relaxation_bound_whitened",
]

#: default node limit of :func:`branch_and_bound_whitened` (deterministic; 35-40 s at
#: the FIMSelection-v1 defaults when it is reached)
DEFAULT_NODE_LIMIT = 5_000
_T0 = 1.0  #: barrier weight of the first centring
_T_STEP = 50.0  #: factor between centrings
_T_MAX = 1e13  #: last centring (the barrier's own gap is then ~2 N / 1e13)
_NEWTON_TOL = 1e-3  #: half the squared Newton decrement at which a centring ends
_MAX_NEWTON = 60  #: Newton steps per centring (a safeguard; a few are usual)
#: the three below were chosen on seeds 20000-20002 of FIMSelection-v1 (15 s per instance):
#: mean certified gap 0.101 % -> 0.057 % against (1e4, 1e-3, 0.05)
_T_WARM = 3e4  #: barrier weight of the first centring from a parent's weights
_WARM_CLIP = 3e-4  #: a parent's weights are moved at least this far inside the box
_BRANCH_TIGHT = 0.4  #: how tight a branched node's bound is made (children inherit it)
_ENUMERATE = 4_000  #: a node with at most this many completions is solved by enumeration
_FIX_ROUNDS = 4  #: relaxations per node while reduced-cost fixing still fixes candidates


@dataclass(frozen=True)
class RelaxationBound:
    """A certified upper bound on ``max f(S)`` from the continuous relaxation.

    Attributes:
        bound: ``F(w) + sum_a top_{K_a}(g) - g^T w - log det Q0`` (nats): no feasible subset
            has a larger ``f``.
        relaxed: ``F(w) - log det Q0`` at the final ``w`` (a lower bound on the relaxed
            optimum, which lies in ``[relaxed, bound]``).
        weights: the final ``w`` ``(N,)`` (0 outside the pools).
        newton_steps: Newton steps taken.
    """

    bound: float
    relaxed: float
    weights: np.ndarray
    newton_steps: int


@dataclass(frozen=True)
class ExactSelection(Selection):
    """:class:`~selenv.agents.fim_solvers.Selection` with its certificate.

    Attributes:
        upper_bound: no feasible subset has ``f`` above this (nats); equal to ``objective`` up
            to ``rtol`` when ``optimal``.
        optimal: every node was closed: ``objective`` is the optimum to ``rtol``.
        nodes: branch-and-bound nodes solved.
        seconds: wall time of the solve (informative only).
    """

    upper_bound: float = math.inf
    optimal: bool = False
    nodes: int = 0
    seconds: float = 0.0

    @property
    def gap(self) -> float:
        """Certified relative gap ``(upper_bound - objective) / |upper_bound|`` (>= 0)."""
        return max(0.0, self.upper_bound - self.objective) / max(abs(self.upper_bound), 1e-300)


@dataclass(frozen=True)
class _Relaxed:
    """A node's relaxation: its certified bound and the tangent point that gave it."""

    bound: float  #: the certified bound (nats)
    relaxed: float  #: F(w) - log det Q0 at the last point
    weights: np.ndarray  #: (N,) the last point (1 for fixed in, 0 for fixed out)
    free: np.ndarray  #: (n,) the free candidates
    members: list[np.ndarray]  #: positions in ``free`` of each pool with free candidates
    left: np.ndarray  #: budget left in each of those pools
    at: np.ndarray  #: (N,) the tangent point of ``bound``
    F: float  #: F at the tangent point
    g: np.ndarray  #: (n,) the gradient there


def _feasible_start(w: np.ndarray, members: list[np.ndarray], left: np.ndarray) -> np.ndarray:
    """``w`` (inside the box) moved onto each pool's sum, staying strictly inside the box.

    A pool above its sum is scaled down; one below has its complement ``1 - w`` scaled down.
    """
    w = w.copy()
    for k, r in zip(members, left, strict=True):
        s, n = float(w[k].sum()), k.size
        if s > r:
            w[k] *= r / s
        elif s < r:
            w[k] = 1.0 - (1.0 - w[k]) * (n - r) / (n - s)
    return w


def _newton_step(
    Zk: np.ndarray,
    triu: tuple[np.ndarray, np.ndarray],
    t: float,
    D: np.ndarray,
    grad: np.ndarray,
    E: np.ndarray,
) -> np.ndarray | None:
    """The barrier's Newton step ``(n,)`` under ``E step = 0``; ``None`` if it cannot be solved.

    The barrier's negated Hessian is ``P = diag(D) + t H`` with ``H_kl = tr(A^-1 Q_k A^-1
    Q_l) = <M_k, M_l>`` for ``M_k = Z_k^T Z_k`` (``Z_k = G_k L^-T``, ``(m, d)``): ``H = V V^T``
    with ``V_k`` the ``d (d + 1) / 2`` entries of ``M_k``'s upper triangle (off-diagonals times
    sqrt 2). So ``P^-1`` is applied by the Woodbury identity in ``O(n d^4)`` instead of an
    ``n x n`` factorisation. The step solves ``P s = grad - E^T nu`` with ``E s = 0``.
    """
    M = np.einsum("kai,kaj->kij", Zk, Zk)[:, triu[0], triu[1]]  # (n, d (d + 1) / 2)
    M[:, triu[0] != triu[1]] *= math.sqrt(2.0)
    Dinv = 1.0 / D
    DV = Dinv[:, None] * M
    C = np.eye(M.shape[1]) / t + M.T @ DV
    try:
        c = cho_factor(C, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    X = np.column_stack([grad, E.T])  # (n, 1 + p)
    DX = Dinv[:, None] * X
    PX = DX - DV @ cho_solve(c, M.T @ DX, check_finite=False)  # P^-1 [grad, E^T]
    Pg, PE = PX[:, 0], PX[:, 1:]
    try:
        nu = np.linalg.solve(E @ PE, E @ Pg)
    except np.linalg.LinAlgError:
        return None
    step: np.ndarray = Pg - PE @ nu
    return step


def _branch_candidate(free: np.ndarray, w: np.ndarray) -> int:
    """The free candidate to branch on: the most fractional weight (first on ties).

    Measured against branching on the largest or the smallest fractional weight at the
    FIMSelection-v1 defaults: the most fractional closes the gap fastest.
    """
    return int(free[np.argmax(np.minimum(w, 1.0 - w))])


class _Problem:
    """A validated pool with its pools' owners and budgets (trusted arrays)."""

    def __init__(self, Q0: FloatArray, G: FloatArray, owner: np.ndarray, budgets: np.ndarray):
        self.Q0, self.G, self.owner, self.budgets = Q0, G, owner, budgets
        self.N, self.m, self.d = G.shape
        self.logdet0 = float(logdet_spd(Q0, "Q0"))  # the existing helper: 2 sum log diag L
        self.evaluations = 0
        self.newton_steps = 0

    def value(self, idx: Sequence[int] | np.ndarray) -> float:
        """``f(S)`` of the subset ``idx`` (eq. 9)."""
        self.evaluations += 1
        return logdet_objective(self.Q0, self.G, [int(k) for k in idx])

    def pools(self, status: np.ndarray) -> list[tuple[np.ndarray, int]]:
        """Each pool's free candidates and budget left, for the pools with free candidates."""
        out = []
        for a, K in enumerate(self.budgets):
            free = np.flatnonzero((self.owner == a) & (status == -1))
            if free.size:
                out.append((free, int(K) - int(np.sum(status[self.owner == a] == 1))))
        return out

    def greedy_bound(self, status: np.ndarray, floor: float) -> tuple[float, float]:
        """``(f(IN), f(IN) + sum_a top_{r_a} rho_k(IN))``: the submodular bound of a node.

        ``rho_k(IN) = log det(I + Z_k Z_k^T)``, ``Z_k = G_k L^-T`` with ``L L^T = A_IN``, is
        the gain of ``k`` on the fixed-in set; by submodularity a completion's gain is at most
        the sum of its members' gains (Nemhauser, Wolsey & Fisher 1978), which is exact for
        one pick left. Candidates whose own gain plus the other best gains cannot exceed
        ``floor`` are fixed out in ``status`` (in place).
        """
        m, d = self.m, self.d
        Gin = self.G[status == 1].reshape(-1, d)
        L = np.linalg.cholesky(self.Q0 + Gin.T @ Gin)
        f_in = 2.0 * float(np.sum(np.log(np.diag(L)))) - self.logdet0
        bound = f_in
        for free, r in self.pools(status):
            Z = solve_triangular(L, self.G[free].reshape(-1, d).T, lower=True).T
            S = np.einsum("kai,kbi->kab", Z.reshape(free.size, m, d), Z.reshape(free.size, m, d))
            rho = np.linalg.slogdet(np.eye(m) + S)[1]
            order = np.argsort(-rho, kind="stable")
            top = float(np.sum(rho[order[:r]]))
            bound += top
            if free.size > r:  # outside the top r: forcing it in drops the r-th best
                rest = order[r:]
                status[free[rest[f_in + top - rho[order[r - 1]] + rho[rest] <= floor]]] = 0
        self.evaluations += 1
        return f_in, bound

    def enumerate_node(self, status: np.ndarray) -> tuple[float, np.ndarray] | None:
        """The best completion of a node by enumeration, or ``None`` when there are too many.

        Every completion (``prod_a C(n_a, r_a) <= _ENUMERATE``) by one batched Cholesky.
        """
        pools = self.pools(status)
        fixed = np.flatnonzero(status == 1)
        if not pools:  # every candidate decided: a leaf
            return self.value(fixed), fixed
        if math.prod(math.comb(f.size, r) for f, r in pools) > _ENUMERATE:
            return None
        d = self.d
        Gin = self.G[fixed].reshape(-1, d)
        B = self.Q0 + Gin.T @ Gin
        parts = [np.array(list(itertools.combinations(f, r)), dtype=np.intp) for f, r in pools]
        combos = parts[0]
        for part in parts[1:]:
            combos = np.concatenate(
                [np.repeat(combos, len(part), axis=0), np.tile(part, (len(combos), 1))], axis=1
            )
        Gc = self.G[combos].reshape(len(combos), -1, d)
        L = np.linalg.cholesky(B + np.einsum("cri,crj->cij", Gc, Gc))
        vals = 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1) - self.logdet0
        self.evaluations += len(combos)
        i = int(np.argmax(vals))
        return float(vals[i]), np.sort(np.concatenate([fixed, combos[i]]))

    def propagate(self, status: np.ndarray) -> np.ndarray | None:
        """Fix the free candidates a pool's budget decides (all in or out); ``None``: infeasible.

        ``status`` ``(N,)`` int8: 1 in, 0 out, -1 free.
        """
        status = status.copy()
        for a, K in enumerate(self.budgets):
            pool = self.owner == a
            left = int(K) - int(np.sum(status[pool] == 1))
            free = pool & (status == -1)
            n_free = int(free.sum())
            if left < 0 or left > n_free:
                return None
            if left == 0:
                status[free] = 0
            elif left == n_free:
                status[free] = 1
        return status

    def relax(
        self,
        status: np.ndarray,
        stop_below: float = -math.inf,
        stop_above: float = math.inf,
        start: np.ndarray | None = None,
    ) -> _Relaxed:
        """The certified relaxation bound at a node (``status`` propagated, some free).

        Centrings stop early once the bound is ``<= stop_below`` (the node can be pruned) or
        the relaxed value is ``> stop_above`` (it must be branched) with the bound within
        ``_BRANCH_TIGHT`` of the relaxed value, relative to its distance to ``stop_above``.
        ``start`` ``(N,)``: a parent's weights to start from (moved inside the box and onto
        the pool sums).
        """
        G, m, d = self.G, self.m, self.d
        free = np.flatnonzero(status == -1)
        n = free.size
        groups = self.owner[free]
        present = np.unique(groups)
        E = (groups[None, :] == present[:, None]).astype(float)  # (p, n) pool rows
        members = [np.flatnonzero(E[i] > 0) for i in range(len(present))]
        left = np.array(
            [self.budgets[a] - np.sum(status[self.owner == a] == 1) for a in present], float
        )
        Gin = G[status == 1].reshape(-1, d)
        B = self.Q0 + Gin.T @ Gin
        Gf = G[free].reshape(n * m, d)
        if start is None:
            w = (left / E.sum(axis=1)) @ E  # uniform within each pool: strictly inside the box
            t = _T0
        else:
            w = _feasible_start(np.clip(start[free], _WARM_CLIP, 1.0 - _WARM_CLIP), members, left)
            t = _T_WARM

        def logdet(w: np.ndarray) -> tuple[float, np.ndarray] | None:
            A = B + Gf.T @ (np.repeat(w, m)[:, None] * Gf)
            try:
                L = np.linalg.cholesky(A)
            except np.linalg.LinAlgError:
                return None
            return 2.0 * float(np.sum(np.log(np.diag(L)))), L

        def barrier(w: np.ndarray, t: float) -> float:
            got = logdet(w)
            if got is None or np.any(w <= 0.0) or np.any(w >= 1.0):
                return -math.inf
            return t * got[0] + float(np.sum(np.log(w)) + np.sum(np.log1p(-w)))

        triu = np.triu_indices(d)
        best: tuple[float, np.ndarray, float, np.ndarray] | None = None  # (bound, w, F, g)
        while True:
            for _ in range(_MAX_NEWTON):
                got = logdet(w)
                assert got is not None  # w stays strictly feasible and A >= B > 0
                F, L = got
                Z = solve_triangular(L, Gf.T, lower=True, check_finite=False).T  # (n m, d)
                Zk = Z.reshape(n, m, d)
                g = np.sum((Z * Z).reshape(n, m * d), axis=1)  # tr(A^-1 Q_k)
                top = sum(float(np.sum(np.sort(g[k])[::-1][: int(r)])) for k, r in
                          zip(members, left, strict=True))  # fmt: skip
                bound = F + top - float(g @ w) - self.logdet0  # the tangent bound at w
                if best is None or bound < best[0]:
                    best = (bound, w.copy(), F, g)
                grad = t * g + 1.0 / w - 1.0 / (1.0 - w)
                D = 1.0 / w**2 + 1.0 / (1.0 - w) ** 2  # the barrier's curvature
                step = _newton_step(Zk, triu, t, D, grad, E)  # within the pool equalities
                if step is None:
                    break
                dec = float(grad @ step)
                self.newton_steps += 1
                if dec / 2.0 <= _NEWTON_TOL:
                    break
                with np.errstate(divide="ignore"):
                    room = np.where(step < 0, -w / step, np.where(step > 0, (1 - w) / step, np.inf))
                alpha = min(1.0, 0.99 * float(room.min()))
                base = barrier(w, t)
                while alpha > 1e-12 and barrier(w + alpha * step, t) < base + 0.25 * alpha * dec:
                    alpha *= 0.5
                if alpha <= 1e-12:
                    break
                w = w + alpha * step
            relaxed = F - self.logdet0
            assert best is not None
            tight = best[0] - relaxed <= _BRANCH_TIGHT * (best[0] - stop_above)
            if best[0] <= stop_below or (relaxed > stop_above and tight) or t >= _T_MAX:
                break
            t *= _T_STEP
        weights = np.zeros(self.N)
        weights[status == 1] = 1.0
        weights[free] = w
        at = np.zeros(self.N)
        at[free] = best[1]
        return _Relaxed(best[0], relaxed, weights, free, members, left, at, best[2], best[3])

    def fix_by_bounds(self, status: np.ndarray, res: _Relaxed, floor: float) -> int:
        """Fix, in place, the free candidates whose other branch the tangent bound prunes.

        At the tangent point, a subset of the node's subtree that holds free ``k`` is bounded
        by ``F + sum(top r with k forced in) - g^T w``; when that is ``<= floor`` (the
        incumbent plus the slack) no better subset holds ``k``, so ``k`` is fixed out (and
        symmetrically fixed in). Returns the number fixed (reduced-cost fixing).
        """
        w, g = res.at[res.free], res.g
        base = res.F - float(g @ w) - self.logdet0
        fixed = 0
        for k, r in zip(res.members, res.left, strict=True):
            r = int(r)
            order = k[np.argsort(-g[k], kind="stable")]
            top = float(np.sum(g[order[:r]]))
            in_top = order[:r]
            rest = order[r:]
            if rest.size:  # forcing a candidate outside the top r in drops the r-th
                out = rest[base + top - g[order[r - 1]] + g[rest] <= floor]
                status[res.free[out]] = 0
                fixed += out.size
                # forcing a top candidate out brings in the (r+1)-th
                into = in_top[base + top - g[in_top] + g[order[r]] <= floor]
                status[res.free[into]] = 1
                fixed += into.size
        return fixed

    def rounded(self, status: np.ndarray, w: np.ndarray) -> np.ndarray:
        """The fixed-in candidates plus each pool's largest weights up to its budget."""
        picks = [np.flatnonzero(status == 1)]
        for a, K in enumerate(self.budgets):
            free = np.flatnonzero((self.owner == a) & (status == -1))
            left = int(K) - int(np.sum(status[self.owner == a] == 1))
            if left > 0:
                order = free[np.argsort(-w[free], kind="stable")]
                picks.append(order[:left])
        return np.sort(np.concatenate(picks)).astype(np.intp)


class _Search:
    """The incumbent of a branch and bound and the node step that improves or closes it."""

    def __init__(self, prob: _Problem, best: np.ndarray, incumbent: float, rtol: float):
        self.prob, self.rtol = prob, rtol
        self.best, self.incumbent = best, incumbent

    @property
    def floor(self) -> float:
        """A node whose bound is at most this cannot hold a better subset (to ``rtol``)."""
        return self.incumbent + self.rtol * max(1.0, abs(self.incumbent))

    def offer(self, subset: np.ndarray, value: float) -> None:
        """Keep ``subset`` if it beats the incumbent."""
        if value > self.incumbent:
            self.best, self.incumbent = np.sort(subset).astype(np.intp), value

    def solve_node(
        self, status: np.ndarray, start: np.ndarray | None
    ) -> tuple[np.ndarray, _Relaxed] | None:
        """Bound, fix and round one node; ``None`` when it is closed, else what to branch on.

        In order: the submodular bound (with its fixings), enumeration when the completions
        are few, then up to ``_FIX_ROUNDS`` relaxations, each followed by rounding and
        reduced-cost fixing.
        """
        prob = self.prob
        if not np.any(status == -1):
            self.offer(np.flatnonzero(status == 1), prob.value(np.flatnonzero(status == 1)))
            return None
        _, sub = prob.greedy_bound(status, self.floor)
        fixed = prob.propagate(status)
        if fixed is None or sub <= self.floor:
            return None  # infeasible, or pruned by the submodular bound
        status = fixed
        exact = prob.enumerate_node(status)
        if exact is not None:
            self.offer(exact[1], exact[0])
            return None
        res = None
        for _ in range(_FIX_ROUNDS):
            res = prob.relax(status, self.floor, self.floor, start)
            guess = prob.rounded(status, res.weights)
            self.offer(guess, prob.value(guess))
            if res.bound <= self.floor:
                return None
            if prob.fix_by_bounds(status, res, self.floor) == 0:
                break
            fixed = prob.propagate(status)
            if fixed is None:
                return None
            status, start = fixed, res.weights
            if not np.any(status == -1):
                return self.solve_node(status, None)
        assert res is not None
        return status, res


def _logdet_only(objective: object, interest: object) -> None:
    """Refuse the objectives the relaxation does not bound (one line, naming the way out)."""
    if objective != "logdet" or interest is not None:
        raise ValueError(
            f"the exact solver bounds objective='logdet' only (got objective={objective!r}"
            f"{'' if interest is None else ', interest=' + repr(interest)}); use brute_force "
            "for 'trace' or 'max_eig' on small pools"
        )


def _problem(
    Q0: object,
    G: object,
    budget: object,
    groups: Sequence[Sequence[int]] | None,
    budgets: Sequence[int] | None,
) -> _Problem:
    Q0_a, G_a = whitened_pool(Q0, G)
    N = G_a.shape[0]
    if (groups is None) != (budgets is None):
        raise ValueError("groups and budgets must be given together (or neither)")
    if groups is None:
        K = _check_budget(budget, N)
        owner, B = np.zeros(N, dtype=np.intp), np.array([K], dtype=np.intp)
    else:
        if budget is not None:
            raise ValueError("give either budget or groups + budgets, not both")
        owner, B = _check_partition(N, groups, budgets)  # type: ignore[arg-type]
    return _Problem(Q0_a, G_a, owner, B)


@small_blas
def relaxation_bound_whitened(
    Q0: FloatArray,
    G: FloatArray,
    budget: int | None = None,
    *,
    groups: Sequence[Sequence[int]] | None = None,
    budgets: Sequence[int] | None = None,
) -> RelaxationBound:
    """Certified upper bound on ``max f(S)`` (log det, eq. 9) from the continuous relaxation.

    ``budget`` for one pool of every candidate, or ``groups`` / ``budgets`` for disjoint pools
    (as :func:`~selenv.agents.fim_solvers.partition_greedy_whitened`). The bound is the tangent
    bound at the barrier method's points (module docstring): valid at any accuracy, within
    1e-6 nats of the relaxed optimum (tested against SLSQP). Cost: ``O(N m d^2 + N d^4)`` per
    Newton step (the Woodbury step of :func:`_newton_step`).

    Raises:
        TypeError, ValueError: as :func:`~selenv.agents.fim_solvers.partition_greedy_whitened`.
    """
    prob = _problem(Q0, G, budget, groups, budgets)
    status = prob.propagate(np.where(prob.owner >= 0, -1, 0).astype(np.int8))
    assert status is not None  # budgets within their pools, checked above
    if not np.any(status == -1):
        value = prob.value(np.flatnonzero(status == 1))
        return RelaxationBound(value, value, (status == 1).astype(float), 0)
    res = prob.relax(status)
    return RelaxationBound(res.bound, res.relaxed, res.weights, prob.newton_steps)


@small_blas
def branch_and_bound_whitened(
    Q0: FloatArray,
    G: FloatArray,
    budget: int | None = None,
    *,
    groups: Sequence[Sequence[int]] | None = None,
    budgets: Sequence[int] | None = None,
    initial: Sequence[int] | None = None,
    node_limit: int = DEFAULT_NODE_LIMIT,
    time_limit: float | None = None,
    rtol: float = 1e-9,
    objective: str = "logdet",
    interest: Sequence[int] | np.ndarray | None = None,
) -> ExactSelection:
    """The log-det optimum by branch and bound, or the incumbent with a certified gap.

    See the module docstring. ``initial``: a feasible subset to start from (default: ``swap``
    on greedy, within each pool for ``groups``). ``node_limit``: nodes solved before returning
    the incumbent (deterministic); ``time_limit``: seconds, checked between nodes (``None``:
    none). ``rtol``: a node is closed when its bound is within ``rtol * max(1, |incumbent|)``
    of the incumbent. The returned ``indices`` are sorted. ``objective`` / ``interest`` (the
    solvers' common signature): log det only.

    Raises:
        TypeError: not real numeric; ``budget`` / ``node_limit`` not an int; ``initial`` not
            int indices; ``time_limit`` / ``rtol`` not real numbers.
        ValueError: see :func:`~selenv.core.information.whitened_pool`; ``budget`` outside
            [0, N]; bad pools; ``initial`` infeasible; ``node_limit`` < 1; ``time_limit`` not
            > 0; ``rtol`` not in [0, 1); ``objective`` other than ``"logdet"`` (or an
            ``interest``).
    """
    start_clock = time.perf_counter()
    _logdet_only(objective, interest)
    prob = _problem(Q0, G, budget, groups, budgets)
    node_limit = check_int(node_limit, "node_limit", 1)
    if time_limit is not None:
        if isinstance(time_limit, bool) or not isinstance(time_limit, int | float):
            raise TypeError(f"time_limit must be a number of seconds, got {time_limit!r}")
        if not 0.0 < float(time_limit) < math.inf:
            raise ValueError(f"time_limit must be a finite number > 0, got {time_limit!r}")
    if isinstance(rtol, bool) or not isinstance(rtol, int | float):
        raise TypeError(f"rtol must be a real number, got {type(rtol).__name__}")
    if not 0.0 <= float(rtol) < 1.0:
        raise ValueError(f"rtol must be in [0, 1), got {rtol!r}")
    if initial is None:
        if groups is None:
            first = swap_whitened(prob.Q0, prob.G, int(prob.budgets[0]))
        else:
            first = partition_swap_whitened(prob.Q0, prob.G, groups, budgets)  # type: ignore[arg-type]
        best = np.sort(np.array(first.indices, dtype=np.intp))
        prob.evaluations += first.evaluations
    else:
        best = np.sort(int_indices(initial, "initial"))
        if best.size and (best.min() < 0 or best.max() >= prob.N):
            raise ValueError(f"initial must hold indices in [0, {prob.N}), got {best.tolist()}")
        counts = np.bincount(prob.owner[best] + 1, minlength=len(prob.budgets) + 1)
        if np.unique(best).size != best.size or counts[0] > 0 or np.any(counts[1:] != prob.budgets):
            raise ValueError(
                f"initial must hold {prob.budgets.tolist()} distinct indices of the pools, "
                f"got {best.tolist()}"
            )
    incumbent = prob.value(best)
    slack = float(rtol) * max(1.0, abs(incumbent))

    root = prob.propagate(np.where(prob.owner >= 0, -1, 0).astype(np.int8))
    assert root is not None
    search = _Search(prob, best, incumbent, float(rtol))
    # (-bound, order, status bytes, parent's weights or None): best bound first
    heap: list[tuple[float, int, bytes, np.ndarray | None]] = [(-math.inf, 0, root.tobytes(), None)]
    counter, nodes = 1, 0
    stopped = False
    while heap:
        if nodes >= node_limit or (
            time_limit is not None and time.perf_counter() - start_clock > time_limit
        ):
            stopped = True
            break
        neg_bound, _, raw, start = heapq.heappop(heap)
        if -neg_bound <= search.floor:
            continue  # the incumbent improved since this node was queued
        nodes += 1
        branch = search.solve_node(np.frombuffer(raw, dtype=np.int8).copy(), start)
        if branch is None:
            continue  # closed: pruned, infeasible, enumerated or a leaf
        status, res = branch
        free = np.flatnonzero(status == -1)
        k = _branch_candidate(free, res.weights[free])
        for fix in (1, 0):
            child = status.copy()
            child[k] = fix
            child_p = prob.propagate(child)
            if child_p is not None:
                heapq.heappush(heap, (-res.bound, counter, child_p.tobytes(), res.weights))
                counter += 1
    best, incumbent, slack = search.best, search.incumbent, search.floor - search.incumbent
    open_bound = max((-e[0] for e in heap), default=-math.inf) if stopped else -math.inf
    upper = max(incumbent, open_bound)
    return ExactSelection(
        indices=tuple(int(k) for k in np.sort(best)),
        objective=incumbent,
        evaluations=prob.evaluations,
        upper_bound=upper,
        optimal=not stopped or upper <= incumbent + slack,
        nodes=nodes,
        seconds=time.perf_counter() - start_clock,
    )
