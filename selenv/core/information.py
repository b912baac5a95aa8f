"""Fisher-information accumulation and log-det marginal gains.

Implements the objective of Kirchner et al. (2020), eq. (9)::

    f(S) = log det(Q0 + sum_{k in S} Q_k) - log det Q0,     Q_k = H_k^T R_k^-1 H_k  (eq. 2, 4)

and the state that makes greedy selection (their Algorithm 1) cheap.

Shape convention: a pool of ``N`` candidate measurements, each with at most ``m`` rows, over a
``d``-dimensional parameter. Jacobians ``H`` are ``(N, m, d)`` and noise covariances ``R`` are
``(N, m, m)``; candidates with fewer rows are zero-padded in ``H`` with identity in ``R`` (a
zero row adds no information, so padding is exact). Every candidate is whitened once,
``G_k = L_k^-1 H_k`` with ``R_k = L_k L_k^T``, so that ``Q_k = G_k^T G_k``.

Marginal gains (matrix determinant lemma; Kirchner et al. 2020, eq. 9): with ``A`` the current
information and ``P = A^-1``, the gain of candidate ``k`` is ``log det(I_m + S_k)``,
``S_k = G_k P G_k^T``.
Adding a row ``g`` is a rank-one update; with ``u = P g``, ``q = g^T u`` and ``c = G u``::

    S <- S - c c^T / (1 + q),   P <- P - u u^T / (1 + q),   f <- f + log(1 + q)

which costs ``O(N m d)`` per row instead of the ``O(N d^3)`` of recomputing every log det.

Validation: :func:`validate_candidates` / :func:`as_candidates` check raw pools in full (real
types, shapes naming the argument that disagrees, finiteness, SPD-ness and the valid range of
:func:`~selenv.core.linalg.check_magnitude`); the functions on whitened pools check types and
shapes (cheap) and that ``G`` is finite and within ``MAX_ABS``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
from scipy.linalg import cho_solve, solve_triangular
from scipy.linalg.lapack import dpotrs, dtrtrs

from selenv.core.linalg import (
    MAX_ABS,
    MIN_PD_DIAG,
    FloatArray,
    ShapeError,
    as_float_array,
    blame_shapes,
    check_finite,
    check_magnitude,
    check_shape,
    cholesky_small,
    cholesky_spd,
    inv_lower_small,
    logdet_spd,
    symmetrize,
    validate_spd,
)

_MAX_ABS2 = MAX_ABS * MAX_ABS

__all__ = [
    "LogDetGainState",
    "as_candidates",
    "block_logdet_gains",
    "information_matrix",
    "logdet_objective",
    "naive_greedy_logdet",
    "validate_candidates",
    "whiten",
    "whitened_pool",
]


#: accepted shapes, in symbols (for :func:`blame_shapes`)
_SHAPES: dict[str, list[str]] = {
    "Q0": ["d d"],
    "H": ["N d", "N m d"],
    "R": ["", "N", "m m", "N m m"],
    "G": ["N m d"],
    "S": ["N m m"],
}


def _blame(exc: ShapeError, **args: object) -> ShapeError:
    return blame_shapes(args, {k: _SHAPES[k] for k in args}, error=exc) or exc


def whitened_pool(Q0: object, G: object) -> tuple[FloatArray, FloatArray]:
    """``Q0`` (d, d) SPD and a whitened pool ``G`` (N, m, d), finite and within ``MAX_ABS``.

    The cheap check of the ``*_whitened`` solvers (``Q0`` fully, ``G`` by type, shape and one
    sum of squares).

    Raises:
        TypeError: not real numeric.
        ValueError: wrong shapes (naming the argument that disagrees), ``Q0`` not SPD or out of
            range, ``G`` not finite or out of range.
    """
    G_a = as_float_array(G, "G")
    try:
        Q0_a = validate_spd(Q0, "Q0")
        check_shape(G_a, (None, None, Q0_a.shape[0]), "G")
    except ShapeError as exc:
        raise _blame(exc, Q0=Q0, G=G) from None
    check_magnitude(Q0_a, "Q0", definite=True)
    if not float(np.vdot(G_a, G_a)) <= MAX_ABS * MAX_ABS:  # NaN/inf fail; exact checks below
        check_magnitude(check_finite(G_a, "G"), "G")
    return Q0_a, G_a


def whiten(H: FloatArray, R: FloatArray) -> FloatArray:
    """Whiten candidate Jacobians: ``G_k = L_k^-1 H_k`` with ``R_k = L_k L_k^T``.

    Args:
        H: ``(N, m, d)`` Jacobians ``d mu_k / d theta``.
        R: ``(N, m, m)`` noise covariances, or one ``(m, m)`` shared by all candidates.

    Returns:
        ``G`` of shape ``(N, m, d)`` with ``G_k^T G_k = H_k^T R_k^-1 H_k`` (eq. 4, Gaussian case).

    Raises:
        TypeError: not real numeric.
        ValueError: wrong shapes (naming the argument), an ``R_k`` that is not SPD (or holds
            NaN/inf), or a result that overflows float64.
    """
    H_a, R_a = as_float_array(H, "H"), as_float_array(R, "R")
    try:
        check_shape(H_a, (None, None, None), "H")
        N, m, _ = H_a.shape
        check_shape(R_a, (m, m) if R_a.ndim == 2 else (N, m, m), "R")
    except ShapeError as exc:
        raise _blame(exc, H=H, R=R) from None
    R_b = np.broadcast_to(R_a, (N, m, m)) if R_a.ndim == 2 else R_a
    L = cholesky_spd(R_b, "R")  # R_k = L_k L_k^T, batched
    G = np.linalg.solve(L, H_a).astype(np.float64, copy=False)  # G_k = L_k^-1 H_k, no inv
    if not np.all(np.isfinite(G)):
        check_finite(H_a, "H")
        raise ValueError(
            "whiten: G = L^-1 H overflows float64; keep |H| <= "
            f"{MAX_ABS:g} and the diagonals of R >= 1e-100 (rescale the problem)"
        )
    return G


def validate_candidates(
    H: object, R: object, d: int | None = None
) -> tuple[FloatArray, FloatArray]:
    """Validate and normalise a candidate pool to ``H (N, m, d)`` and ``R (N, m, m)``.

    Accepted forms: ``H (N, m, d)`` with ``R (N, m, m)`` or ``(m, m)``; or scalar candidates
    ``H (N, d)`` with ``R`` of shape ``(N,)`` (variances) or a scalar variance.

    Raises:
        TypeError: not real numeric (complex, bool, str, object).
        ValueError: wrong shapes (naming the argument that disagrees), NaN/inf, an ``R_k``
            that is not SPD (names the candidate), or values outside the valid range
            (``|H| <= MAX_ABS``, variances / diagonals of ``R`` in ``[MIN_PD_DIAG, MAX_ABS]``).
    """
    H_a = as_float_array(H, "H")
    R_a = as_float_array(R, "R")
    try:
        return _candidates(H_a, R_a, d)
    except ShapeError as exc:
        raise _blame(exc, H=H, R=R) from None


def _candidates(H_a: FloatArray, R_a: FloatArray, d: int | None) -> tuple[FloatArray, FloatArray]:
    if H_a.ndim not in (2, 3):
        raise ShapeError(f"H must have shape (N, d) or (N, m, d), got {H_a.shape}", "H")
    if d is not None and H_a.shape[-1] != d:
        want = "(N, d)" if H_a.ndim == 2 else "(N, m, d)"
        raise ShapeError(f"H must have shape {want} with d = {d} to match Q0, got {H_a.shape}", "H")
    if H_a.ndim == 2 and _scalar_pool_ok(H_a, R_a):  # fast path: every check below passes
        return H_a[:, None, :], R_a[:, None, None]
    check_magnitude(check_finite(H_a, "H"), "H")
    check_finite(R_a, "R")
    if H_a.ndim == 2:
        N = H_a.shape[0]
        if R_a.ndim == 0:
            R_a = np.full(N, float(R_a))
        if R_a.ndim != 1 or R_a.shape[0] != N:
            raise ShapeError(
                f"R (variances of scalar candidates) must have shape ({N},), got {R_a.shape}",
                "R",
            )
        if np.any(R_a <= 0):
            k = int(np.argmin(R_a))
            raise ValueError(f"R must hold positive variances, but R[{k}] = {R_a[k]:g}")
        check_magnitude(R_a, "R", definite=True)
        return H_a[:, None, :], R_a[:, None, None]
    N, m, _ = H_a.shape
    if R_a.ndim == 2:
        R_a = check_magnitude(validate_spd(R_a, "R", m), "R", definite=True)
        return H_a, np.broadcast_to(R_a, (N, m, m)).copy()
    check_shape(R_a, (N, m, m), "R")
    try:
        R_a = validate_spd(R_a, "R", m, batch=True)
    except ValueError:
        for k in range(N):  # find the culprit for a precise message
            validate_spd(R_a[k], f"R[{k}]", m)
        raise
    return H_a, check_magnitude(R_a, "R", definite=True)


def _scalar_pool_ok(H_a: FloatArray, R_a: FloatArray) -> bool:
    """Whether scalar candidates ``H (N, d)``, ``R (N,)`` pass every check of :func:`_candidates`.

    One ``np.vdot`` bounds ``H`` (finite and ``|h| <= MAX_ABS``: NaN/inf fail the comparison)
    and ``min`` / ``max`` bound ``R`` (NaN fails both comparisons). Anything that fails runs
    the canonical checks, so every error message and its precedence is unchanged.
    """
    if R_a.ndim != 1 or R_a.shape[0] != H_a.shape[0] or not R_a.size:
        return False
    if not float(np.vdot(H_a, H_a)) <= _MAX_ABS2:  # vdot: no FP warning on overflow
        return False
    return bool(MIN_PD_DIAG <= R_a.min()) and bool(R_a.max() <= MAX_ABS)


def _whiten_rows(H_a: FloatArray, R_a: FloatArray) -> FloatArray:
    """:func:`whiten` of validated one-row candidates ``H (N, 1, d)``, ``R (N, 1, 1)``.

    ``G_k = H_k * (1 / sqrt(R_k))``: the 1 x 1 Cholesky factor is ``sqrt(R_k)``, so this is
    :func:`whiten`'s ``L_k^-1 H_k`` to one rounding (a BLAS may divide where this multiplies
    by the reciprocal), without the per-candidate overhead of the batched factorisation and
    solve. Validated inputs (``|H| <= MAX_ABS``, ``R >= MIN_PD_DIAG``) cannot overflow.
    """
    G: FloatArray = H_a * (1.0 / np.sqrt(R_a))
    return G


def _valid_prior(Q0: object) -> tuple[FloatArray, FloatArray] | None:
    """Fast path of ``validate_spd(Q0)`` + ``check_magnitude(Q0, definite=True)``: ``(Q0, L0)``.

    Accepts only a float64 ``(d, d)`` ndarray that is byte-wise symmetric (so its symmetrized
    copy is bit for bit itself), bounded by one ``np.vdot`` (finite, ``|a| <= MAX_ABS``), with
    diagonal ``>= MIN_PD_DIAG`` and a Cholesky factor ``L0`` (returned, so it is not factored
    again). ``None`` for anything else: the caller then runs the canonical checks.
    """
    if type(Q0) is not np.ndarray or Q0.dtype != np.float64 or Q0.ndim != 2:
        return None
    d = Q0.shape[0]
    if Q0.shape[1] != d or d == 0 or Q0.tobytes() != Q0.T.tobytes():
        return None
    if not float(np.vdot(Q0, Q0)) <= _MAX_ABS2 or not bool(Q0.diagonal().min() >= MIN_PD_DIAG):
        return None
    try:
        L0 = np.linalg.cholesky(Q0)
    except np.linalg.LinAlgError:
        return None
    if not math.isfinite(float(np.sum(L0.diagonal()))):
        return None
    return 0.5 * (Q0 + Q0.T), L0  # = symmetrize(Q0), a copy as validate_spd returns


def _as_candidates(Q0: object, H: object, R: object) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`as_candidates` plus ``cholesky_spd(Q0)`` (the same checks and results)."""
    fast = _valid_prior(Q0)
    if fast is None:
        Q0_a, G = as_candidates(Q0, H, R)
        return Q0_a, G, cholesky_spd(Q0_a, "Q0")
    Q0_a, L0 = fast
    H_a, R_a = as_float_array(H, "H"), as_float_array(R, "R")
    try:
        H_a, R_a = _candidates(H_a, R_a, Q0_a.shape[0])
    except ShapeError as exc:
        raise _blame(exc, Q0=Q0, H=H, R=R) from None
    G = _whiten_rows(H_a, R_a) if H_a.shape[1] == 1 else whiten(H_a, R_a)
    return Q0_a, G, L0


def as_candidates(Q0: object, H: object, R: object) -> tuple[FloatArray, FloatArray]:
    """Validate ``Q0`` (SPD, ``(d, d)``) and a candidate pool, and whiten the pool.

    Returns:
        ``(Q0, G)`` with ``Q0`` float64 ``(d, d)`` and ``G`` ``(N, m, d)``.

    Raises:
        TypeError: not real numeric (complex, bool, str, object).
        ValueError: as :func:`validate_candidates`; ``Q0`` not SPD or out of range; shapes
            name the argument that disagrees with the others (``Q0``, ``H`` or ``R``).
    """
    H_a, R_a = as_float_array(H, "H"), as_float_array(R, "R")
    try:
        Q0_a = validate_spd(Q0, "Q0")
        H_a, R_a = _candidates(H_a, R_a, Q0_a.shape[0])
    except ShapeError as exc:
        raise _blame(exc, Q0=Q0, H=H, R=R) from None
    check_magnitude(Q0_a, "Q0", definite=True)
    if H_a.shape[1] == 1:  # one row per candidate: no batched factorisation needed
        return Q0_a, _whiten_rows(H_a, R_a)
    return Q0_a, whiten(H_a, R_a)


def _indices(selected: Iterable[int] | FloatArray | None, N: int) -> np.ndarray:
    if selected is None:
        return np.zeros(0, dtype=np.intp)
    idx = np.asarray(list(selected) if not isinstance(selected, np.ndarray) else selected)
    if idx.dtype == bool:
        check_shape(idx, (N,), "selected (boolean mask)")
        return np.flatnonzero(idx)
    if idx.size == 0:
        return np.zeros(0, dtype=np.intp)
    if not np.issubdtype(idx.dtype, np.integer):
        raise TypeError(f"selected must hold integer indices or be a bool mask, got {idx.dtype}")
    idx = idx.astype(np.intp, copy=False).ravel()
    if idx.min() < 0 or idx.max() >= N:
        raise ValueError(f"selected indices must lie in [0, {N}), got {idx.min()}..{idx.max()}")
    return idx


def _pool(Q0: object, G: object) -> tuple[FloatArray, FloatArray]:
    """Types and shapes of ``Q0`` (d, d) and ``G`` (N, m, d) (no value checks)."""
    Q0_a, G_a = as_float_array(Q0, "Q0"), as_float_array(G, "G")
    try:
        check_shape(Q0_a, (None, None), "Q0")
        check_shape(Q0_a, (Q0_a.shape[0], Q0_a.shape[0]), "Q0")
        check_shape(G_a, (None, None, Q0_a.shape[0]), "G")
    except ShapeError as exc:
        raise _blame(exc, Q0=Q0, G=G) from None
    return Q0_a, G_a


def information_matrix(
    Q0: FloatArray, G: FloatArray, selected: Iterable[int] | FloatArray | None = None
) -> FloatArray:
    """FIM of a selection, eq. (2): ``Q0 + sum_{k in S} G_k^T G_k``, shape ``(d, d)``.

    Raises:
        TypeError: not real numeric, or ``selected`` not integer indices / a bool mask.
        ValueError: shapes that disagree (names the argument), indices out of range.
    """
    Q0, G = _pool(Q0, G)
    idx = _indices(selected, G.shape[0])
    Gs = G[idx].reshape(-1, G.shape[2])
    return symmetrize(Q0 + Gs.T @ Gs)


def logdet_objective(
    Q0: FloatArray, G: FloatArray, selected: Iterable[int] | FloatArray | None
) -> float:
    """Objective ``f(S)`` of eq. (9) by direct Cholesky log-dets (the independent reference).

    Raises:
        TypeError, ValueError: as :func:`information_matrix`; a FIM or ``Q0`` that is not
            (numerically) positive definite.
    """
    return float(logdet_spd(information_matrix(Q0, G, selected), "FIM")) - float(
        logdet_spd(Q0, "Q0")
    )


def _lower_solve(L: FloatArray, B: FloatArray) -> FloatArray:
    """``solve_triangular(L, B, lower=True)`` for a finite non-singular ``L``, bit for bit.

    Calls LAPACK ``trtrs`` exactly as SciPy's ``_solve_triangular`` does (on ``L^T`` with
    ``trans=1`` unless ``L`` is Fortran-ordered), without its validation and batching
    wrappers (about 20 us per call); anything unusual goes through SciPy.
    """
    if B.size:
        if L.flags.f_contiguous:
            X, info = dtrtrs(L, B, lower=1, trans=0)
        else:
            X, info = dtrtrs(L.T, B, lower=0, trans=1)
        if info == 0:
            out: FloatArray = X
            return out
    return solve_triangular(L, B, lower=True)


def _logdet_objective_trusted(
    Q0: FloatArray, G: FloatArray, selected: list[int], L0: FloatArray
) -> float:
    """:func:`logdet_objective` of validated inputs, bit for bit, without re-validating.

    ``L0`` is ``cholesky_spd(Q0)`` (so ``log det Q0`` is not factored again). The FIM is
    formed and factored exactly as :func:`information_matrix` and :func:`logdet_spd` do (the
    symmetrized FIM is exactly symmetric, so :func:`cholesky_spd` would factor it as is); a
    failed factorisation runs :func:`logdet_objective` for the canonical error.
    """
    idx = np.asarray(selected, dtype=np.intp)
    Gs = G[idx].reshape(-1, G.shape[2])
    B = Q0 + Gs.T @ Gs
    A = 0.5 * (B + B.T)  # = symmetrize(B)
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        return logdet_objective(Q0, G, selected)
    out = 2.0 * np.sum(np.log(np.diagonal(L)), axis=-1)
    if not math.isfinite(float(out)):
        return logdet_objective(Q0, G, selected)
    return float(out) - float(2.0 * np.sum(np.log(np.diagonal(L0)), axis=-1))


def _logdet_gains3(S: FloatArray) -> FloatArray:
    """``log det(I + S_k)`` of PSD ``3 x 3`` blocks ``S`` ``(N, 3, 3)`` by a vectorised Cholesky.

    The column-by-column Cholesky ``A = I + S = L L^T`` written out for ``3 x 3`` (one LAPACK
    call per candidate becomes about 20 vector operations), then
    ``2 (log l00 + log l11 + log l22)``. It agrees with LAPACK's factorisation to rounding:
    ``|error| <~ 1e-13 (1 + S22) / l22^2`` (tested), and the solvers' picks do not depend on
    which of the two computed a gain. Internal (the greedy solvers), ``S`` not validated.
    """
    with np.errstate(invalid="ignore", divide="ignore"):  # not PD: reported below
        a00, a11, a22 = 1.0 + S[:, 0, 0], 1.0 + S[:, 1, 1], 1.0 + S[:, 2, 2]
        l00 = np.sqrt(a00)
        r0 = 1.0 / l00
        l10, l20 = S[:, 1, 0] * r0, S[:, 2, 0] * r0
        l11 = np.sqrt(a11 - l10 * l10)
        l21 = (S[:, 2, 1] - l20 * l10) * (1.0 / l11)
        l22 = np.sqrt(a22 - (l20 * l20 + l21 * l21))
        out: FloatArray = 2.0 * ((np.log(l00) + np.log(l11)) + np.log(l22))
    if not np.all(np.isfinite(out)):
        return block_logdet_gains(S)  # the canonical error (or result)
    return out


def block_logdet_gains(S: FloatArray) -> FloatArray:
    """``log det(I_m + S_k)`` for a batch ``S`` of PSD ``(N, m, m)`` matrices, shape ``(N,)``.

    Closed forms for ``m = 1`` (``log1p``) and ``m = 2``; batched Cholesky otherwise.

    Raises:
        TypeError: ``S`` not a float64 array.
        ValueError: ``S`` not ``(N, m, m)``, or (m > 2) ``I + S_k`` not positive definite.
    """
    if type(S) is not np.ndarray or S.dtype != np.float64:
        S = as_float_array(S, "S")
    if S.ndim != 3 or S.shape[1] != S.shape[2]:
        raise ShapeError(f"S must have shape (N, m, m), got {np.shape(S)}", "S")
    m = S.shape[-1]
    if m == 1:
        return np.log1p(S[:, 0, 0])
    if m == 2:
        a, b, c = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
        return np.log1p(a + c + a * c - b * b)  # det(I + S) - 1 = a + c + ac - b^2
    L = cholesky_spd(S + np.eye(m), "I + S_k")
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

    Raises:
        TypeError: ``Q0`` / ``G`` not real numeric.
        ValueError: wrong shapes (naming the argument that disagrees), ``Q0`` not SPD, values
            not finite or outside the valid range (see :func:`whitened_pool`).
    """

    def __init__(
        self,
        Q0: FloatArray,
        G: FloatArray,
        *,
        track_gains: bool = True,
        track_whitened: bool = False,
    ) -> None:
        Q0_a, G_a = whitened_pool(Q0, G)
        self._setup(Q0_a, G_a, cholesky_spd(Q0_a, "Q0"), track_gains, track_whitened)

    @classmethod
    def _trusted(cls, Q0: FloatArray, G: FloatArray, L0: FloatArray) -> LogDetGainState:
        """Rank-one state with gains over an already validated ``Q0`` / ``G`` (no checks).

        ``L0`` is ``cholesky_spd(Q0)``. For the solvers, which validated their input with
        :func:`whitened_pool` or :func:`as_candidates` (internal: not for user input).
        """
        self = cls.__new__(cls)
        self._setup(Q0, G, L0, True, False, closed3=True)
        return self

    def _setup(
        self,
        Q0: FloatArray,
        G: FloatArray,
        L0: FloatArray,
        track_gains: bool,
        track_whitened: bool,
        *,
        closed3: bool = False,
    ) -> None:
        """Initial ``P`` (or ``L^-1``), ``Z``, ``S`` and gains from validated inputs.

        ``closed3``: gains of 3-row candidates by the vectorised Cholesky
        :func:`_logdet_gains3` instead of LAPACK's (the solvers only: the last bits of gains may
        differ, the picks do not; see ``tests/test_speed_identity_greedy.py``).
        """
        self._closed3 = closed3 and G.shape[1] == 3
        self.Q0 = Q0
        self.G = G
        self.N, self.m, self.d = G.shape
        self._Gflat = G.reshape(self.N * self.m, self.d)
        self._pairs = [(a, b) for a in range(self.m) for b in range(a, self.m)]
        self.L0 = L0
        # rank-one mode keeps P = A^-1; whitened mode keeps L^-1 (A = L L^T) and P = L^-T L^-1
        self._P: FloatArray | None = None
        self._Linv: FloatArray | None = None
        if track_whitened:
            self._Linv = solve_triangular(L0, np.eye(self.d), lower=True, check_finite=False)
        else:  # P = Q0^-1 by LAPACK potrs, the routine cho_solve calls, minus its wrappers
            P, info = dpotrs(L0, np.eye(self.d), lower=1)
            if info != 0:
                P = cho_solve((L0, True), np.eye(self.d))
            self._P = P
        self.selected = np.zeros(self.N, dtype=bool)
        self.order: list[int] = []
        self.objective = 0.0
        self.track_gains = track_gains
        self.track_whitened = track_whitened
        W = _lower_solve(L0, self._Gflat.T).T  # rows g L0^-T
        self.Z: FloatArray | None = W.reshape(G.shape) if track_whitened else None
        self.S: FloatArray | None = None
        self.gains: FloatArray | None = None
        if track_gains:
            Wb = W.reshape(G.shape)
            self.S = np.einsum("kid,kjd->kij", Wb, Wb)  # S_k = G_k Q0^-1 G_k^T
            self.gains = self._gains(self.S)

    def _gains(self, S: FloatArray) -> FloatArray:
        """``log det(I + S_k)`` of the tracked ``S`` (see :func:`block_logdet_gains`)."""
        if self.m == 1:  # inlined: block_logdet_gains computes the same log1p
            out: FloatArray = np.log1p(S[:, 0, 0])
            return out
        if self._closed3:
            return _logdet_gains3(S)
        return block_logdet_gains(S)

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
        """Exact gain ``log det(I + G_k P G_k^T)`` of one candidate, ``O(m d^2)``.

        Raises:
            TypeError: ``k`` not an int.
            ValueError: ``k`` out of range.
        """
        k = self._index(k, "k")
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
            TypeError: ``j`` not an int.
            ValueError: ``j`` out of range or already selected (the state is unchanged).
        """
        j = self._index(j, "j")
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

    def _index(self, j: object, name: str) -> int:
        if isinstance(j, bool) or not isinstance(j, int | np.integer):
            raise TypeError(f"{name} must be an int candidate index, got {type(j).__name__}")
        if not 0 <= j < self.N:
            raise ValueError(f"candidate index must lie in [0, {self.N}), got {j}")
        return int(j)

    def _add_rank_one(self, Gj: FloatArray) -> None:
        """One Sherman-Morrison update of ``P`` (and ``S``) per non-zero row of ``G_j``."""
        P = self._P
        assert P is not None
        S = self.S
        for g in Gj:
            if not g.any():
                continue  # zero padding row: no information
            u = P @ g  # u = P g
            q = float(g @ u)  # q = g^T P g
            B = P - u[:, None] * u / (1.0 + q)  # Sherman-Morrison (u[:, None] * u = np.outer)
            P = 0.5 * (B + B.T)  # = symmetrize(B), inlined
            self.objective += float(np.log1p(q))  # matrix determinant lemma
            if S is not None:
                c = (self._Gflat @ u).reshape(self.N, self.m)  # c = G u
                c *= 1.0 / np.sqrt(1.0 + q)
                # S <- S - c c^T / (1 + q), unique entries only: N-long vector operations are
                # 3-7x faster here than one (N, m, m) broadcast or einsum (inner loops of m)
                for a, b in self._pairs:
                    v = c[:, a] * c[:, b]
                    S[:, a, b] -= v
                    if a != b:
                        S[:, b, a] -= v
        self._P = P
        if S is not None:
            self.gains = self._gains(S)

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

    Raises:
        TypeError: not real numeric, or ``budget`` not an int.
        ValueError: shapes that disagree (names the argument), ``budget`` outside [0, N].
    """
    Q0, G = _pool(Q0, G)
    N = G.shape[0]
    if isinstance(budget, bool) or not isinstance(budget, int | np.integer):
        raise TypeError(f"budget must be an int, got {type(budget).__name__}")
    if not 0 <= budget <= N:
        raise ValueError(f"budget must lie in [0, {N}], got {budget}")
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
