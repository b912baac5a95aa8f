"""Plain solvers for FIM-based measurement selection on raw arrays (Kirchner et al. 2020).

Every solver maximises ``f(S)`` subject to ``|S| <= budget`` (eq. 8) and returns a
:class:`Selection`. ``objective`` chooses ``f`` (:mod:`selenv.core.objectives`), higher is
always better and ``f(empty) = 0``:

* ``"logdet"`` (default, D-optimal): ``log det(Q0 + sum_{k in S} H_k^T R_k^-1 H_k) - log det
  Q0`` (eq. 9, from eq. 5); monotone submodular.
* ``"trace"`` (A-optimal, eq. 6): ``tr(E P0 E^T) - tr(E P_S E^T)``, the decrease of the
  mean-square error bound of the parameters of interest (``interest``, default all).
* ``"max_eig"`` (E-optimal, eq. 7): ``lambda_max(E P0 E^T) - lambda_max(E P_S E^T)``.

``P_S`` is the CRLB ``(Q0 + sum_{k in S} Q_k)^-1``. trace and max_eig are monotone but not
submodular (the paper, after eq. 7), so the guarantees below hold for ``"logdet"`` only;
``lazy_greedy`` refuses the other two (its stale gains are upper bounds only by submodularity).

Public solvers take ``(Q0, H, R, budget)`` with ``Q0`` ``(d, d)`` SPD, and either ``H (N, m, d)``
with ``R (N, m, m)`` / ``(m, m)``, or scalar candidates ``H (N, d)`` with variances ``R (N,)``.
The ``*_whitened`` variants take the whitened pool ``G (N, m, d)`` (see
:func:`selenv.core.information.whiten`) and are what the env agents call.

============== ====================================================== ==================
solver         method                                                 guarantee
============== ====================================================== ==================
greedy         Algorithm 1 with rank-one (scalar) / block updates     >= (1 - 1/e) OPT (a)
lazy_greedy    Minoux's lazy evaluations of the same greedy (logdet)  same set as greedy
swap           greedy, then best-improvement 1-swap local search      >= greedy
brute_force    exhaustive over all C(N, B) subsets (size-guarded)     optimal
random         uniform subset                                         baseline
============== ====================================================== ==================

(a) log det only; for trace and max_eig greedy has no guarantee (swap >= greedy and brute force
optimal still hold).

Multi-agent (disjoint pools, a budget per pool, i.e. a partition matroid): ``cooperative_greedy``
(the paper's per-agent schemes), and the centralised ``partition_greedy_whitened`` (greedy over
the union of the pools, each pick the best gain among the pools with budget left: >= OPT / 2,
Fisher, Nemhauser & Wolsey 1978, log det only) and ``partition_swap_whitened`` (then swaps
within a pool); all three take ``objective`` too.

Memory: before anything is copied, a pool whose working arrays (:func:`working_bytes`, from
``N``, ``m`` and ``d``) would exceed the memory available now is a ``ValueError`` naming ``N``
and the estimate (a ``np.broadcast_to`` view of 10^8 candidates costs nothing until copied).

Validation: the raw-array solvers go through :func:`~selenv.core.information.as_candidates`
(real types only: complex, bool, str, object raise ``TypeError``; shapes name the argument
that disagrees with the others; finiteness, SPD-ness and the valid range of
:func:`~selenv.core.linalg.check_magnitude`); the ``*_whitened`` solvers check ``Q0`` and ``G``
with :func:`~selenv.core.information.whitened_pool`. Index arguments (``initial``, ``groups``)
must hold integers: a fraction is refused, never truncated.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import solve_triangular

from selenv.core.information import (
    LogDetGainState,
    _as_candidates,
    _logdet_objective_trusted,
    as_candidates,
    logdet_objective,
    whitened_pool,
)
from selenv.core.linalg import (
    FloatArray,
    check_magnitude,
    cholesky_spd,
    logdet_spd,
    validate_spd,
)
from selenv.core.objectives import (
    check_interest,
    check_objective,
    get_objective,
    make_gain_state,
    objective_value,
    subset_criteria,
    swap_criteria,
)
from selenv.families.clustering.labels import check_int
from selenv.memory import refuse_if_larger
from selenv.threads import small_blas

__all__ = [
    "MAX_BRUTE_FORCE_SUBSETS",
    "CooperativeSelection",
    "Selection",
    "brute_force",
    "brute_force_whitened",
    "cooperative_greedy",
    "greedy",
    "greedy_whitened",
    "lazy_greedy",
    "lazy_greedy_whitened",
    "partition_greedy_whitened",
    "partition_swap_whitened",
    "random_selection",
    "swap",
    "swap_deltas",
    "swap_whitened",
    "whiten_in",
]

#: default size guard of :func:`brute_force` (number of subsets evaluated)
MAX_BRUTE_FORCE_SUBSETS = 2_000_000


#: working memory below which a pool is not checked against the available memory
_CHECK_ABOVE_BYTES = 64 * 2**20


def working_bytes(N: int, m: int, d: int) -> int:
    """The memory a solver may hold at once for a pool of ``N`` candidates of ``m x d``.

    float64 arrays of the validated ``H`` and the whitened ``G`` (2 N m d), their temporaries
    (2 N m d), the broadcast, factored and validated ``R`` (3 N m^2), per-candidate ``d x d``
    information matrices and gain states (2 N d^2) and per-candidate vectors (4 N).
    """
    return 8 * N * (4 * m * d + 3 * m * m + 2 * d * d + 4)


def _check_pool_memory(pool: object, name: str) -> None:
    """Refuse a pool (``H`` or ``G``) whose solver working memory would not fit, before copying.

    The shape is read without copying an array (a broadcast view of 10^8 candidates is a few
    bytes until something copies it); anything without a usable shape is left to the
    validation that follows.

    Raises:
        ValueError: naming ``N``, ``m``, ``d``, the estimate and the available memory.
    """
    try:
        shape = np.shape(cast(ArrayLike, pool))
    except (ValueError, TypeError):  # ragged or odd input: the checks that follow name it
        return
    if len(shape) == 2:
        (N, d), m = shape, 1
    elif len(shape) == 3:
        N, m, d = shape
    else:
        return
    estimate = working_bytes(N, m, d)
    if estimate > _CHECK_ABOVE_BYTES:  # small pools (every env step) skip reading the memory
        refuse_if_larger(
            estimate, f"{name} has N={N:,} candidates of {m} x {d}: the solver's working arrays"
        )


@dataclass(frozen=True)
class Selection:
    """Result of a selection solver.

    Attributes:
        indices: selected candidate indices, in the order they were picked.
        objective: ``f(S)`` of the chosen objective (higher is better), recomputed exactly
            from the selection by :func:`~selenv.core.objectives.objective_value`: nats for
            ``"logdet"`` (eq. 9), squared parameter units for ``"trace"`` / ``"max_eig"``.
        evaluations: number of marginal-gain or subset evaluations the solver made.
        objective_name: the registered objective's name (``"logdet"``, ``"trace"``, ...).
    """

    indices: tuple[int, ...]
    objective: float
    evaluations: int
    objective_name: str = "logdet"


def _check_budget(budget: object, N: int) -> int:
    if isinstance(budget, bool) or not isinstance(budget, int | np.integer):
        raise TypeError(f"budget must be an int, got {type(budget).__name__}")
    if budget < 0:
        raise ValueError(f"budget must be >= 0, got {budget}")
    if budget > N:
        raise ValueError(f"budget ({budget}) is larger than the pool of {N} candidates")
    return int(budget)


def int_indices(value: object, name: str) -> np.ndarray:
    """``value`` as a 1-D ``intp`` array of indices; fractions are refused, never truncated.

    Raises:
        TypeError: not numeric (complex, str, object) or bool.
        ValueError: non-integer values (e.g. ``2.5``).
    """
    try:
        arr = np.asarray(list(value) if not isinstance(value, np.ndarray) else value)  # type: ignore[call-overload]
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be a sequence of int indices, got {value!r}") from exc
    if arr.size == 0:
        return np.zeros(0, dtype=np.intp)
    if arr.dtype == bool or arr.dtype.kind not in "iuf":
        raise TypeError(f"{name} must hold int indices, got dtype {arr.dtype}")
    if arr.dtype.kind == "f":
        raise ValueError(f"{name} must hold integer indices, got {value!r}")
    if arr.ndim != 1:
        raise ValueError(f"{name} must be a 1-D sequence of indices, got shape {arr.shape}")
    return arr.astype(np.intp)


def _finish(
    Q0: FloatArray,
    G: FloatArray,
    indices: Sequence[int],
    evals: int,
    objective: str = "logdet",
    interest: np.ndarray | None = None,
) -> Selection:
    idx = tuple(int(k) for k in indices)
    if objective == "logdet":
        return Selection(idx, logdet_objective(Q0, G, list(idx)), evals)
    value = objective_value(Q0, G, list(idx), objective, interest)
    return Selection(idx, value, evals, objective)


Interest = Sequence[int] | np.ndarray | None


def _objective(objective: object, interest: object, d: int) -> tuple[str, np.ndarray | None]:
    """Validated ``objective`` and ``interest`` indices (``None``: all parameters)."""
    name = check_objective(objective)
    return name, check_interest(interest, d, name)


@small_blas
def greedy_whitened(
    Q0: FloatArray,
    G: FloatArray,
    budget: int,
    *,
    objective: str = "logdet",
    interest: Interest = None,
) -> Selection:
    """Algorithm 1 with rank-one / block gain updates: ``O(N d^2 + B N m d)`` (log det).

    ``objective="trace"`` / ``"max_eig"``: the batched Woodbury gains of
    :func:`~selenv.core.objectives.criterion_gains` after each pick (``O(B N m d^2)``).

    Raises:
        TypeError: not real numeric, ``budget`` not an int, ``objective`` not a str,
            ``interest`` not int indices.
        ValueError: see :func:`~selenv.core.information.whitened_pool`; ``budget`` outside
            [0, N]; an unknown ``objective``; a bad ``interest``.
    """
    _check_pool_memory(G, "G")  # before any copy of a (maybe broadcast) pool
    if type(objective) is str and objective == "logdet" and interest is None:  # one validation
        Q0_a, G_a = whitened_pool(Q0, G)
        return _greedy_logdet(Q0_a, G_a, cholesky_spd(Q0_a, "Q0"), budget)
    state = make_gain_state(Q0, G, objective, interest=interest, track_gains=True)
    budget = _check_budget(budget, state.N)
    for _ in range(budget):
        state.add(int(np.argmax(state.masked_gains())))  # line 4: best marginal gain
    idx = getattr(state, "interest", None)
    return _finish(state.Q0, state.G, state.order, budget * state.N, objective, idx)


def _greedy_logdet(Q0: FloatArray, G: FloatArray, L0: FloatArray, budget: object) -> Selection:
    """Log-det greedy on a validated ``Q0`` / ``G``: the picks and objective of the general path.

    The same :class:`~selenv.core.information.LogDetGainState` updates and argmax as
    :func:`greedy_whitened` with ``make_gain_state``, minus the re-validation of ``Q0`` and
    ``G`` and with ``Q0``'s Cholesky factor ``L0`` (``cholesky_spd(Q0)``) reused for the final
    objective.

    Raises:
        TypeError: ``budget`` not an int.
        ValueError: ``budget`` outside [0, N].
    """
    budget = _check_budget(budget, G.shape[0])
    state = LogDetGainState._trusted(Q0, G, L0)
    selected, order, gains = state.selected, state.order, state.gains
    for _ in range(budget):
        assert gains is not None  # tracked by construction
        j = int(np.argmax(np.where(selected, -np.inf, gains)))  # line 4: best marginal gain
        state._add_rank_one(G[j])
        selected[j] = True
        order.append(j)
        gains = state.gains
    value = _logdet_objective_trusted(Q0, G, order, state.L0)
    return Selection(tuple(order), value, budget * state.N)


def _refuse_lazy(objective: object) -> None:
    obj = get_objective(objective)
    if not obj.submodular:
        raise ValueError(
            f"lazy_greedy needs a submodular objective, and objective={objective!r} is not "
            "submodular (Kirchner et al. 2020, after eq. 7): stale gains are then no upper "
            "bounds and the lazy picks could differ from greedy's; use greedy with this "
            "objective, or objective='logdet'"
        )
    if obj.name != "logdet":
        raise ValueError(
            f"lazy_greedy is implemented for objective='logdet' only, got {objective!r}; use "
            "greedy with this objective"
        )


@small_blas
def lazy_greedy_whitened(
    Q0: FloatArray,
    G: FloatArray,
    budget: int,
    *,
    objective: str = "logdet",
    interest: Interest = None,
) -> Selection:
    """Greedy with lazy evaluations (Minoux 1978): stale gains are upper bounds by submodularity.

    Only ``P = A^-1`` is updated per pick; a candidate's gain is recomputed (``O(m d^2)``) when
    it reaches the top of the heap. Ties break towards the lower index, as in :func:`greedy`.
    Log det only: ``objective="trace"`` / ``"max_eig"`` are refused (not submodular);
    ``interest`` (accepted for a uniform solver signature) must then be ``None``.

    Raises:
        TypeError, ValueError: as :func:`greedy_whitened`; ``ValueError`` for an
            ``objective`` other than ``"logdet"``.
    """
    _check_pool_memory(G, "G")  # before any copy of a (maybe broadcast) pool
    _refuse_lazy(objective)
    check_interest(interest, 0, "logdet")
    state = LogDetGainState(Q0, G, track_gains=True)  # validates Q0 and G
    Q0, G = state.Q0, state.G
    budget = _check_budget(budget, state.N)
    assert state.gains is not None  # internal invariant, not user input
    heap = [(-float(g), k, 0) for k, g in enumerate(state.gains)]
    heapq.heapify(heap)
    state.S = state.gains = None
    state.track_gains = False  # from now on only P is updated
    evals = G.shape[0]
    for step in range(budget):
        while True:
            _, k, stamp = heapq.heappop(heap)
            if stamp == step:  # fresh bound for this step: it is the exact max
                state.add(k)
                break
            gain = state.gain_of(k)
            evals += 1
            heapq.heappush(heap, (-gain, k, step))
    return _finish(Q0, G, state.order, evals)


def _subset_logdets(Qk: FloatArray, Q0: FloatArray, combos: np.ndarray) -> FloatArray:
    A = Q0 + Qk[combos].sum(axis=1)  # (C, d, d) FIM of each subset, eq. (2)
    L = cholesky_spd(A, "FIM")
    return 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)


@small_blas
def brute_force_whitened(
    Q0: FloatArray,
    G: FloatArray,
    budget: int,
    *,
    max_subsets: int = MAX_BRUTE_FORCE_SUBSETS,
    objective: str = "logdet",
    interest: Interest = None,
) -> Selection:
    """Exhaustive optimum over all subsets of size ``budget`` (f is monotone, so ``|S| = B``).

    Every objective: batched Cholesky of each subset's FIM (log det, or ``E A_S^-1 E^T`` for
    trace / max_eig, :func:`~selenv.core.objectives.subset_criteria`); ties towards the
    lexicographically first subset.

    Raises:
        TypeError: not real numeric, ``budget`` / ``max_subsets`` not an int, ``objective`` /
            ``interest`` of the wrong type.
        ValueError: see :func:`~selenv.core.information.whitened_pool`; ``budget`` outside
            [0, N], or ``C(N, budget) > max_subsets`` (the size guard); an unknown
            ``objective``; a bad ``interest``.
    """
    _check_pool_memory(G, "G")  # before any copy of a (maybe broadcast) pool
    Q0, G = whitened_pool(Q0, G)
    N = G.shape[0]
    objective, idx = _objective(objective, interest, G.shape[2])
    budget = _check_budget(budget, N)
    max_subsets = check_int(max_subsets, "max_subsets", 1)  # NaN would skip the guard
    n_sub = math.comb(N, budget)
    if n_sub > max_subsets:
        raise ValueError(
            f"brute_force refuses C({N}, {budget}) = {n_sub:,} subsets (max_subsets="
            f"{max_subsets:,}); use greedy or swap, or raise max_subsets"
        )
    if budget == 0:
        return Selection((), 0.0, 1, objective)
    Qk = np.einsum("kmi,kmj->kij", G, G)  # Q_k = G_k^T G_k
    best_val, best = -np.inf, None
    it = itertools.combinations(range(N), budget)
    chunk = max(1, 200_000 // (budget * G.shape[2] ** 2))
    while True:
        block = np.array(list(itertools.islice(it, chunk)), dtype=np.intp)
        if block.size == 0:
            break
        if objective == "logdet":
            vals = _subset_logdets(Qk, Q0, block)
        else:  # minus the criterion: the argmax of f = crit0 - crit
            vals = -subset_criteria(Q0, Qk, block, objective, idx)
        i = int(np.argmax(vals))
        if vals[i] > best_val:
            best_val, best = float(vals[i]), block[i]
    assert best is not None
    return _finish(Q0, G, best.tolist(), n_sub, objective, idx)


def whiten_in(Q0: FloatArray, G: FloatArray, sel: np.ndarray) -> FloatArray:
    """``Z = G L^-T`` with ``L L^T = A = Q0 + sum_{k in sel} G_k^T G_k`` (eq. 2), ``(N, m, d)``.

    The candidates whitened in the information of the selection ``sel``: ``Z_i Z_j^T =
    G_i A^-1 G_j^T``. Inputs are trusted (validated by the caller).

    Raises:
        ValueError: ``A`` is not numerically positive definite.
    """
    N, m, d = G.shape
    Gs = G[sel].reshape(-1, d)
    L = cholesky_spd(Q0 + Gs.T @ Gs, "FIM")
    Z = solve_triangular(L, G.reshape(N * m, d).T, lower=True, check_finite=False)  # L^-1 G^T
    out: FloatArray = np.ascontiguousarray(Z.T).reshape(N, m, d)
    return out


def swap_deltas(Z: FloatArray, sel: np.ndarray, uns: np.ndarray) -> FloatArray:
    """``log det(A - Q_i + Q_j) - log det A`` for selected ``i`` and unselected ``j``, ``(K, U)``.

    ``Z`` ``(N, m, d)``: the candidates whitened in the selection's information ``A = L L^T``
    (:func:`whiten_in`, ``Z_k = G_k L^-T``), so ``S_ii = Z_i Z_i^T = G_i A^-1 G_i^T``,
    ``S_jj = Z_j Z_j^T`` and ``C_ij = Z_i Z_j^T``. The matrix determinant lemma with
    ``U = [G_i; G_j]`` and ``D = diag(-I, I)`` gives ``det(A + U^T D U) / det A =
    det(I + D U A^-1 U^T)``, the determinant of ``[[I - S_ii, -C_ij], [C_ij^T, I + S_jj]]``,
    and its Schur complement on the first block:

    ``log det(A - Q_i + Q_j) - log det A
    = log det(I - S_ii) + log det(I + S_jj + C_ij^T (I - S_ii)^-1 C_ij)``.

    Written out entry by entry for ``m = 1`` and ``m = 2`` rows per candidate (every Kirchner
    preset), so one pass over the ``K x U`` pairs is one matrix product and a few elementwise
    array operations instead of ``K U`` determinants of ``2m x 2m`` matrices; batched
    ``slogdet`` of the ``m x m`` blocks otherwise. A pair whose matrix is not positive
    definite (rounding on a degenerate pool) gets ``-inf``. Inputs are trusted.
    """
    _, m, d = Z.shape
    Zi, Zj = Z[sel], Z[uns]  # (K, m, d), (U, m, d)
    K, U = len(sel), len(uns)
    C = (Zi.reshape(K * m, d) @ Zj.reshape(U * m, d).T).reshape(K, m, U, m)
    C = C.transpose(0, 2, 1, 3)  # C[k, u] = Z_i Z_j^T (K, U, m, m)
    with np.errstate(divide="ignore", invalid="ignore"):
        if m == 1:
            a = 1.0 - np.einsum("kd,kd->k", Zi[:, 0], Zi[:, 0])  # I - S_ii (K,)
            s = np.einsum("ud,ud->u", Zj[:, 0], Zj[:, 0])  # S_jj (U,)
            comp = 1.0 + s[None] + C[..., 0, 0] ** 2 / a[:, None]
            out = np.log(a)[:, None] + np.log(comp)
            ok = (a[:, None] > 0) & (comp > 0)
        elif m == 2:
            i0, i1, j0, j1 = Zi[:, 0], Zi[:, 1], Zj[:, 0], Zj[:, 1]
            a00 = 1.0 - np.einsum("kd,kd->k", i0, i0)  # I - S_ii
            a01 = -np.einsum("kd,kd->k", i0, i1)
            a11 = 1.0 - np.einsum("kd,kd->k", i1, i1)
            det_a = a00 * a11 - a01 * a01  # det(I - S_ii)
            p, q, r = (x[:, None] / det_a[:, None] for x in (a11, -a01, a00))  # (I - S_ii)^-1
            c00, c01, c10, c11 = C[..., 0, 0], C[..., 0, 1], C[..., 1, 0], C[..., 1, 1]
            t00 = p * c00 * c00 + 2.0 * q * c00 * c10 + r * c10 * c10  # C^T (I - S_ii)^-1 C
            t01 = p * c00 * c01 + q * (c00 * c11 + c10 * c01) + r * c10 * c11
            t11 = p * c01 * c01 + 2.0 * q * c01 * c11 + r * c11 * c11
            s00 = np.einsum("ud,ud->u", j0, j0)  # S_jj
            s01 = np.einsum("ud,ud->u", j0, j1)
            s11 = np.einsum("ud,ud->u", j1, j1)
            det_c = (1.0 + s00 + t00) * (1.0 + s11 + t11) - (s01 + t01) ** 2
            out = np.log(det_a)[:, None] + np.log(det_c)
            ok = (det_a[:, None] > 0) & (a00[:, None] > 0) & (det_c > 0)
        else:
            eye = np.eye(m)
            A = eye - Zi @ np.swapaxes(Zi, -1, -2)  # I - S_ii (K, m, m)
            sign_a, log_a = np.linalg.slogdet(A)
            X = np.linalg.solve(A[:, None], C)  # (I - S_ii)^-1 C
            Sjj = Zj @ np.swapaxes(Zj, -1, -2)
            sign_c, log_c = np.linalg.slogdet(eye + Sjj[None] + np.swapaxes(C, -1, -2) @ X)
            out = log_a[:, None] + log_c
            ok = (sign_a[:, None] > 0) & (sign_c > 0)
    return np.where(ok, out, -np.inf)


def _check_tol(tol: object) -> float:
    if isinstance(tol, bool) or not isinstance(tol, int | float | np.integer | np.floating):
        raise TypeError(f"tol must be a real number, got {type(tol).__name__}")
    if not 0.0 <= float(tol) < math.inf:
        raise ValueError(f"tol must be a finite number >= 0, got {tol!r}")
    return float(tol)


@small_blas
def swap_whitened(
    Q0: FloatArray,
    G: FloatArray,
    budget: int,
    *,
    initial: Sequence[int] | None = None,
    max_rounds: int = 200,
    tol: float = 1e-9,
    objective: str = "logdet",
    interest: Interest = None,
) -> Selection:
    """Greedy (or ``initial``) followed by best-improvement swap local search.

    Each round evaluates every (selected, unselected) swap in one batched pass of
    :func:`swap_deltas` (the pool whitened in the current information, ``O(N m d^2)``, then
    the Schur complement of the determinant-lemma matrix, ``O(K N m^2 d)``) and applies the
    best (the first in row-major order on ties) if it gains more than ``tol`` nats. The
    objective never decreases, so the result is at least as good as greedy. For
    ``objective="trace"`` / ``"max_eig"`` a swap's value is the criterion of ``A - Q_i + Q_j``
    by batched Cholesky (:func:`~selenv.core.objectives.swap_criteria`, ``O(K N d^3)``) and
    ``tol`` is in the objective's units.

    Raises:
        TypeError: not real numeric, ``budget`` / ``max_rounds`` not an int, ``initial`` not
            int indices.
        ValueError: see :func:`~selenv.core.information.whitened_pool`; ``budget`` outside
            [0, N]; ``initial`` not ``budget`` distinct indices in [0, N); ``tol`` not a
            finite number >= 0.
    """
    _check_pool_memory(G, "G")  # before any copy of a (maybe broadcast) pool
    Q0, G = whitened_pool(Q0, G)
    N = G.shape[0]
    budget = _check_budget(budget, N)
    max_rounds = check_int(max_rounds, "max_rounds", 0)
    tol = _check_tol(tol)
    objective, idx = _objective(objective, interest, G.shape[2])
    if initial is None:
        start = greedy_whitened(Q0, G, budget, objective=objective, interest=idx)
        sel = np.array(start.indices, dtype=np.intp)
    else:
        start, sel = None, int_indices(initial, "initial")
        if sel.size and (sel.min() < 0 or sel.max() >= N):
            raise ValueError(f"initial must hold indices in [0, {N}), got {list(sel)}")
    if len(set(sel.tolist())) != budget or sel.size != budget:
        raise ValueError(f"initial must hold {budget} distinct indices, got {list(sel)}")
    evals = start.evaluations if start else 0
    for _ in range(max_rounds):
        if budget in (0, N):
            break
        uns = np.setdiff1d(np.arange(N), sel)
        delta = _deltas(Q0, G, sel, uns, objective, idx)
        evals += delta.size
        i, j = np.unravel_index(int(np.argmax(delta)), delta.shape)
        if delta[i, j] <= tol:
            break
        sel[i] = uns[j]
    return _finish(Q0, G, sel.tolist(), evals, objective, idx)


def _deltas(
    Q0: FloatArray,
    G: FloatArray,
    sel: np.ndarray,
    uns: np.ndarray,
    objective: str,
    interest: np.ndarray | None,
) -> FloatArray:
    """``f(S - i + j) - f(S)`` for every selected ``i`` and unselected ``j``, ``(K, U)``."""
    if objective == "logdet":
        return swap_deltas(whiten_in(Q0, G, sel), sel, uns)
    crit = subset_criteria(Q0, np.einsum("kmi,kmj->kij", G, G), sel[None], objective, interest)
    return float(crit[0]) - swap_criteria(Q0, G, sel, uns, objective, interest)


@small_blas
def greedy(
    Q0: object,
    H: object,
    R: object,
    budget: int,
    *,
    objective: str = "logdet",
    interest: Interest = None,
) -> Selection:
    """Greedy selection (Algorithm 1) on raw arrays; see the module docstring for shapes.

    ``objective``: a registered objective (:mod:`selenv.core.objective_registry`): ``"logdet"``
    (default), ``"trace"``, ``"max_eig"``, ``"det"`` or the user's own; ``interest``: indices
    of the parameters scored by objectives other than log det (default all ``d``).

    Raises:
        TypeError: ``Q0``, ``H`` or ``R`` not real numeric (complex, bool, str, object),
            ``budget`` not an int, ``objective`` / ``interest`` of the wrong type.
        ValueError: see :func:`~selenv.core.information.as_candidates`; ``budget`` outside
            [0, N]; an unknown ``objective``; a bad ``interest``.
    """
    _check_pool_memory(H, "H")  # before any copy of a (maybe broadcast) pool
    if type(objective) is str and objective == "logdet" and interest is None:  # fast path
        return _greedy_logdet(*_as_candidates(Q0, H, R), budget)
    Q0_a, G = as_candidates(Q0, H, R)
    return greedy_whitened(Q0_a, G, budget, objective=objective, interest=interest)


@small_blas
def lazy_greedy(
    Q0: object, H: object, R: object, budget: int, *, objective: str = "logdet"
) -> Selection:
    """Lazy greedy on raw arrays; returns the same set as :func:`greedy` with fewer evaluations.

    Log det only (``objective`` other than ``"logdet"`` is refused: not submodular).

    Raises:
        TypeError: ``Q0``, ``H`` or ``R`` not real numeric (complex, bool, str, object), or
            ``budget`` not an int.
        ValueError: see :func:`~selenv.core.information.as_candidates`; ``budget`` outside
            [0, N]; ``objective`` not ``"logdet"``.
    """
    _refuse_lazy(objective)
    _check_pool_memory(H, "H")  # before any copy of a (maybe broadcast) pool
    Q0_a, G = as_candidates(Q0, H, R)
    return lazy_greedy_whitened(Q0_a, G, budget)


@small_blas
def brute_force(
    Q0: object,
    H: object,
    R: object,
    budget: int,
    *,
    max_subsets: int = MAX_BRUTE_FORCE_SUBSETS,
    objective: str = "logdet",
    interest: Interest = None,
) -> Selection:
    """Exhaustive optimum on raw arrays; refuses more than ``max_subsets`` subsets.

    Raises:
        TypeError: ``Q0``, ``H`` or ``R`` not real numeric (complex, bool, str, object),
            ``budget`` not an int, ``objective`` / ``interest`` of the wrong type.
        ValueError: see :func:`~selenv.core.information.as_candidates`; ``budget`` outside
            [0, N]; an unknown ``objective``; a bad ``interest``.
    """
    _check_pool_memory(H, "H")  # before any copy of a (maybe broadcast) pool
    Q0_a, G = as_candidates(Q0, H, R)
    return brute_force_whitened(
        Q0_a, G, budget, max_subsets=max_subsets, objective=objective, interest=interest
    )


@small_blas
def swap(
    Q0: object,
    H: object,
    R: object,
    budget: int,
    *,
    max_rounds: int = 200,
    objective: str = "logdet",
    interest: Interest = None,
) -> Selection:
    """Greedy plus swap local search on raw arrays.

    Raises:
        TypeError: ``Q0``, ``H`` or ``R`` not real numeric (complex, bool, str, object),
            ``budget`` not an int, ``objective`` / ``interest`` of the wrong type.
        ValueError: see :func:`~selenv.core.information.as_candidates`; ``budget`` outside
            [0, N]; an unknown ``objective``; a bad ``interest``.
    """
    _check_pool_memory(H, "H")  # before any copy of a (maybe broadcast) pool
    Q0_a, G = as_candidates(Q0, H, R)
    return swap_whitened(
        Q0_a, G, budget, max_rounds=max_rounds, objective=objective, interest=interest
    )


def random_selection(
    Q0: object, H: object, R: object, budget: int, *, rng: np.random.Generator
) -> Selection:
    """Uniformly random subset of size ``budget`` drawn from ``rng`` (the baseline).

    Raises:
        TypeError: as :func:`greedy`, or ``rng`` not a ``numpy.random.Generator``.
        ValueError: as :func:`greedy`.
    """
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    Q0_a, G = as_candidates(Q0, H, R)
    budget = _check_budget(budget, G.shape[0])
    idx = rng.choice(G.shape[0], size=budget, replace=False)
    return _finish(Q0_a, G, idx.tolist(), 0)


@dataclass(frozen=True)
class CooperativeSelection:
    """Per-agent selections and the fusion centre's objective ``f(F_1 u ... u F_n)``."""

    selections: tuple[Selection, ...]
    objective: float


def cooperative_greedy(
    Q0: object,
    pools: Sequence[tuple[object, object]],
    budgets: Sequence[int],
    *,
    mode: str = "cooperative",
    objective: str = "logdet",
    interest: Interest = None,
) -> CooperativeSelection:
    """Multi-agent greedy selection (Kirchner et al. 2020, Sec. 6, "Cooperative Selection").

    ``mode="independent"``: every agent runs Algorithm 1 on its own pool with prior ``Q0``.
    ``mode="cooperative"``: agents select in turn; agent ``i`` replaces ``Q0`` with the FIM of
    the prior and of agents ``1..i-1``'s picks.

    Args:
        Q0: ``(d, d)`` SPD prior information shared by all agents.
        pools: one ``(H_i, R_i)`` pool per agent, shapes as in :func:`greedy`.
        budgets: ``B_i`` per agent.
        mode: ``"independent"`` or ``"cooperative"``.
        objective: ``"logdet"`` (default, the paper's), ``"trace"`` or ``"max_eig"``: the
            criterion of each agent's greedy and of the centre's ``f``.
        interest: parameters scored by trace / max_eig (default all).

    Returns:
        Each agent's :class:`Selection` (its ``objective`` is the agent's own gain on top of its
        prior) and the centre's ``f`` of the union.

    Raises:
        TypeError: as :func:`greedy` (for ``Q0`` and every pool).
        ValueError: as :func:`greedy`, an unknown ``mode``, or ``pools`` and ``budgets`` of
            different lengths.
    """
    if mode not in ("independent", "cooperative"):
        raise ValueError(f"mode must be 'independent' or 'cooperative', got {mode!r}")
    if len(pools) != len(budgets):
        raise ValueError(f"pools ({len(pools)}) and budgets ({len(budgets)}) must match")
    Q0_a = check_magnitude(validate_spd(Q0, "Q0"), "Q0", definite=True)
    objective, idx = _objective(objective, interest, Q0_a.shape[0])
    Gs = [as_candidates(Q0_a, H, R)[1] for H, R in pools]
    prior = Q0_a
    picks: list[Selection] = []
    centre = Q0_a.copy()
    rows = [np.zeros((0, Q0_a.shape[0]))]
    for G, B in zip(Gs, budgets, strict=True):
        s = greedy_whitened(prior, G, B, objective=objective, interest=idx)
        picks.append(s)
        Gs_sel = G[list(s.indices)].reshape(-1, G.shape[2])
        rows.append(Gs_sel)
        centre = centre + Gs_sel.T @ Gs_sel
        if mode == "cooperative":
            prior = centre
    if objective == "logdet":
        obj = float(logdet_spd(centre, "FIM")) - float(logdet_spd(Q0_a, "Q0"))
    else:  # f of the union: every picked row as one pseudo-candidate (its FIM is the centre's)
        obj = objective_value(Q0_a, np.concatenate(rows)[None], [0], objective, idx)
    return CooperativeSelection(tuple(picks), obj)


def _check_partition(
    N: int, groups: Sequence[Sequence[int]], budgets: Sequence[int]
) -> tuple[np.ndarray, np.ndarray]:
    """``owner`` ``(N,)`` (group of each candidate, ``-1`` for none) and budgets as an array."""
    if len(groups) != len(budgets):
        raise ValueError(f"groups ({len(groups)}) and budgets ({len(budgets)}) must match")
    owner = np.full(N, -1, dtype=np.intp)
    B = np.empty(len(groups), dtype=np.intp)
    for g, (members, budget) in enumerate(zip(groups, budgets, strict=True)):
        idx = int_indices(members, f"groups[{g}]")
        if idx.size and (idx.min() < 0 or idx.max() >= N):
            raise ValueError(f"group {g} holds indices outside [0, {N})")
        if np.any(owner[idx] >= 0) or np.unique(idx).size != idx.size:
            raise ValueError(f"groups must be disjoint sets of indices; group {g} overlaps")
        owner[idx] = g
        B[g] = _check_budget(budget, idx.size)
    return owner, B


def partition_greedy_whitened(
    Q0: FloatArray,
    G: FloatArray,
    groups: Sequence[Sequence[int]],
    budgets: Sequence[int],
    *,
    objective: str = "logdet",
    interest: Interest = None,
) -> Selection:
    """Greedy under a partition matroid: at most ``budgets[g]`` picks from ``groups[g]``.

    The centralised multi-agent greedy: one decision-maker sees the pooled candidates of every
    agent (``groups[g]`` the indices of agent ``g``'s pool) and, for ``sum(budgets)`` picks,
    takes the largest marginal gain among the unselected candidates whose group still has
    budget (ties towards the lower index). ``f`` is monotone submodular, so this is
    ``>= OPT / 2`` (Fisher, Nemhauser & Wolsey 1978); with one group holding every candidate it
    is :func:`greedy_whitened`. Candidates in no group are never picked. ``objective`` /
    ``interest`` as in :func:`greedy_whitened` (the ``OPT / 2`` bound is for log det only).

    Raises:
        TypeError: not real numeric, group members not int indices, budgets not ints.
        ValueError: see :func:`~selenv.core.information.whitened_pool`; groups that overlap
            or leave ``[0, N)``, a budget larger than its group; an unknown ``objective``.
    """
    Q0, G = whitened_pool(Q0, G)
    N = G.shape[0]
    owner, left = _check_partition(N, groups, budgets)
    objective, idx = _objective(objective, interest, G.shape[2])
    state = make_gain_state(Q0, G, objective, interest=idx, track_gains=True)
    total = int(left.sum())
    for _ in range(total):
        open_ = owner >= 0
        open_[open_] = left[owner[open_]] > 0  # the candidate's group has budget left
        k = int(np.argmax(np.where(open_, state.masked_gains(), -np.inf)))
        state.add(k)
        left[owner[k]] -= 1
    return _finish(Q0, G, state.order, total * N, objective, idx)


def partition_swap_whitened(
    Q0: FloatArray,
    G: FloatArray,
    groups: Sequence[Sequence[int]],
    budgets: Sequence[int],
    *,
    initial: Sequence[int] | None = None,
    max_rounds: int = 200,
    tol: float = 1e-9,
    objective: str = "logdet",
    interest: Interest = None,
) -> Selection:
    """:func:`partition_greedy_whitened` (or ``initial``), then swaps within each group.

    Each round evaluates, for every group, every (selected, unselected) pair of that group
    (:func:`swap_deltas`, as :func:`swap_whitened`) and applies the best swap over all
    groups if it gains more than ``tol`` nats, so every group keeps its number of picks and the
    objective never decreases: at least the partition greedy.

    Raises:
        TypeError: as :func:`partition_greedy_whitened`, or ``initial`` not int indices.
        ValueError: as :func:`partition_greedy_whitened`, or an ``initial`` selection that is
            not ``budgets[g]`` distinct indices of each group ``g``.
    """
    Q0, G = whitened_pool(Q0, G)
    N = G.shape[0]
    owner, B = _check_partition(N, groups, budgets)
    max_rounds = check_int(max_rounds, "max_rounds", 0)
    tol = _check_tol(tol)
    objective, idx = _objective(objective, interest, G.shape[2])
    start = (
        partition_greedy_whitened(Q0, G, groups, budgets, objective=objective, interest=idx)
        if initial is None
        else None
    )
    sel = np.array(start.indices, dtype=np.intp) if start else int_indices(initial, "initial")
    inside = bool(np.all((sel >= 0) & (sel < N)))
    group_of = owner[sel] if inside else np.full(sel.size, -1)
    counts = np.bincount(group_of[group_of >= 0], minlength=len(B))
    if np.unique(sel).size != sel.size or np.any(group_of < 0) or not np.array_equal(counts, B):
        raise ValueError(
            f"initial must hold budgets[g] distinct indices of each group g, got {list(sel)}"
        )
    evals = start.evaluations if start else 0
    for _ in range(max_rounds):
        if sel.size == 0:
            break
        best, best_i, best_j = tol, -1, -1
        Z = whiten_in(Q0, G, sel) if objective == "logdet" else None  # once per round
        for g in range(len(B)):
            rows = np.flatnonzero(owner[sel] == g)
            uns = np.setdiff1d(np.flatnonzero(owner == g), sel)
            if rows.size == 0 or uns.size == 0:
                continue
            delta = _group_deltas(Q0, G, Z, sel, rows, uns, objective, idx)
            evals += delta.size
            i, j = np.unravel_index(int(np.argmax(delta)), delta.shape)
            if delta[i, j] > best:
                best, best_i, best_j = float(delta[i, j]), int(rows[i]), int(uns[j])
        if best_i < 0:
            break
        sel[best_i] = best_j
    return _finish(Q0, G, sel.tolist(), evals, objective, idx)


def _group_deltas(
    Q0: FloatArray,
    G: FloatArray,
    Z: FloatArray | None,
    sel: np.ndarray,
    rows: np.ndarray,
    uns: np.ndarray,
    objective: str,
    interest: np.ndarray | None,
) -> FloatArray:
    """``f(S - sel[r] + j) - f(S)`` for ``r`` in ``rows`` and ``j`` in ``uns``, ``(|rows|, U)``.

    ``Z``: for log det, the pool whitened in the information of ``S`` (:func:`whiten_in`),
    shared by every group of the round; ``None`` for the other objectives.
    """
    if Z is not None:
        return swap_deltas(Z, sel[rows], uns)
    return _deltas(Q0, G, sel, uns, objective, interest)[rows]
