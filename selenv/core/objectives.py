"""A- and E-optimal selection objectives: trace and largest eigenvalue of the CRLB.

Kirchner et al. (2020) name two alternatives to the log-det criterion eq. (5): the trace of the
inverse FIM, eq. (6) (A-optimal: the achievable mean-square error ``E|theta - theta_hat|^2``),
and its largest eigenvalue, eq. (7) (E-optimal: the longest axis of the error ellipsoid). As
gains to maximise (higher is better, ``f(empty) = 0``)::

    trace:    f(S) = tr(E P0 E^T) - tr(E P_S E^T)
    max_eig:  f(S) = lambda_max(E P0 E^T) - lambda_max(E P_S E^T)

with ``P_S = (Q0 + sum_{k in S} G_k^T G_k)^-1`` (eq. 2, whitened candidates as in
:mod:`selenv.core.information`), ``P0 = Q0^-1`` and ``E`` ``(p, d)`` the rows of the identity
that select the ``p`` parameters of interest (``interest``; default: all ``d``). Both are
monotone (``P_S`` shrinks in the Loewner order as ``S`` grows) but, unlike log det, not
submodular in general (the paper, after eq. 7), so greedy carries no ``1 - 1/e`` guarantee and
lazy greedy is not valid.

Marginal gains. With ``P`` the current CRLB and a candidate ``G_k`` ``(m, d)``, Woodbury gives
``P_k = P - P G_k^T (I_m + S_k)^-1 G_k P`` with ``S_k = G_k P G_k^T``. With ``W_k = G_k P E^T``
``(m, p)`` and ``I + S_k = C_k C_k^T`` (Cholesky), ``V_k = C_k^-1 W_k``::

    trace gain    = tr(W_k^T (I + S_k)^-1 W_k) = ||V_k||_F^2
    max_eig gain  = lambda_max(E P E^T) - lambda_max(E P E^T - V_k^T V_k)

both batched over every candidate; ``P`` itself is kept by the rank-one / block updates of
:class:`~selenv.core.information.LogDetGainState`.

The objectives themselves are :class:`~selenv.core.objective_registry.Objective` records in one
registry (:mod:`selenv.core.objective_registry`): every function here takes a registered name,
so an objective the user registers (``register_objective``) works in the greedy, swap,
brute-force and VNS solvers through the generic downdate ``c(M0) - c(M0 - V_k^T V_k)``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from selenv.core.information import (
    LogDetGainState,
    information_matrix,
    logdet_objective,
)
from selenv.core.linalg import FloatArray, cholesky_spd
from selenv.core.objective_registry import (
    Objective,
    check_objective,
    get_objective,
    objective_names,
    register_objective,
)

__all__ = [
    "OBJECTIVES",
    "CriterionGainState",
    "GainState",
    "Objective",
    "check_interest",
    "check_objective",
    "covariance_criterion",
    "criterion_gains",
    "get_objective",
    "make_gain_state",
    "objective_names",
    "objective_value",
    "register_objective",
    "subset_criteria",
    "swap_criteria",
]

#: the FIM-selection objectives shipped with selenv: D-optimal (eq. 5/9), A-optimal (eq. 6),
#: E-optimal (eq. 7). Every registered objective is accepted (:func:`objective_names`), including
#: ``"det"`` and the user's own (:func:`register_objective`).
OBJECTIVES: tuple[str, ...] = ("logdet", "trace", "max_eig")


def check_interest(interest: object, d: int, objective: str = "trace") -> np.ndarray | None:
    """Indices ``(p,)`` of the parameters of interest (``E`` selects them), or ``None`` = all.

    Raises:
        TypeError: ``interest`` not a sequence of int indices (bools and floats refused).
        ValueError: empty, repeated or out of ``[0, d)``; or given with ``objective="logdet"``
            (log det is over the whole parameter).
    """
    if interest is None:
        return None
    if objective == "logdet":
        raise ValueError(
            "interest applies to objectives other than 'logdet' (e.g. 'trace', 'max_eig'); "
            "objective='logdet' scores the whole parameter (pass interest=None)"
        )
    if isinstance(interest, str) or not isinstance(interest, Sequence | np.ndarray):
        raise TypeError(f"interest must be a sequence of int indices, got {interest!r}")
    arr = np.asarray(interest)
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"interest must be a non-empty 1-D sequence of indices, got {interest!r}")
    if arr.dtype == bool or arr.dtype.kind not in "iu":
        raise TypeError(f"interest must hold int indices, got {interest!r}")
    idx = arr.astype(np.intp)
    if idx.min() < 0 or idx.max() >= d or np.unique(idx).size != idx.size:
        raise ValueError(f"interest must hold distinct indices in [0, {d}), got {interest!r}")
    return idx


def _block(P: FloatArray, interest: np.ndarray | None) -> FloatArray:
    """``E P E^T`` ``(..., p, p)`` of a batch of covariances ``P`` ``(..., d, d)``."""
    return P if interest is None else P[..., interest[:, None], interest[None, :]]


def covariance_criterion(
    P: FloatArray, objective: str, interest: np.ndarray | None = None
) -> FloatArray:
    """``c(E P E^T)`` of the registered objective: ``(..., d, d) -> (...)`` (lower is better).

    ``"trace"``: eq. 6; ``"max_eig"``: eq. 7; ``"logdet"``: eq. 5 on the block.

    Raises:
        TypeError, ValueError: ``objective`` not a registered name.
    """
    return get_objective(objective).value(_block(P, interest))


def _inverse_block(A: FloatArray, interest: np.ndarray | None) -> FloatArray:
    """``E A^-1 E^T`` ``(..., p, p)`` of SPD ``A`` ``(..., d, d)``: ``Y^T Y``, ``Y = L^-1 E^T``."""
    L = cholesky_spd(A, "FIM")  # A = L L^T
    d = A.shape[-1]
    Et = np.eye(d) if interest is None else np.eye(d)[:, interest]  # E^T (d, p)
    Y = np.linalg.solve(L, np.broadcast_to(Et, (*A.shape[:-2], *Et.shape)))
    return np.swapaxes(Y, -1, -2) @ Y


def objective_value(
    Q0: FloatArray,
    G: FloatArray,
    selected: Iterable[int] | FloatArray | None,
    objective: str = "logdet",
    interest: Sequence[int] | np.ndarray | None = None,
) -> float:
    """``f(S)`` of the chosen objective by direct Cholesky solves (the independent reference).

    ``"logdet"`` is :func:`~selenv.core.information.logdet_objective` (eq. 9); every other
    registered objective (``"trace"``, ``"max_eig"``: eqs. 6, 7 as gains) is
    ``c(E Q0^-1 E^T) - c(E FIM(S)^-1 E^T)``.

    Raises:
        TypeError, ValueError: as :func:`~selenv.core.information.information_matrix`, an
            unknown ``objective`` or a bad ``interest`` (see :func:`check_interest`).
    """
    objective = check_objective(objective)
    if objective == "logdet":
        check_interest(interest, 0, objective)
        return logdet_objective(Q0, G, selected)
    A = information_matrix(Q0, G, selected)
    idx = check_interest(interest, A.shape[0], objective)
    crit = covariance_criterion(
        np.stack([_inverse_block(Q0, idx), _inverse_block(A, idx)]), objective
    )
    return float(crit[0] - crit[1])


def criterion_gains(
    P: FloatArray, G: FloatArray, objective: str, interest: np.ndarray | None = None
) -> FloatArray:
    """Marginal gains ``(N,)`` of every candidate ``G`` ``(N, m, d)`` given the CRLB ``P`` (d, d).

    The Woodbury downdate of the module docstring, batched (no loop over candidates), for any
    registered objective (:meth:`~selenv.core.objective_registry.Objective.downdate_gain`).
    Gains are exactly ``>= 0`` (monotonicity); rounding below 0 is set to 0.

    Raises:
        TypeError, ValueError: ``objective`` not a registered name.
    """
    obj = get_objective(objective)
    N, m, d = G.shape
    B = (G.reshape(N * m, d) @ P).reshape(N, m, d)  # G_k P
    S = np.einsum("kad,kbd->kab", B, G)  # S_k = G_k P G_k^T (m, m)
    W = B if interest is None else B[:, :, interest]  # W_k = G_k P E^T (m, p)
    C = np.linalg.cholesky(S + np.eye(m))  # I + S_k = C_k C_k^T
    V = np.linalg.solve(C, W)  # C_k^-1 W_k
    return np.maximum(obj.downdate_gain(_block(P, interest), V), 0.0)  # c(M0) - c(M0 - V^T V)


class CriterionGainState:
    """Marginal gains of every candidate in a registered objective other than log det.

    The counterpart of :class:`~selenv.core.information.LogDetGainState` (same attributes, so
    envs and agents can hold either): ``P`` (and ``Z``) are kept by an inner log-det state's
    rank-one / block updates; ``gains`` ``(N,)`` are recomputed after every pick by
    :func:`criterion_gains` (``O(N m d^2)``); ``objective`` is ``f(S)`` of the module
    docstring, ``crit(E P0 E^T) - crit(E P E^T)`` on the current ``P``.

    Args:
        Q0: ``(d, d)`` SPD prior information.
        G: ``(N, m, d)`` whitened candidates.
        objective: a registered objective other than ``"logdet"``: ``"trace"`` (eq. 6),
            ``"max_eig"`` (eq. 7), ``"det"`` or the user's own.
        interest: indices of the parameters of interest (default all).
        track_gains: keep ``gains`` for all candidates.
        track_whitened: keep ``Z`` (as in :class:`LogDetGainState`).

    Raises:
        TypeError, ValueError: as :class:`LogDetGainState`, an ``objective`` that is not a
            registered name or is ``"logdet"``, or a bad ``interest``.
    """

    def __init__(
        self,
        Q0: FloatArray,
        G: FloatArray,
        objective: str = "trace",
        *,
        interest: Sequence[int] | np.ndarray | None = None,
        track_gains: bool = True,
        track_whitened: bool = False,
    ) -> None:
        if check_objective(objective) == "logdet":
            raise ValueError("objective='logdet' is LogDetGainState; use make_gain_state")
        self.objective_name = objective
        self._inner = LogDetGainState(Q0, G, track_gains=False, track_whitened=track_whitened)
        self.Q0, self.G = self._inner.Q0, self._inner.G
        self.N, self.m, self.d = self.G.shape
        self.interest = check_interest(interest, self.d, objective)
        self.track_gains = track_gains
        self.track_whitened = track_whitened
        self._crit0 = float(covariance_criterion(self._inner.P, objective, self.interest))
        self.objective = 0.0
        self.gains: FloatArray | None = self._gains() if track_gains else None

    @property
    def selected(self) -> np.ndarray:
        """``(N,)`` bool: the candidates selected so far."""
        return self._inner.selected

    @property
    def order(self) -> list[int]:
        """Selected indices in the order they were picked."""
        return self._inner.order

    @property
    def P(self) -> FloatArray:
        """``A^-1`` ``(d, d)``: the CRLB of the current selection."""
        return self._inner.P

    @property
    def Z(self) -> FloatArray | None:
        """``(N, m, d)`` ``G_k L^-T`` with ``A = L L^T`` (only when ``track_whitened``)."""
        return self._inner.Z

    @property
    def information(self) -> FloatArray:
        """Current FIM ``A`` of eq. (2), recomputed exactly from the selection."""
        return self._inner.information

    def _gains(self) -> FloatArray:
        return criterion_gains(self.P, self.G, self.objective_name, self.interest)

    def gain_of(self, k: int) -> float:
        """Exact gain of one candidate (``O(m d^2)``).

        Raises:
            TypeError: ``k`` not an int.
            ValueError: ``k`` out of range.
        """
        k = self._inner._index(k, "k")
        return float(
            criterion_gains(self.P, self.G[k : k + 1], self.objective_name, self.interest)[0]
        )

    def masked_gains(self) -> FloatArray:
        """Gains with already-selected candidates set to ``-inf`` (for argmax)."""
        if self.gains is None:
            raise ValueError("masked_gains needs track_gains=True")
        return np.where(self.selected, -np.inf, self.gains)

    def add(self, j: int) -> float:
        """Select candidate ``j``; return the change of ``objective``.

        Raises:
            TypeError: ``j`` not an int.
            ValueError: ``j`` out of range or already selected (the state is unchanged).
        """
        self._inner.add(j)
        before = self.objective
        crit = float(covariance_criterion(self.P, self.objective_name, self.interest))
        self.objective = self._crit0 - crit
        if self.track_gains:
            self.gains = self._gains()
        return self.objective - before


#: what an env or agent may hold as its gain state
GainState = LogDetGainState | CriterionGainState


def make_gain_state(
    Q0: FloatArray,
    G: FloatArray,
    objective: str = "logdet",
    *,
    interest: Sequence[int] | np.ndarray | None = None,
    track_gains: bool = True,
    track_whitened: bool = False,
) -> GainState:
    """:class:`LogDetGainState` for ``"logdet"`` (unchanged), else :class:`CriterionGainState`.

    Raises:
        TypeError, ValueError: as the two classes; ``objective`` not in :data:`OBJECTIVES`.
    """
    if check_objective(objective) == "logdet":
        check_interest(interest, 0, objective)
        return LogDetGainState(Q0, G, track_gains=track_gains, track_whitened=track_whitened)
    return CriterionGainState(
        Q0,
        G,
        objective,
        interest=interest,
        track_gains=track_gains,
        track_whitened=track_whitened,
    )


def subset_criteria(
    Q0: FloatArray,
    Qk: FloatArray,
    combos: np.ndarray,
    objective: str,
    interest: np.ndarray | None = None,
) -> FloatArray:
    """``crit(E A_S^-1 E^T)`` ``(C,)`` of every subset ``combos`` ``(C, B)`` (lower is better).

    ``A_S = Q0 + sum_{k in S} Q_k`` (eq. 2) with ``Qk`` ``(N, d, d)``; batched Cholesky.
    """
    A = Q0 + Qk[combos].sum(axis=1)  # (C, d, d)
    return covariance_criterion(_inverse_block(A, interest), objective)


def swap_criteria(
    Q0: FloatArray,
    G: FloatArray,
    sel: np.ndarray,
    uns: np.ndarray,
    objective: str,
    interest: np.ndarray | None = None,
    *,
    chunk: int = 4096,
) -> FloatArray:
    """``crit`` after swapping selected ``i`` for unselected ``j``: ``(K, U)`` (lower is better).

    ``A_ij = A - Q_i + Q_j`` for every pair, batched in chunks of ``chunk`` pairs (``A_ij >=
    Q0 > 0``, so every Cholesky exists).
    """
    A = information_matrix(Q0, G, sel)
    Qi = np.einsum("kmi,kmj->kij", G[sel], G[sel])
    Qj = np.einsum("kmi,kmj->kij", G[uns], G[uns])
    pairs = np.stack(np.meshgrid(np.arange(sel.size), np.arange(uns.size), indexing="ij"), -1)
    pairs = pairs.reshape(-1, 2)
    out = np.empty(pairs.shape[0])
    for s in range(0, pairs.shape[0], chunk):
        p = pairs[s : s + chunk]
        Aij = A[None] - Qi[p[:, 0]] + Qj[p[:, 1]]
        out[s : s + chunk] = covariance_criterion(
            _inverse_block(0.5 * (Aij + np.swapaxes(Aij, -1, -2)), interest), objective
        )
    return out.reshape(sel.size, uns.size)
