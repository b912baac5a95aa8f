"""Batched DMV / PECMV solvers over a leading axis: labels for surrogate (LDMV, LPECMV) datasets.

Each function equals its single-case counterpart row by row (tested):

* :func:`dmv_omega_batch` -- ``w*`` of eq. (6). ``m = 1``: the stationarity cubic solved for
  every row at once by vectorised safeguarded Newton; ``m > 1``: vectorised safeguarded
  Newton on the derivative of the m x m cost.
* :func:`pecmv_batch` -- ``P``, ``K``, ``X*``, ``C*`` of eqs. (8)-(12). ``m = 1``: the closed
  form for every row at once; ``m > 1``: a loop over the exact fast path of
  :func:`~selenv.core.fusion.pecmv_update`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from selenv.core.fusion.common import (
    Pair,
    finite_matrix,
    overflow_error,
    root_increasing_batch,
)
from selenv.core.fusion.dmv import _B_NOT_PD, _W_PROBE, _check_dims, _cubic
from selenv.core.fusion.pecmv import solve_guarded
from selenv.core.linalg import (
    SYM_RTOL,
    FloatArray,
    ShapeError,
    as_float_array,
    blame_shapes,
    check_finite,
    check_magnitude,
    check_shape,
    validate_spd,
)

__all__ = ["PECMVBatchResult", "dmv_omega_batch", "pecmv_batch"]


def _omega_scalar_batch(a: FloatArray, b: FloatArray, n: int) -> FloatArray:
    """Vectorised ``selenv.core.fusion.dmv._omega_scalar``: same cubic, same safeguarded Newton."""
    c3, c2, c1, c0 = (
        np.broadcast_to(np.asarray(c, dtype=np.float64), a.shape) for c in _cubic(a, b, n)
    )
    if n == 1:
        c3, c2, c1, c0 = np.zeros_like(a), c3, c2, c1

    def g(w: FloatArray) -> tuple[FloatArray, FloatArray]:
        return -(((c3 * w + c2) * w + c1) * w + c0), -((3.0 * c3 * w + 2.0 * c2) * w + c1)

    ones = np.ones_like(a)
    w = root_increasing_batch(g, 0.0 * ones, ones, 0.5 * ones)
    w = np.where((n == 1) & (c0 <= 0.0), 0.0, w)
    return np.where(a <= n * b, 1.0, w)


def _derivs(
    w: FloatArray, A: FloatArray, B: FloatArray, R: FloatArray, n: int
) -> tuple[FloatArray, FloatArray]:
    """``f'(w)``, ``f''(w)`` of the cheap cost, batched: ``w`` (k,), ``A``, ``B``, ``R`` (k, m, m).

    With ``M = B + (1-w) R``, ``Q = (1-w) A + w B + w(1-w) R`` and ``Q' = B - A + (1-2w) R``::

        f'  = -(n-m)/w - tr(M^-1 R) - tr(Q^-1 Q')
        f'' = (n-m)/w^2 - tr((M^-1 R)^2) + tr((Q^-1 Q')^2) + 2 tr(Q^-1 R)
    """
    m = A.shape[-1]
    wb = w[:, None, None]
    M = B + (1.0 - wb) * R
    Q = (1.0 - wb) * A + wb * B + wb * (1.0 - wb) * R
    dQ = B - A + (1.0 - 2.0 * wb) * R
    X1 = np.linalg.solve(M, R)  # M^-1 R
    X2 = np.linalg.solve(Q, np.concatenate([dQ, R], axis=-1))  # Q^-1 [Q', R]
    G, H = X2[..., :m], X2[..., m:]
    tr = lambda X: np.trace(X, axis1=-2, axis2=-1)  # noqa: E731
    sq = lambda X: np.einsum("...ij,...ji->...", X, X)  # noqa: E731
    f1 = -(n - m) / w - tr(X1) - tr(G)
    f2 = (n - m) / w**2 - sq(X1) + sq(G) + 2.0 * tr(H)
    return f1, f2


@dataclass(frozen=True, kw_only=True, eq=False)
class PECMVBatchResult:
    """Result of :func:`pecmv_batch`: the fields of :class:`PECMVResult` with a leading B axis."""

    P: FloatArray
    K: FloatArray
    X: FloatArray
    C: FloatArray
    updated: FloatArray
    log_det: FloatArray


def _spd_batch(value: ArrayLike, name: str, B: int | None = None) -> tuple[FloatArray, FloatArray]:
    """Validate a (B, n, n) stack of SPD matrices; return it symmetrized with its Cholesky factors.

    Fast path: per-matrix ``||A - A^T||_F <= SYM_RTOL ||A||_F / n`` (NaN-safe) and one batched
    Cholesky; anything else goes to ``validate_spd`` for the canonical ``ValueError``. Every
    stack is also checked against the valid range (``check_magnitude``, definite).
    """
    A = as_float_array(value, name)
    if A.ndim != 3 or A.shape[1] != A.shape[2] or A.shape[0] == 0 or A.shape[1] == 0:
        A = validate_spd(A, name, batch=True)
        if A.shape[0] == 0 or A.shape[1] == 0:
            raise ShapeError(
                f"{name} must be a non-empty (B, n, n) stack, got shape {A.shape}", name
            )
    if B is not None:
        check_shape(A, (B, None, None), name)
    # finite and in range before any arithmetic (which would warn on inf / overflow)
    check_magnitude(check_finite(A, name), name, definite=True)
    d = A - np.swapaxes(A, 1, 2)
    asym2, norm2 = np.einsum("bij,bij->b", d, d), np.einsum("bij,bij->b", A, A)
    if not np.all(asym2 <= (SYM_RTOL / A.shape[1]) ** 2 * norm2):
        A = validate_spd(A, name, batch=True)
    A = 0.5 * (A + np.swapaxes(A, 1, 2))
    try:
        L: FloatArray = np.linalg.cholesky(A).astype(np.float64, copy=False)
    except np.linalg.LinAlgError:
        validate_spd(A, name, batch=True)  # raises, naming the argument
        raise ValueError(f"{name} is not positive definite (Cholesky failed)") from None
    return A, L


_BATCH_SHAPES = {
    "P_i": "B n_i n_i",
    "P_j": "B n_j n_j",
    "H_i": "B m n_i",
    "H_j": "B m n_j",
    "R": ["m m", "B m m"],
}


def _validate_batch(
    P_i: ArrayLike, P_j: ArrayLike, H_i: ArrayLike, H_j: ArrayLike, R: ArrayLike
) -> tuple[FloatArray, ...]:
    """``(P_i, L_i, P_j, L_j, H_i, H_j, R)`` validated; ``R`` broadcast to (B, m, m)."""
    try:
        Pi, Li = _spd_batch(P_i, "P_i")
        Bn, n_i = Pi.shape[0], Pi.shape[1]
        Pj, Lj = _spd_batch(P_j, "P_j", Bn)
        Hi = finite_matrix(H_i, "H_i", (Bn, None, n_i))
        m = Hi.shape[1]
        if m == 0:
            raise ShapeError("H_i must have at least one row (m >= 1)", "H_i")
        Hj = finite_matrix(H_j, "H_j", (Bn, m, Pj.shape[1]))
        Rm = as_float_array(R, "R")
        Rm = validate_spd(Rm, "R", m, batch=Rm.ndim == 3)
        if Rm.ndim == 3:
            check_shape(Rm, (Bn, m, m), "R")
    except ShapeError as exc:
        args = {"P_i": P_i, "P_j": P_j, "H_i": H_i, "H_j": H_j, "R": R}
        raise (blame_shapes(args, _BATCH_SHAPES, error=exc) or exc) from None
    check_magnitude(Rm, "R", definite=True)
    return Pi, Li, Pj, Lj, Hi, Hj, np.broadcast_to(Rm, (Bn, m, m))


def dmv_omega_batch(
    P_i: ArrayLike, P_j: ArrayLike, H_i: ArrayLike, H_j: ArrayLike, R: ArrayLike
) -> FloatArray:
    """The DMV optimiser ``w*`` of eq. (6) for a batch of problems (labels for LDMV training).

    Args:
        P_i: (B, n_i, n_i) SPD.
        P_j: (B, n_j, n_j) SPD.
        H_i: (B, m, n_i).
        H_j: (B, m, n_j).
        R: (B, m, m) or (m, m) SPD.

    Returns:
        (B,) ``w*``, equal to ``dmv_update(...).omega`` per row. ``m = 1``: the cubic solved
        for all rows at once; ``m > 1``: vectorised safeguarded Newton on the m x m cost.

    Raises:
        TypeError: an argument is not real numeric (complex, bool, str, object).
        ValueError: as for :func:`dmv_update` (names the argument).
    """
    args = _validate_batch(P_i, P_j, H_i, H_j, R)
    try:
        w = _dmv_omega_batch(*args)
    except (OverflowError, ZeroDivisionError, np.linalg.LinAlgError):
        raise overflow_error("dmv_omega_batch") from None
    if not np.all(np.isfinite(w)):
        raise overflow_error("dmv_omega_batch")
    return w


def _dmv_omega_batch(
    Pi: FloatArray,
    _Li: FloatArray,
    Pj: FloatArray,
    _Lj: FloatArray,
    Hi: FloatArray,
    Hj: FloatArray,
    Rm: FloatArray,
) -> FloatArray:
    """:func:`dmv_omega_batch` on validated inputs."""
    Bn, n, m = Pi.shape[0], Pi.shape[1], Hi.shape[1]
    _check_dims(n, m)
    A = np.einsum("bki,bij,blj->bkl", Hi, Pi, Hi)  # H_i P_i H_i^T
    B = np.einsum("bki,bij,blj->bkl", Hj, Pj, Hj)
    if m == 1:
        r = Rm[:, 0, 0]
        a, b = A[:, 0, 0] / r, B[:, 0, 0] / r
        if np.any(~(b > 0.0)):
            raise ValueError(_B_NOT_PD)
        return _omega_scalar_batch(a, b, n)
    try:
        np.linalg.cholesky(B)
    except np.linalg.LinAlgError:
        raise ValueError(_B_NOT_PD) from None
    trace_ratio = np.trace(np.linalg.solve(B, A), axis1=1, axis2=2)  # tr(B^-1 A)
    w = np.ones(Bn)
    todo = trace_ratio > n
    if n == m:
        zero = todo & (_derivs(np.full(Bn, _W_PROBE), A, B, Rm, n)[0] >= 0.0)
        w[zero] = 0.0
        todo &= ~zero
    if todo.any():
        At, Bt, Rt = A[todo], B[todo], Rm[todo]
        k = int(todo.sum())
        w[todo] = root_increasing_batch(
            lambda x: _derivs(x, At, Bt, Rt, n), np.zeros(k), np.ones(k), np.full(k, 0.5)
        )
    return w


def pecmv_batch(
    P_i: ArrayLike, P_j: ArrayLike, H_i: ArrayLike, H_j: ArrayLike, R: ArrayLike
) -> PECMVBatchResult:
    """PECMV for a batch of problems (labels ``C*`` for LPECMV training).

    Args:
        P_i: (B, n_i, n_i) SPD.
        P_j: (B, n_j, n_j) SPD.
        H_i: (B, m, n_i).
        H_j: (B, m, n_j).
        R: (B, m, m) or (m, m) SPD.

    Returns:
        :class:`PECMVBatchResult` with ``P`` (B, n_i, n_i), ``K`` (B, n_i, m), ``X`` and ``C``
        (B, n_i, n_j), ``updated`` (B,) bool and ``log_det`` (B,), equal row by row to
        :func:`pecmv_update` (``method="auto"``). ``m = 1``: the closed form for all rows at
        once; ``m > 1``: a loop over the exact fast path.

    Raises:
        TypeError: an argument is not real numeric (complex, bool, str, object).
        ValueError: bad shapes (naming the argument that disagrees), NaN/inf, non-SPD inputs,
            values outside the valid range or a result that overflows float64.
    """
    try:
        res = _pecmv_batch(*_validate_batch(P_i, P_j, H_i, H_j, R))
    except (OverflowError, ZeroDivisionError, np.linalg.LinAlgError):
        raise overflow_error("pecmv_batch") from None
    parts = (res.P, res.K, res.X, res.C)
    if np.any(np.isnan(res.log_det)) or not all(np.all(np.isfinite(v)) for v in parts):
        raise overflow_error("pecmv_batch")
    return res


def _pecmv_batch(
    Pi: FloatArray,
    L_i: FloatArray,
    Pj: FloatArray,
    L_j: FloatArray,
    Hi: FloatArray,
    Hj: FloatArray,
    Rm: FloatArray,
) -> PECMVBatchResult:
    """:func:`pecmv_batch` on validated inputs."""
    Bn, m = Pi.shape[0], Hi.shape[1]
    if m > 1:
        L_R = np.linalg.cholesky(Rm)
        rows = []
        for k in range(Bn):
            pair = Pair(Pi[k], L_i[k], Pj[k], L_j[k], Hi[k], Hj[k], Rm[k], L_R[k])
            rows.append(solve_guarded(pair, "fast", None, "pecmv_batch"))
        return PECMVBatchResult(
            **{f: np.stack([getattr(r, f) for r in rows]) for f in ("P", "K", "X", "C")},
            updated=np.array([r.updated for r in rows]),
            log_det=np.array([r.log_det for r in rows]),
        )
    r = Rm[:, 0, 0]
    sr = np.sqrt(r)[:, None]
    h_i, h_j = Hi[:, 0, :], Hj[:, 0, :]
    g_i = np.einsum("bki,bk->bi", L_i, h_i) / sr  # L_i^T h_i^T / sqrt(r)
    g_j = np.einsum("bki,bk->bi", L_j, h_j) / sr
    alpha, beta = np.linalg.norm(g_i, axis=1), np.linalg.norm(g_j, axis=1)
    upd = beta < alpha
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(upd, np.minimum(beta, (beta**2 + 1.0) / alpha), alpha)
        s = (alpha - rho) ** 2 + beta**2 + 1.0 - rho**2  # S / r
        c = np.where(beta > 0.0, -rho / beta, 0.0)  # C = c u_i u_j^T
        u_i = np.where(alpha[:, None] > 0.0, g_i / alpha[:, None], 0.0)
        u_j = np.where(beta[:, None] > 0.0, g_j / beta[:, None], 0.0)
        kcoef = np.where(upd, (alpha - rho) / (alpha * r * s), 0.0)
        xcoef = np.where((alpha > 0.0) & (beta > 0.0), c / (alpha * beta * r), 0.0)
    C = c[:, None, None] * u_i[:, :, None] * u_j[:, None, :]
    Ph = np.einsum("bij,bj->bi", Pi, h_i)  # P_i h_i^T
    Pjh = np.einsum("bij,bj->bi", Pj, h_j)  # P_j h_j^T
    X = xcoef[:, None, None] * Ph[:, :, None] * Pjh[:, None, :]  # L_i C L_j^T, rank one
    K = Ph * kcoef[:, None]
    P = Pi - (r * s)[:, None, None] * K[:, :, None] * K[:, None, :]
    ld_Pi = 2.0 * np.sum(np.log(np.diagonal(L_i, axis1=1, axis2=2)), axis=1)
    ld = ld_Pi + np.where(upd, np.log((beta**2 + 1.0 - rho**2) / s), 0.0)
    return PECMVBatchResult(P=P, K=K[:, :, None], X=X, C=C, updated=upd, log_det=ld)
