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
* pick ``j``: ``C = chol(I + Z_j^T Z_j)`` as ``m`` rank-one factors whose inverses are closed
  forms (:func:`_inverse_factor`), ``L'^-1 = C^-1 L^-1`` (one stacked ``(d, d)`` product),
  ``Z' = G L'^-T`` (one stacked BLAS product); the log-det gain is
  ``log det(I + Z_j^T Z_j) = sum_a log(1 + |w_a|^2)`` (eq. 9 accumulated:
  ``f(S) = log det A_S - log det Q0``);
* ``"logdet"`` gains ``log det(I + S_k)``, ``S_k = Z_k Z_k^T`` (:func:`_gram`: long
  elementwise products in a parameter-major copy of ``Z``, closed forms for ``m <= 2``);
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
        G, Z: ``(B, N, m, d)``; Linv: ``(B, d, d)``; S: ``(B, N, m, m)`` (log det only, a view
        of the gram's layout); gains: ``(B, N)``; selected: ``(B, N)`` bool; objective:
        ``(B,)`` ``f(S_b)``; order: ``(B, N)`` picks in order, the first ``count[b]`` valid.

    Layout: besides ``G`` the state keeps its transpose ``(B, d, m, N)`` (parameter axis
    first); ``Z^T = L^-1 G^T`` in that layout, a scratch array of :data:`_CHUNK` sub-envs at a
    time, makes the gram ``S_k = Z_k Z_k^T`` a few long elementwise products (:func:`_gram`)
    instead of ``B N`` tiny ones; ``Z`` (the observation's ``whitened``) and ``Z^T`` are each
    one stacked BLAS product per step.

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
        self.G = np.zeros((B, N, m, d))
        self.Z = np.zeros((B, N, m, d))
        self._GT = np.zeros((B, d, m, N)) if self.logdet else None  # G_b^T, parameter-major
        #: scratch ``Z_b^T`` of :data:`_CHUNK` sub-envs at a time (the gram's input)
        self._ZT = np.zeros((min(B, _CHUNK), d, m, N)) if self.logdet else None
        self.Linv = np.broadcast_to(self.Linv0, (B, d, d)).copy()
        self._ST = np.zeros((B, m, m, N)) if self.logdet else None  # S, candidate axis last
        self.gains = np.zeros((B, N))
        self.selected = np.zeros((B, N), dtype=bool)
        self.objective = np.zeros(B)
        self.order = np.zeros((B, N), dtype=np.intp)
        self.count = np.zeros(B, dtype=np.intp)

    @property
    def S(self) -> FloatArray | None:
        """``(B, N, m, m)`` ``S_k = Z_k Z_k^T`` (log det only, else ``None``; a live view)."""
        return None if self._ST is None else self._ST.transpose(0, 3, 1, 2)

    # -- episodes --------------------------------------------------------------------------
    def start(self, idx: np.ndarray, G: FloatArray) -> None:
        """New episodes for sub-envs ``idx`` ``(k,)`` (sorted) over pools ``G`` ``(k, N, m, d)``.

        ``Z = G L0^-T``, ``L^-1 = L0^-1``, gains against the prior: log det
        ``log det(I + Z_k Z_k^T)`` or :func:`~selenv.core.objectives.criterion_gains` at
        ``P0 = Q0^-1``; nothing selected. The products are those of :meth:`add` (same stacked
        shapes), so a sub-env that does not pick keeps its values bit for bit.
        """
        k = idx.size
        rows: np.ndarray | slice = slice(None) if k == self.num_envs else idx
        self.G[rows] = G
        GT = None
        if self._GT is not None:
            GT = np.ascontiguousarray(G.transpose(0, 3, 2, 1))  # (k, d, m, N)
            self._GT[rows] = GT
        Linv = np.broadcast_to(self.Linv0, (k, self.d, self.d)).copy()
        self.Linv[rows] = Linv
        self._refresh(rows, G, GT, Linv)
        if not self.logdet:
            gains = criterion_gains(self.P0, G.reshape(k * self.N, self.m, self.d),
                                    self.objective_name, self.interest)  # fmt: skip
            self.gains[rows] = gains.reshape(k, self.N)
        self.selected[rows] = False
        self.objective[rows] = 0.0
        self.count[rows] = 0

    def add(self, idx: np.ndarray, picks: np.ndarray) -> FloatArray:
        """Sub-env ``idx[i]`` (sorted) selects candidate ``picks[i]`` (unselected: not re-checked).

        The block update of the module docstring for all ``k`` sub-envs at once:
        ``C^-1`` of ``C C^T = I + Z_j^T Z_j`` in closed form (:func:`_inverse_factor`, ``m``
        rank-one factors), ``L'^-1 = C^-1 L^-1`` (one stacked ``(k, d, d)`` product), then
        ``Z' = G L'^-T``, ``S'`` and the closed-form gains (:meth:`_refresh`; over all ``B``
        sub-envs when at least half pick: a sub-env whose ``L^-1`` did not change gets its
        values again, bit for bit, and no gather or scatter of the pools is needed).

        Returns:
            ``(k,)`` the change of each sub-env's objective ``f`` (the step reward).
        """
        k, B = idx.size, self.num_envs
        before = self.objective[idx]
        Cinv, logdet = _inverse_factor(self.Z[idx, picks])  # (k, d, d), log det(I + Zj^T Zj)
        Linv = np.matmul(Cinv, self.Linv[idx])  # L'^-1 = C^-1 L^-1
        self.Linv[idx] = Linv
        if 2 * k >= B:
            self._refresh(slice(None), self.G, self._GT, self.Linv)
        else:
            GT = None if self._GT is None else self._GT[idx]
            self._refresh(idx, self.G[idx], GT, Linv)
        if self.logdet:
            after = before + logdet  # eq. (9): log det A' = log det A + log det(I + Z_j^T Z_j)
        else:
            P = np.matmul(np.swapaxes(Linv, 1, 2), Linv)  # P = L^-T L^-1, the CRLB
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

    def _refresh(
        self, rows: np.ndarray | slice, G: FloatArray, GT: FloatArray | None, Linv: FloatArray
    ) -> None:
        """``Z = G L^-T`` of the sub-envs ``rows`` (with their ``G``, ``G^T``, ``L^-1``).

        One stacked BLAS product ``(k, N m, d) @ (k, d, d)`` for ``Z``; for log det also
        ``Z^T = L^-1 G^T`` ``(c, d, d) @ (c, d, m N)`` into a scratch array, :data:`_CHUNK`
        sub-envs at a time, and the gram ``S`` and the gains from it while it is in the CPU
        caches (the non-log-det gains are the caller's). In place when ``rows`` is every
        sub-env.
        """
        k, (N, m, d) = Linv.shape[0], (self.N, self.m, self.d)
        everyone = isinstance(rows, slice)
        LinvT = np.ascontiguousarray(np.swapaxes(Linv, 1, 2))
        if everyone:
            np.matmul(G.reshape(k, N * m, d), LinvT, out=self.Z.reshape(k, N * m, d))
        else:
            self.Z[rows] = np.matmul(G.reshape(k, N * m, d), LinvT).reshape(k, N, m, d)
        if GT is None or self._ZT is None or self._ST is None:  # not log det
            return
        if everyone:
            ST, gains = self._ST, self.gains
        else:
            ST, gains = np.empty((k, m, m, N)), np.empty((k, N))
        c = self._ZT.shape[0]
        for lo in range(0, k, c):
            hi = min(lo + c, k)
            ZT = self._ZT[: hi - lo]
            np.matmul(Linv[lo:hi], GT[lo:hi].reshape(hi - lo, d, m * N),
                      out=ZT.reshape(hi - lo, d, m * N))  # fmt: skip
            _gram(ZT, ST[lo:hi], gains[lo:hi])
        if not everyone:
            self._ST[rows] = ST
            self.gains[rows] = gains

    def view(self, b: int) -> SubEnvGainState:
        """Sub-env ``b``'s gain state (live view; the ``GainState`` interface)."""
        return SubEnvGainState(self, b)


#: sub-envs per pass of the gram (their scratch ``Z^T`` stays in the CPU caches)
_CHUNK = 64


def _gram(ZT: FloatArray, ST: FloatArray, gains: FloatArray) -> None:
    """``S_k = Z_k Z_k^T`` into ``ST`` ``(k, m, m, N)`` and ``log det(I + S_k)`` into ``gains``.

    ``ZT`` ``(k, d, m, N)``: ``S[a, c] = sum_i Z[i, a] Z[i, c]``, the diagonal entries in one
    ``einsum`` over the contiguous ``(m, N)`` rows, each off-diagonal pair in one more. Gains
    in closed form for ``m = 1`` (``log1p(s)``) and ``m = 2`` (``log1p(a + c + a c - b^2)``,
    :func:`~selenv.core.information.block_logdet_gains`'s formula); a batched Cholesky
    otherwise.
    """
    k, m, N = ZT.shape[0], ZT.shape[2], ZT.shape[3]
    assert ST.flags.c_contiguous  # the diagonal below is a view
    diagonal = ST.reshape(k, m * m, N)[:, :: m + 1]  # (k, m, N) view of S[a, a]
    np.einsum("kian,kian->kan", ZT, ZT, out=diagonal)
    for a in range(m):
        for c in range(a + 1, m):
            np.einsum("kin,kin->kn", ZT[:, :, a], ZT[:, :, c], out=ST[:, a, c])
            ST[:, c, a] = ST[:, a, c]
    if m == 1:
        np.log1p(ST[:, 0, 0], out=gains)
    elif m == 2:
        s00, s01, s11 = ST[:, 0, 0], ST[:, 0, 1], ST[:, 1, 1]
        x = s00 + s11  # det(I + S) - 1 = a + c + a c - b^2, in that order
        x += np.multiply(s00, s11, out=gains)
        x -= np.multiply(s01, s01, out=gains)
        np.log1p(x, out=gains)
    else:
        S = np.ascontiguousarray(ST.transpose(0, 3, 1, 2))
        gains[:] = block_logdet_gains(S.reshape(-1, m, m)).reshape(gains.shape)


def _inverse_factor(X: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``C^-1`` ``(k, d, d)`` and ``log det(C C^T)`` ``(k,)`` for ``C C^T = I + X^T X``.

    ``X`` ``(k, m, d)``: the picked candidates' whitened rows. ``C`` is the product of ``m``
    rank-one factors ``C_a = chol(I + w_a w_a^T)``, ``w_a = (C_1 .. C_{a-1})^-1 x_a``, each
    inverted in closed form with ``beta_i = 1 + sum_{l <= i} w_l^2`` (``beta_{-1} = 1``)::

        (C_a^-1)_ii = sqrt(beta_{i-1} / beta_i),
        (C_a^-1)_il = -w_i w_l / sqrt(beta_i beta_{i-1})   (l < i),

    and ``log det(I + X^T X) = sum_a log(1 + |w_a|^2)`` (the log-det step of eq. 9). A zero
    row (a padded scalar candidate) gives ``C_a = I``.

    Raises:
        ValueError: a non-finite row (NaN/inf in the state).
    """
    k, m, d = X.shape
    if not np.isfinite(X).all():
        raise ValueError("I + Z_j^T Z_j is not finite: the gain state holds NaN or inf")
    Cinv: FloatArray | None = None
    logdet = np.zeros(k)
    diag = np.arange(d)
    for a in range(m):
        w = X[:, a] if Cinv is None else np.matmul(Cinv, X[:, a, :, None])[..., 0]
        cum = np.cumsum(w * w, axis=1)
        beta = 1.0 + cum
        beta_prev = np.empty_like(beta)
        beta_prev[:, 0] = 1.0
        beta_prev[:, 1:] = beta[:, :-1]
        F = np.tril((w / -np.sqrt(beta * beta_prev))[:, :, None] * w[:, None, :], -1)
        F[:, diag, diag] = np.sqrt(beta_prev / beta)
        Cinv = F if Cinv is None else np.matmul(F, Cinv)
        logdet += np.log1p(cum[:, -1])
    assert Cinv is not None
    return Cinv, logdet


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
