"""Variable Neighbourhood Search for log-det subset selection (Soubaras & Chahbazian 2023, Alg. 2).

Maximises ``f(S) = log det(Q0 + sum_{k in S} G_k^T G_k) - log det Q0`` over subsets of exactly
``budget`` candidates (the same objective as :mod:`selenv.agents.fim_solvers`; minimising the
det or log det of the posterior covariance, eq. 11, is the same problem because
``log det P_post = log det P_prior - f(S)``).

Neighbourhood ``V_l(s)`` (eq. 15): the selections that differ from ``s`` in exactly ``l``
candidates. From a reference ``s`` (warm start: the previous step's selection, as the paper
suggests) and ``l = 1``: draw ``w ~ U(V_l(s))`` by exchanging ``l`` selected with ``l`` unselected
candidates; if ``f(w) > f(s)`` take it and reset ``l = 1``; after ``M_l`` draws without
improvement go to ``l + 1``; stop after ``l_max``. ``f`` of a subset is
``log det(I + Z_S Z_S^T)`` with ``Z_k = G_k L^-T`` (``Q0 = L L^T``), read off one Gram matrix
of the whitened rows, so one evaluation is a ``(m K) x (m K)`` log det.

``objective="trace"`` / ``"max_eig"`` (A- / E-optimal, Kirchner et al. 2020 eqs. 6, 7; see
:mod:`selenv.core.objectives`): with ``Y = G P0 E^T`` (rows ``Z L^-1 E^T``), Woodbury gives
``E P_S E^T = E P0 E^T - Y_S^T (I + Z_S Z_S^T)^-1 Y_S``, so one evaluation is a Cholesky of the
same ``(m K) x (m K)`` matrix: ``f = ||C^-1 Y_S||_F^2`` (trace) or
``lambda_max(E P0 E^T) - lambda_max(E P0 E^T - (C^-1 Y_S)^T C^-1 Y_S)`` (max_eig); any other
registered objective ``c`` is ``c(E P0 E^T) - c(E P_S E^T)`` by the same downdate
(:meth:`~selenv.core.objective_registry.Objective.downdate_gain`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np

from selenv.agents.fim_solvers import Interest, Selection, _check_budget, _finish, int_indices
from selenv.core.information import as_candidates, whitened_pool
from selenv.core.linalg import FloatArray, cholesky_spd
from selenv.core.objectives import check_interest, check_objective, get_objective
from selenv.threads import small_blas

__all__ = ["DEFAULT_M", "vns", "vns_whitened"]

#: default ``M_l`` (draws without improvement before widening), for ``l = 1, 2, ...``
DEFAULT_M: tuple[int, ...] = (40, 20)


@small_blas
def vns_whitened(
    Q0: FloatArray,
    G: FloatArray,
    budget: int,
    *,
    initial: Sequence[int] | None = None,
    l_max: int | None = None,
    m_l: Sequence[int] = DEFAULT_M,
    batched: bool = True,
    rng: np.random.Generator | int | None = None,
    objective: str = "logdet",
    interest: Interest = None,
) -> Selection:
    """Algorithm 2 of Soubaras & Chahbazian on a whitened pool.

    Args:
        Q0: (d, d) SPD prior information (``P_prior^-1`` in the filter).
        G: (N, m, d) whitened candidates ``R^-1/2 H``.
        budget: subset size ``K``.
        initial: warm start (``K`` distinct indices); ``None`` starts from the ``K`` candidates
            with the largest single gains.
        l_max: largest neighbourhood, default ``min(K, N - K, len(m_l))``.
        m_l: ``M_1, M_2, ...``: draws without improvement before widening (the last value is
            reused for larger ``l``).
        batched: draw the ``M_l`` neighbours of the reference at once, evaluate them in one
            batched log det and move to the best if it improves (default); ``False`` is the
            paper's sequential loop (move at the first improving draw). Same neighbourhoods
            and stopping rule; the batched form is ~5x faster per evaluation in numpy and
            picks the best of the draws instead of the first improvement. When the whole
            neighbourhood ``V_l`` has at most ``M_l`` members it is enumerated instead of
            sampled, so with ``K = 1`` VNS returns the exact optimum.
        rng: generator or seed for the neighbourhood draws.
        objective: a registered objective (:mod:`selenv.core.objective_registry`):
            ``"logdet"`` (default, the paper's), ``"trace"``, ``"max_eig"``, ...
        interest: parameters scored by trace / max_eig (default all ``d``).

    Returns:
        The best subset found (indices sorted), ``f`` and the number of subset evaluations.

    Raises:
        TypeError: ``Q0`` / ``G`` not real numeric, ``budget`` not an int, ``initial`` not
            int indices, ``l_max`` or an ``M_l`` that is not an int, ``batched`` not a bool,
            ``rng`` not a ``Generator`` / seed.
        ValueError: ``Q0`` / ``G`` as :func:`~selenv.core.information.whitened_pool`
            (shapes, SPD, finite, valid range), ``budget`` out of range, an invalid
            ``initial`` (fractions are refused, not truncated), ``l_max`` or ``M_l < 1``.
    """
    Q0, G = whitened_pool(Q0, G)
    N, _, d = G.shape
    K = _check_budget(budget, N)
    objective = check_objective(objective)
    idx = check_interest(interest, d, objective)
    init = _check_options(batched, rng, m_l, initial, l_max, K, N)
    if K == 0 or K == N:
        return _finish(Q0, G, list(range(K)), 0, objective, idx)
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    score = _SubsetScorer(Q0, G, K, objective, idx)
    sel = np.sort(np.argsort(-score.singles(), kind="stable")[:K]) if init is None else init
    widest = min(K, N - K)  # no swap of more than this many exists
    if l_max is not None and l_max > widest:
        raise ValueError(f"l_max must be an int <= min(K, N - K) = {widest}, got {l_max!r}")
    l_max = min(widest, len(m_l)) if l_max is None else int(l_max)
    if l_max < 1 or not m_l or min(m_l) < 1:
        raise ValueError(f"l_max and every M_l must be >= 1, got l_max={l_max}, m_l={m_l!r}")

    best = float(score(sel[None])[0])
    evals = 1
    size, j = 1, 0  # neighbourhood size l and draws without improvement at this size
    while size <= l_max:
        M = m_l[min(size, len(m_l)) - 1]
        cands, exhaustive = _neighbours(sel, size, M, N, batched, rng)
        v = score(cands)
        evals += cands.shape[0]
        i = int(np.argmax(v))
        if v[i] > best:
            sel, best = np.sort(cands[i]), float(v[i])
            size, j = 1, 0
        else:
            j += cands.shape[0]
            if exhaustive or j >= M:  # V_l was enumerated whole: drawing again cannot help
                size, j = size + 1, 0
    return _finish(Q0, G, sel.tolist(), evals, objective, idx)


def _check_options(
    batched: object,
    rng: object,
    m_l: object,
    initial: Sequence[int] | None,
    l_max: object,
    K: int,
    N: int,
) -> np.ndarray | None:
    """Validate the search options (see :func:`vns_whitened`); the sorted warm start or ``None``."""
    if not isinstance(batched, bool | np.bool_):
        raise TypeError(f"batched must be a bool, got {batched!r}")
    if not (
        rng is None
        or isinstance(rng, np.random.Generator | np.random.SeedSequence | np.random.BitGenerator)
        or (isinstance(rng, int | np.integer) and not isinstance(rng, bool) and rng >= 0)
    ):
        raise TypeError(f"rng must be a numpy Generator, a seed int >= 0 or None, got {rng!r}")
    if (
        not isinstance(m_l, Sequence | np.ndarray)
        or isinstance(m_l, str)
        or not all(isinstance(M, int | np.integer) and not isinstance(M, bool) for M in m_l)
    ):
        raise TypeError(f"m_l must be a sequence of ints, got {m_l!r}")
    if len(m_l) == 0 or min(m_l) < 1:
        raise ValueError(f"m_l must hold at least one M_l and every M_l must be >= 1, got {m_l!r}")
    init = None
    if initial is not None:  # checked even when budget in (0, N) makes the search trivial
        init = np.sort(int_indices(initial, "initial"))  # 2.7 -> 2 no more
        if init.size != K or np.unique(init).size != K or (K and (init[0] < 0 or init[-1] >= N)):
            raise ValueError(f"initial must be {K} distinct indices in [0, {N}), got {initial!r}")
    if l_max is not None and (isinstance(l_max, bool) or not isinstance(l_max, int | np.integer)):
        raise TypeError(f"l_max must be an int or None, got {l_max!r}")
    return init


class _SubsetScorer:
    """``f`` of batches of ``K'``-subsets from one Gram matrix of the whitened rows.

    ``log det(I + Z_S Z_S^T)`` for log det; for any other registered objective the downdate
    ``c(E P0 E^T) - c(E P_S E^T)`` with ``E P_S E^T = E P0 E^T - Y_S^T (I + Z_S Z_S^T)^-1 Y_S``
    (module docstring).
    """

    def __init__(
        self, Q0: FloatArray, G: FloatArray, K: int, objective: str, idx: np.ndarray | None
    ) -> None:
        N, m, d = G.shape
        L = cholesky_spd(Q0, "Q0")
        Z = np.linalg.solve(L, G.reshape(N * m, d).T).T  # rows of G L^-T, (N m, d)
        self.gram = Z @ Z.T  # (N m, N m)
        self.rows = np.arange(N * m).reshape(N, m)
        self.eye = np.eye(m * K)
        self.m, self.N = m, N
        self.objective = objective
        self.crit = get_objective(objective)
        if objective != "logdet":
            Et = np.eye(d) if idx is None else np.eye(d)[:, idx]  # E^T (d, p)
            Ye = np.linalg.solve(L, Et)  # L^-1 E^T
            self.Y = Z @ Ye  # rows of G P0 E^T, (N m, p)
            self.C0 = Ye.T @ Ye  # E P0 E^T

    def __call__(self, cands: np.ndarray) -> FloatArray:
        """``(B,)`` values of the subsets ``cands`` ``(B, K')``."""
        r = self.rows[cands].reshape(cands.shape[0], -1)
        M = self.eye[: r.shape[1], : r.shape[1]] + self.gram[r[:, :, None], r[:, None, :]]
        if self.objective == "logdet":
            return np.linalg.slogdet(M)[1]
        V = np.linalg.solve(np.linalg.cholesky(M), self.Y[r])  # C^-1 Y_S, (B, m K', p)
        return self.crit.downdate_gain(self.C0, V)  # c(E P0 E^T) - c(E P_S E^T)

    def singles(self) -> FloatArray:
        """``(N,)`` value of every candidate alone (the default warm start ranks them)."""
        if self.objective == "logdet":  # the original single-gain pass
            rows, m = self.rows, self.m
            return np.linalg.slogdet(
                self.eye[:m, :m] + self.gram[rows[:, :, None], rows[:, None, :]]
            )[1]
        return self(np.arange(self.N)[:, None])


def _neighbours(
    sel: np.ndarray, size: int, M: int, N: int, batched: bool, rng: np.random.Generator
) -> tuple[np.ndarray, bool]:
    """Subsets of ``V_size(sel)`` to evaluate, and whether they are the whole neighbourhood.

    When ``V_size`` has at most ``M`` members (and ``batched``) it is enumerated; otherwise
    ``M`` (batched) or 1 (sequential) draws exchange ``size`` selected for ``size`` unselected.
    """
    K = sel.size
    unsel = np.setdiff1d(np.arange(N), sel, assume_unique=True)
    exhaustive = batched and math.comb(K, size) * math.comb(N - K, size) <= M
    if exhaustive:
        pairs = itertools.product(
            itertools.combinations(range(K), size), itertools.combinations(unsel, size)
        )
        out_l, new_l = zip(*pairs, strict=True)
        out_pos, new = np.array(out_l, dtype=np.intp), np.array(new_l, dtype=np.intp)
    else:
        n_draw = M if batched else 1
        out_pos = np.argsort(rng.random((n_draw, K)), axis=1)[:, :size]  # selected to drop
        new = unsel[np.argsort(rng.random((n_draw, unsel.size)), axis=1)[:, :size]]
    cands = np.repeat(sel[None], out_pos.shape[0], axis=0)
    np.put_along_axis(cands, out_pos, new, axis=1)
    return cands, exhaustive


@small_blas
def vns(
    Q0: object,
    H: object,
    R: object,
    budget: int,
    **kwargs: object,
) -> Selection:
    """:func:`vns_whitened` on raw arrays (validated): ``Q0 (d, d)``, ``H (N, m, d)``, ``R``.

    Raises:
        TypeError: ``Q0``, ``H`` or ``R`` not real numeric (complex, bool, str, object), or as
            :func:`vns_whitened`.
        ValueError: see :func:`~selenv.core.information.as_candidates`, or as
            :func:`vns_whitened`.
    """
    Q0_a, G = as_candidates(Q0, H, R)
    return vns_whitened(Q0_a, G, budget, **kwargs)
