"""Fisher-information accumulation and log-det marginal gains.

Implements the objective of Kirchner et al. (2020), eq. (9)::

    f(S) = log det(Q0 + sum_{k in S} Q_k) - log det Q0,     Q_k = H_k^T R_k^-1 H_k  (eq. 2, 4)

and the state that makes greedy selection (their Algorithm 1) cheap.

Shape convention: a pool of ``N`` candidate measurements, each with at most ``m`` rows, over a
``d``-dimensional parameter. Jacobians ``H`` are ``(N, m, d)`` and noise covariances ``R`` are
``(N, m, m)``; candidates with fewer rows are zero-padded in ``H`` with identity in ``R`` (a
zero row adds no information, so padding is exact). Every candidate is whitened once,
``G_k = L_k^-1 H_k`` with ``R_k = L_k L_k^T``, so that ``Q_k = G_k^T G_k``.

Marginal gains (see ``shared/notes/selection_math.md``): with ``A`` the current information and
``P = A^-1``, the gain of candidate ``k`` is ``log det(I_m + S_k)``, ``S_k = G_k P G_k^T``.
Adding a row ``g`` is a rank-one update; with ``u = P g``, ``q = g^T u`` and ``c = G u``::

    S <- S - c c^T / (1 + q),   P <- P - u u^T / (1 + q),   f <- f + log(1 + q)

which costs ``O(N m d)`` per row instead of the ``O(N d^3)`` of recomputing every log det.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from selenv.core.linalg import (
    FloatArray,
    as_float_array,
    check_finite,
    check_shape,
    cholesky_small,
    cholesky_spd,
    inv_lower_small,
    logdet_spd,
    symmetrize,
    validate_spd,
)

__all__ = [
    "LogDetGainState",
    "as_candidates",
    "block_logdet_gains",
    "information_matrix",
    "logdet_objective",
    "naive_greedy_logdet",
    "validate_candidates",
    "whiten",
]


def whiten(H: FloatArray, R: FloatArray) -> FloatArray:
    """Whiten candidate Jacobians: ``G_k = L_k^-1 H_k`` with ``R_k = L_k L_k^T``.

    Args:
        H: ``(N, m, d)`` Jacobians ``d mu_k / d theta``.
        R: ``(N, m, m)`` noise covariances, or one ``(m, m)`` shared by all candidates.

    Returns:
        ``G`` of shape ``(N, m, d)`` with ``G_k^T G_k = H_k^T R_k^-1 H_k`` (eq. 4, Gaussian case).
    """
    N, m, _ = H.shape
    R_b = np.broadcast_to(R, (N, m, m)) if R.ndim == 2 else R
    L = np.linalg.cholesky(R_b)  # R_k = L_k L_k^T, batched
    return np.linalg.solve(L, H)  # G_k = L_k^-1 H_k (a solve, never inv)


def validate_candidates(
    H: object, R: object, d: int | None = None
) -> tuple[FloatArray, FloatArray]:
    """Validate and normalise a candidate pool to ``H (N, m, d)`` and ``R (N, m, m)``.

    Accepted forms: ``H (N, m, d)`` with ``R (N, m, m)`` or ``(m, m)``; or scalar candidates
    ``H (N, d)`` with ``R`` of shape ``(N,)`` (variances) or a scalar variance.

    Raises:
        TypeError: non-numeric input.
        ValueError: wrong shapes, NaN/inf, or an ``R_k`` that is not SPD (names the candidate).
    """
    H_a = check_finite(as_float_array(H, "H"), "H")
    R_a = check_finite(as_float_array(R, "R"), "R")
    if H_a.ndim == 2:
        N = H_a.shape[0]
        if R_a.ndim == 0:
            R_a = np.full(N, float(R_a))
        check_shape(R_a, (N,), "R (variances of scalar candidates)")
        if np.any(R_a <= 0):
            k = int(np.argmin(R_a))
            raise ValueError(f"R must hold positive variances, but R[{k}] = {R_a[k]:g}")
        return H_a[:, None, :], R_a[:, None, None]
    if H_a.ndim != 3:
        raise ValueError(f"H must have shape (N, d) or (N, m, d), got {H_a.shape}")
    N, m, dd = H_a.shape
    if d is not None and dd != d:
        raise ValueError(f"H must have shape (N, m, {d}) to match Q0, got {H_a.shape}")
    if R_a.ndim == 2:
        R_a = validate_spd(R_a, "R", m)
        return H_a, np.broadcast_to(R_a, (N, m, m)).copy()
    check_shape(R_a, (N, m, m), "R")
    try:
        R_a = validate_spd(R_a, "R", m, batch=True)
    except ValueError:
        for k in range(N):  # find the culprit for a precise message
            validate_spd(R_a[k], f"R[{k}]", m)
        raise
    return H_a, R_a


def as_candidates(Q0: object, H: object, R: object) -> tuple[FloatArray, FloatArray]:
    """Validate ``Q0`` (SPD, ``(d, d)``) and a candidate pool, and whiten the pool.

    Returns:
        ``(Q0, G)`` with ``Q0`` float64 ``(d, d)`` and ``G`` ``(N, m, d)``.
    """
    Q0_a = validate_spd(Q0, "Q0")
    H_a, R_a = validate_candidates(H, R, Q0_a.shape[0])
    if H_a.shape[2] != Q0_a.shape[0]:
        raise ValueError(
            f"H must have {Q0_a.shape[0]} columns to match Q0 {Q0_a.shape}, got {H_a.shape}"
        )
    return Q0_a, whiten(H_a, R_a)


def _indices(selected: Iterable[int] | FloatArray | None, N: int) -> np.ndarray:
    if selected is None:
        return np.zeros(0, dtype=np.intp)
    idx = np.asarray(list(selected) if not isinstance(selected, np.ndarray) else selected)
    if idx.dtype == bool:
        check_shape(idx, (N,), "selected (boolean mask)")
        return np.flatnonzero(idx)
    idx = idx.astype(np.intp, copy=False).ravel()
    if idx.size and (idx.min() < 0 or idx.max() >= N):
        raise ValueError(f"selected indices must lie in [0, {N}), got {idx.min()}..{idx.max()}")
    return idx


def information_matrix(
    Q0: FloatArray, G: FloatArray, selected: Iterable[int] | FloatArray | None = None
) -> FloatArray:
    """FIM of a selection, eq. (2): ``Q0 + sum_{k in S} G_k^T G_k``, shape ``(d, d)``."""
    idx = _indices(selected, G.shape[0])
    Gs = G[idx].reshape(-1, G.shape[2])
    return symmetrize(Q0 + Gs.T @ Gs)


def logdet_objective(
    Q0: FloatArray, G: FloatArray, selected: Iterable[int] | FloatArray | None
) -> float:
    """Objective ``f(S)`` of eq. (9) by direct Cholesky log-dets (the independent reference)."""
    return float(logdet_spd(information_matrix(Q0, G, selected), "FIM")) - float(
        logdet_spd(Q0, "Q0")
    )


def block_logdet_gains(S: FloatArray) -> FloatArray:
    """``log det(I_m + S_k)`` for a batch ``S`` of PSD ``(N, m, m)`` matrices, shape ``(N,)``.

    Closed forms for ``m = 1`` (``log1p``) and ``m = 2``; batched Cholesky otherwise.
    """
    m = S.shape[-1]
    if m == 1:
        return np.log1p(S[:, 0, 0])
    if m == 2:
        a, b, c = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
        return np.log1p(a + c + a * c - b * b)  # det(I + S) - 1 = a + c + ac - b^2
    L = np.linalg.cholesky(S + np.eye(m))
    return 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)


class LogDetGainState:
    """Marginal log-det gains of every candidate given the measurements selected so far.

    Maintains, for the information ``A = Q0 + sum_{k in S} G_k^T G_k``:

    * ``P`` ``(d, d)``: ``A^-1`` (the CRLB of the selection), rank-one updated (or, when
      ``track_whitened``, kept as ``L^-1`` with ``P = L^-T L^-1``);
    * ``S`` ``(N, m, m)``: ``G_k P G_k^T`` and ``gains`` ``(N,)``: ``log det(I + S_k)``
      (only when ``track_gains``; lazy greedy turns it off and calls :meth:`gain_of`);
    * ``Z`` ``(N, m, d)``: ``G_k L^-T`` with ``A = L L^T``, each candidate whitened in the
      current information metric (only when ``track_whitened``; ``Z_k Z_k^T = S_k``);
    * ``objective``: ``f(S)`` of eq. (9), accumulated exactly as ``sum log(1 + q)``.

    Args:
        Q0: ``(d, d)`` SPD prior information (validated).
        G: ``(N, m, d)`` whitened candidates (see :func:`whiten`).
        track_gains: keep ``S`` and ``gains`` for all candidates (``O(N m d)`` per row added).
        track_whitened: keep ``Z`` (``O(N m d^2)`` per pick).
    """

    def __init__(
        self,
        Q0: FloatArray,
        G: FloatArray,
        *,
        track_gains: bool = True,
        track_whitened: bool = False,
    ) -> None:
        self.Q0 = validate_spd(Q0, "Q0")
        G = np.asarray(G, dtype=np.float64)
        check_shape(G, (None, None, self.Q0.shape[0]), "G")
        self.G = G
        self.N, self.m, self.d = G.shape
        self._Gflat = G.reshape(self.N * self.m, self.d)
        L0 = cholesky_spd(self.Q0, "Q0")
        # rank-one mode keeps P = A^-1; whitened mode keeps L^-1 (A = L L^T) and P = L^-T L^-1
        self._P: FloatArray | None = None
        self._Linv: FloatArray | None = None
        if track_whitened:
            self._Linv = solve_triangular(L0, np.eye(self.d), lower=True)
        else:
            self._P = cho_solve((L0, True), np.eye(self.d))  # P = Q0^-1
        self.selected = np.zeros(self.N, dtype=bool)
        self.order: list[int] = []
        self.objective = 0.0
        self.track_gains = track_gains
        self.track_whitened = track_whitened
        W = solve_triangular(L0, self._Gflat.T, lower=True).T  # rows g L0^-T
        self.Z: FloatArray | None = W.reshape(G.shape) if track_whitened else None
        self.S: FloatArray | None = None
        self.gains: FloatArray | None = None
        if track_gains:
            Wb = W.reshape(G.shape)
            self.S = np.einsum("kid,kjd->kij", Wb, Wb)  # S_k = G_k Q0^-1 G_k^T
            self.gains = block_logdet_gains(self.S)

    @property
    def P(self) -> FloatArray:
        """``A^-1`` ``(d, d)``: the CRLB of the current selection."""
        if self._P is not None:
            return self._P
        assert self._Linv is not None
        return self._Linv.T @ self._Linv

    @property
    def information(self) -> FloatArray:
        """Current FIM ``A`` of eq. (2), recomputed exactly from the selection."""
        return information_matrix(self.Q0, self.G, self.order)

    def gain_of(self, k: int) -> float:
        """Exact gain ``log det(I + G_k P G_k^T)`` of one candidate, ``O(m d^2)``."""
        Gk = self.G[k]
        return float(block_logdet_gains((Gk @ self.P @ Gk.T)[None])[0])

    def masked_gains(self) -> FloatArray:
        """Gains with already-selected candidates set to ``-inf`` (for argmax)."""
        if self.gains is None:
            raise ValueError("masked_gains needs track_gains=True")
        return np.where(self.selected, -np.inf, self.gains)

    def add(self, j: int) -> float:
        """Select candidate ``j`` (one rank-one update per non-zero row); return its gain.

        Raises:
            ValueError: ``j`` out of range or already selected.
        """
        if not 0 <= j < self.N:
            raise ValueError(f"candidate index must lie in [0, {self.N}), got {j}")
        if self.selected[j]:
            raise ValueError(f"candidate {j} is already selected")
        before = self.objective
        if self.Z is not None:
            self._add_whitened(j)
        else:
            self._add_rank_one(self.G[j])
        self.selected[j] = True
        self.order.append(j)
        return self.objective - before

    def _add_rank_one(self, Gj: FloatArray) -> None:
        """One Sherman-Morrison update of ``P`` (and ``S``) per non-zero row of ``G_j``."""
        assert self._P is not None
        pairs = [(a, b) for a in range(self.m) for b in range(a, self.m)]
        for g in Gj:
            if not np.any(g):
                continue  # zero padding row: no information
            u = self._P @ g  # u = P g
            q = float(g @ u)  # q = g^T P g
            self._P = symmetrize(self._P - np.outer(u, u) / (1.0 + q))  # Sherman-Morrison
            self.objective += float(np.log1p(q))  # matrix determinant lemma
            if self.S is not None:
                c = (self._Gflat @ u).reshape(self.N, self.m)  # c = G u
                c *= 1.0 / np.sqrt(1.0 + q)
                for a, b in pairs:  # S <- S - c c^T / (1 + q), unique entries only
                    v = c[:, a] * c[:, b]
                    self.S[:, a, b] -= v
                    if a != b:
                        self.S[:, b, a] -= v
        if self.S is not None:
            self.gains = block_logdet_gains(self.S)

    def _add_whitened(self, j: int) -> None:
        """Block update through the whitened rows: ``Z <- Z C^-T``, then ``S = Z Z^T``.

        With ``A = L L^T`` and ``Z_j = G_j L^-T``: ``A + G_j^T G_j = L (I + Z_j^T Z_j) L^T``,
        so ``L' = L C`` with ``C = chol(I + Z_j^T Z_j)`` (d x d), ``Z' = Z C^-T``,
        ``L'^-1 = C^-1 L^-1`` and the gain is ``log det(I + Z_j^T Z_j) = 2 sum log diag C``.
        """
        assert self.Z is not None and self._Linv is not None
        Zj = self.Z[j]
        C = cholesky_small(np.eye(self.d) + Zj.T @ Zj, "I + Z_j^T Z_j")
        self.objective += float(2.0 * np.sum(np.log(np.diag(C))))  # log det(I + S_j)
        Cinv = inv_lower_small(C)
        self._Linv = Cinv @ self._Linv  # L'^-1 = C^-1 L^-1
        self.Z = (self.Z.reshape(self.N * self.m, self.d) @ Cinv.T).reshape(self.G.shape)
        if self.S is not None:
            for a in range(self.m):  # S_k = Z_k Z_k^T, unique entries by row-wise dots
                for b in range(a, self.m):
                    v = np.einsum("kd,kd->k", self.Z[:, a], self.Z[:, b])
                    self.S[:, a, b] = v
                    self.S[:, b, a] = v
            self.gains = block_logdet_gains(self.S)


def naive_greedy_logdet(Q0: FloatArray, G: FloatArray, budget: int) -> list[int]:
    """Reference greedy (Algorithm 1) with one Cholesky log det per candidate per step.

    ``O(K N d^3)``: kept only as the independent check and the speed baseline.
    """
    N = G.shape[0]
    A = Q0.copy()
    chosen: list[int] = []
    Qk = np.einsum("kmi,kmj->kij", G, G)  # Q_k = G_k^T G_k
    for _ in range(budget):
        best, best_val = -1, -np.inf
        for k in range(N):
            if k in chosen:
                continue
            val = float(logdet_spd(A + Qk[k]))
            if val > best_val:
                best, best_val = k, val
        chosen.append(best)
        A = A + Qk[best]
    return chosen
