"""The batched core of ``FIMSelection``: the whitened gain state of ``B`` episodes at once.

One :class:`FIMBatchState` holds ``B`` selection episodes over pools of one config in arrays
with a leading batch axis; :class:`~selenv.families.fim.env.FIMSelectionEnv` is its ``B = 1``
case and :class:`~selenv.families.fim.vector.FIMSelectionVectorEnv` steps all ``B`` sub-envs
with it, so the per-step math exists once. It is the math of
:class:`~selenv.core.information.LogDetGainState` with ``track_whitened=True`` (and of
:class:`~selenv.core.objectives.CriterionGainState` for the other objectives), batched:

* information ``A_b = Q0 + sum_{k in S_b} G_k^T G_k`` (eq. 2) kept as ``L_b^-1``
  (``A_b = L_b L_b^T``);
* ``Z_b = G_b L_b^-T`` ``(N, m, d)``: every candidate whitened in the current information;
* pick ``j``: ``C = chol(I + Z_j^T Z_j)``, ``L'^-1 = C^-1 L^-1`` (a batched solve),
  ``Z' = G L'^-T``; the log-det gain is ``log det(I + Z_j^T Z_j) = 2 sum log diag C``
  (eq. 9 accumulated: ``f(S) = log det A_S - log det Q0``);
* ``"logdet"`` gains ``log det(I + S_k)``, ``S_k = Z_k Z_k^T`` (batched closed forms);
  other objectives (eqs. 6, 7, ``"det"``, user-registered): ``f = c(E P0 E^T) - c(E P E^T)``
  batched over ``B`` with ``P = L^-T L^-1``; their candidate gains are
  :func:`~selenv.core.objectives.criterion_gains` per sub-env (the registry's downdate takes
  one ``E P E^T``), i.e. a loop over the sub-envs that picked.

Shapes: ``B`` sub-envs, ``N`` candidates of ``m`` rows over ``d`` parameters.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.linalg import solve_triangular

from selenv.core.information import block_logdet_gains, information_matrix
from selenv.core.linalg import FloatArray, cholesky_spd
from selenv.core.objectives import (
    check_interest,
    check_objective,
    covariance_criterion,
    criterion_gains,
)

__all__ = ["FIMBatchState", "SubEnvGainState", "batched_features"]


def batched_features(times: FloatArray, sensor: np.ndarray) -> np.ndarray:
    """Static per-candidate features ``(K, N, 4)`` float32 of ``K`` pools.

    One-hot sensor code (``sensor`` ``(N,)``, camera / TOA / Doppler) and the candidate's
    time in the window scaled to [0, 1] (``times`` ``(K, N)``; a pool of one time gets 0).
    """
    K, N = times.shape
    tmin = times.min(axis=1, keepdims=True)
    span = times.max(axis=1, keepdims=True) - tmin
    span[span == 0.0] = 1.0
    feats = np.zeros((K, N, 4), np.float32)
    feats[:, np.arange(N), sensor] = 1.0
    feats[:, :, 3] = (times - tmin) / span
    return feats


class FIMBatchState:
    """Gain states of ``B`` selection episodes over pools ``G`` of one shape and prior.

    Args:
        num_envs: ``B``.
        Q0: ``(d, d)`` SPD prior information (eq. 3), shared by the sub-envs.
        shape: ``(N, m, d)`` of every pool.
        objective: a registered objective name (``"logdet"``: eq. 9).
        interest: indices ``(p,)`` of the parameters scored by a non-log-det objective
            (``None``: all).

    Attributes (batch arrays, updated in place):
        G, Z: ``(B, N, m, d)``; Linv: ``(B, d, d)``; S: ``(B, N, m, m)`` (log det only);
        gains: ``(B, N)``; selected: ``(B, N)`` bool; objective: ``(B,)`` ``f(S_b)``;
        order: ``(B, N)`` picks in order, the first ``count[b]`` valid.

    Raises:
        TypeError, ValueError: an unknown ``objective``, a bad ``interest`` or ``Q0`` not SPD.
    """

    def __init__(
        self,
        num_envs: int,
        Q0: FloatArray,
        shape: tuple[int, int, int],
        objective: str = "logdet",
        interest: Sequence[int] | np.ndarray | None = None,
    ) -> None:
        B, (N, m, d) = num_envs, shape
        self.num_envs, self.N, self.m, self.d = B, N, m, d
        self.objective_name = check_objective(objective)
        self.logdet = self.objective_name == "logdet"
        self.interest = check_interest(interest, d, self.objective_name)
        self.Q0 = Q0
        self.L0 = cholesky_spd(Q0, "Q0")  # Q0 = L0 L0^T
        self.Linv0 = solve_triangular(self.L0, np.eye(d), lower=True, check_finite=False)
        self.P0 = self.Linv0.T @ self.Linv0  # Q0^-1
        self._crit0 = (
            0.0
            if self.logdet
            else float(covariance_criterion(self.P0, self.objective_name, self.interest))
        )
        self._eye_d = np.eye(d)
        self.G = np.zeros((B, N, m, d))
        self.Z = np.zeros((B, N, m, d))
        self.Linv = np.broadcast_to(self.Linv0, (B, d, d)).copy()
        self.S: FloatArray | None = np.zeros((B, N, m, m)) if self.logdet else None
        self.gains = np.zeros((B, N))
        self.selected = np.zeros((B, N), dtype=bool)
        self.objective = np.zeros(B)
        self.order = np.zeros((B, N), dtype=np.intp)
        self.count = np.zeros(B, dtype=np.intp)

    # -- episodes --------------------------------------------------------------------------
    def start(self, idx: np.ndarray, G: FloatArray) -> None:
        """New episodes for sub-envs ``idx`` ``(k,)`` over pools ``G`` ``(k, N, m, d)``.

        ``Z = G L0^-T`` (one product for all ``k`` pools), ``L^-1 = L0^-1``, gains
        against the prior: log det ``log det(I + Z_k Z_k^T)`` or
        :func:`~selenv.core.objectives.criterion_gains` at ``P0 = Q0^-1``; nothing selected.
        """
        k, (N, m, d) = idx.size, (self.N, self.m, self.d)
        self.G[idx] = G
        W = np.matmul(G.reshape(k * N * m, d), self.Linv0.T)  # rows g L0^-T
        self.Z[idx] = W.reshape(k, N, m, d)
        self.Linv[idx] = self.Linv0
        if self.S is not None:
            S = _gram(W.reshape(k, N, m, d))  # S_k = G_k Q0^-1 G_k^T
            self.S[idx] = S
            self.gains[idx] = block_logdet_gains(S.reshape(k * N, m, m)).reshape(k, N)
        else:
            gains = criterion_gains(self.P0, G.reshape(k * N, m, d), self.objective_name,
                                    self.interest)  # fmt: skip
            self.gains[idx] = gains.reshape(k, N)
        self.selected[idx] = False
        self.objective[idx] = 0.0
        self.count[idx] = 0

    def add(self, idx: np.ndarray, picks: np.ndarray) -> FloatArray:
        """Sub-env ``idx[i]`` selects candidate ``picks[i]`` (unselected: not re-checked).

        The block update of the module docstring for all ``k`` sub-envs at once: one batched
        Cholesky ``(k, d, d)``, one batched solve for ``L'^-1``, one batched product for
        ``Z'``, the ``S`` entries by row-wise dots and the closed-form gains.

        Returns:
            ``(k,)`` the change of each sub-env's objective ``f`` (the step reward).
        """
        k, (N, m, d) = idx.size, (self.N, self.m, self.d)
        rows: np.ndarray | slice = slice(None) if k == self.num_envs else idx  # views if all
        before = self.objective[rows].copy()
        Zj = self.Z[idx, picks]  # (k, m, d)
        M = np.matmul(np.swapaxes(Zj, 1, 2), Zj) + self._eye_d  # I + Z_j^T Z_j
        C = _cholesky(M)
        Linv = np.linalg.solve(C, self.Linv[rows])  # L'^-1 = C^-1 L^-1
        self.Linv[rows] = Linv
        Linv_T = np.swapaxes(Linv, 1, 2)
        if k == self.num_envs:  # every sub-env: write Z' = G L'^-T in place
            np.matmul(self.G.reshape(k, N * m, d), Linv_T, out=self.Z.reshape(k, N * m, d))
            Z = self.Z
        else:
            Z = np.matmul(self.G[idx].reshape(k, N * m, d), Linv_T).reshape(k, N, m, d)
            self.Z[idx] = Z
        if self.S is not None:  # log det
            after = before + 2.0 * np.sum(np.log(np.diagonal(C, axis1=1, axis2=2)), axis=1)
            S = _gram(Z)
            self.S[rows] = S
            self.gains[rows] = block_logdet_gains(S.reshape(k * N, m, m)).reshape(k, N)
        else:
            P = np.matmul(Linv_T, Linv)  # P = L^-T L^-1, the CRLB
            crit = covariance_criterion(P, self.objective_name, self.interest)
            after = self._crit0 - crit
            G = self.G
            for i, b in enumerate(idx.tolist()):  # the registry's downdate takes one E P E^T
                self.gains[b] = criterion_gains(P[i], G[b], self.objective_name, self.interest)
        self.objective[idx] = after
        self.selected[idx, picks] = True
        self.order[idx, self.count[idx]] = picks
        self.count[idx] += 1
        gain: FloatArray = after - before
        return gain

    def view(self, b: int) -> SubEnvGainState:
        """Sub-env ``b``'s gain state (live view; the ``GainState`` interface)."""
        return SubEnvGainState(self, b)


def _gram(Z: FloatArray) -> FloatArray:
    """``S_k = Z_k Z_k^T`` ``(k, N, m, m)`` of ``Z`` ``(k, N, m, d)`` (unique entries by dots)."""
    k, N, m, _ = Z.shape
    S = np.empty((k, N, m, m))
    for a in range(m):
        for b in range(a, m):
            v = np.einsum("knd,knd->kn", Z[:, :, a], Z[:, :, b])
            S[:, :, a, b] = v
            S[:, :, b, a] = v
    return S


def _cholesky(M: FloatArray) -> FloatArray:
    """Batched lower Cholesky factor of ``(k, d, d)`` SPD matrices (``I + Z^T Z`` >= I).

    Raises:
        ValueError: a factor failed (NaN/inf in the state), naming the matrix.
    """
    try:
        C: FloatArray = np.linalg.cholesky(M).astype(np.float64, copy=False)
    except np.linalg.LinAlgError:
        return cholesky_spd(M, "I + Z_j^T Z_j")  # the canonical error
    return C


class SubEnvGainState:
    """The gain state of sub-env ``b`` of a :class:`FIMBatchState`, as a ``GainState``.

    The interface of :class:`~selenv.core.information.LogDetGainState` /
    :class:`~selenv.core.objectives.CriterionGainState` that envs and agents use: ``Q0``,
    ``G``, ``N``, ``m``, ``d``, ``selected``, ``order``, ``objective``, ``gains``, ``Z``,
    ``S`` (log det only), ``P``, ``information``, :meth:`gain_of`, :meth:`masked_gains`,
    :meth:`add`. Arrays are views of the batch (updated in place by its steps).
    """

    track_gains = True
    track_whitened = True

    def __init__(self, batch: FIMBatchState, b: int) -> None:
        self._batch, self._b = batch, b
        self.Q0, self.L0 = batch.Q0, batch.L0
        self.N, self.m, self.d = batch.N, batch.m, batch.d
        self.objective_name = batch.objective_name
        self.interest = batch.interest

    @property
    def G(self) -> FloatArray:
        """``(N, m, d)`` whitened candidates (read-only view)."""
        G = self._batch.G[self._b]
        G.flags.writeable = False
        return G

    @property
    def selected(self) -> np.ndarray:
        """``(N,)`` bool: the candidates selected so far."""
        out: np.ndarray = self._batch.selected[self._b]
        return out

    @property
    def order(self) -> list[int]:
        """Selected indices in the order they were picked."""
        b = self._b
        return [int(k) for k in self._batch.order[b, : self._batch.count[b]]]

    @property
    def objective(self) -> float:
        """``f(S)``: eq. (9) for log det, ``c(E P0 E^T) - c(E P E^T)`` otherwise."""
        return float(self._batch.objective[self._b])

    @property
    def gains(self) -> FloatArray:
        """``(N,)`` marginal gain of every candidate in the objective."""
        out: FloatArray = self._batch.gains[self._b]
        return out

    @property
    def Z(self) -> FloatArray:
        """``(N, m, d)`` ``G_k L^-T`` with ``A = L L^T``."""
        out: FloatArray = self._batch.Z[self._b]
        return out

    @property
    def S(self) -> FloatArray | None:
        """``(N, m, m)`` ``S_k = Z_k Z_k^T`` (log det only, else ``None``)."""
        S = self._batch.S
        return None if S is None else S[self._b]

    @property
    def P(self) -> FloatArray:
        """``A^-1`` ``(d, d)``: the CRLB of the current selection."""
        Linv = self._batch.Linv[self._b]
        out: FloatArray = Linv.T @ Linv
        return out

    @property
    def information(self) -> FloatArray:
        """Current FIM ``A`` of eq. (2), recomputed exactly from the selection."""
        return information_matrix(self.Q0, self.G, self.order)

    def gain_of(self, k: int) -> float:
        """Exact gain of one candidate in the objective, ``O(m d^2)``.

        Raises:
            TypeError: ``k`` not an int.
            ValueError: ``k`` out of range.
        """
        k = self._index(k, "k")
        Gk = self.G[k]
        if self._batch.logdet:
            return float(block_logdet_gains((Gk @ self.P @ Gk.T)[None])[0])
        gain = criterion_gains(self.P, self.G[k : k + 1], self.objective_name, self.interest)
        return float(gain[0])

    def masked_gains(self) -> FloatArray:
        """Gains with already-selected candidates set to ``-inf`` (for argmax)."""
        return np.where(self.selected, -np.inf, self.gains)

    def add(self, j: int) -> float:
        """Select candidate ``j``; return the change of ``objective``.

        Raises:
            TypeError: ``j`` not an int.
            ValueError: ``j`` out of range or already selected (the state is unchanged).
        """
        j = self._index(j, "j")
        if self.selected[j]:
            raise ValueError(f"candidate {j} is already selected")
        gain = self._batch.add(np.array([self._b]), np.array([j]))
        return float(gain[0])

    def _index(self, j: object, name: str) -> int:
        if isinstance(j, bool) or not isinstance(j, int | np.integer):
            raise TypeError(f"{name} must be an int candidate index, got {type(j).__name__}")
        if not 0 <= j < self.N:
            raise ValueError(f"candidate index must lie in [0, {self.N}), got {j}")
        return int(j)
