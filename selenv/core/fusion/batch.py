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

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from selenv.core import npfast
from selenv.core.fusion.common import (
    IntArray,
    Pair,
    finite_matrix,
    overflow_error,
    root_increasing_batch,
    root_increasing_one,
)
from selenv.core.fusion.dmv import _B_NOT_PD, _W_PROBE, _check_dims, _cubic
from selenv.core.fusion.pecmv import solve_guarded
from selenv.core.linalg import (
    MAX_ABS,
    MIN_PD_DIAG,
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
from selenv.core.spd import require_spd

__all__ = ["PECMVBatchResult", "dmv_omega_batch", "pecmv_batch"]

_MAX_ABS2 = MAX_ABS * MAX_ABS


def _omega_scalar_batch(a: FloatArray, b: FloatArray, n: int) -> FloatArray:
    """Vectorised ``selenv.core.fusion.dmv._omega_scalar``: same cubic, same safeguarded Newton."""
    c3, c2, c1, c0 = (
        np.broadcast_to(np.asarray(c, dtype=np.float64), a.shape) for c in _cubic(a, b, n)
    )
    if n == 1:
        c3, c2, c1, c0 = np.zeros_like(a), c3, c2, c1

    if a.shape[0] == 1:  # one problem: the same iteration in Python floats
        k3, k2, k1, k0 = float(c3[0]), float(c2[0]), float(c1[0]), float(c0[0])

        def g1(w: float) -> tuple[float, float]:
            return -(((k3 * w + k2) * w + k1) * w + k0), -((3.0 * k3 * w + 2.0 * k2) * w + k1)

        w = np.array([root_increasing_one(g1, 0.0, 1.0, 0.5)])
    else:
        rows = _Rows(c3, c2, c1, c0)

        def g(w: FloatArray, i: IntArray) -> tuple[FloatArray, FloatArray]:
            d3, d2, d1, d0 = rows(i)
            return -(((d3 * w + d2) * w + d1) * w + d0), -((3.0 * d3 * w + 2.0 * d2) * w + d1)

        def one(i: int) -> Callable[[float], tuple[float, float]]:
            k3, k2, k1, k0 = float(c3[i]), float(c2[i]), float(c1[i]), float(c0[i])
            return lambda w: (
                -(((k3 * w + k2) * w + k1) * w + k0),
                -((3.0 * k3 * w + 2.0 * k2) * w + k1),
            )

        ones = np.ones_like(a)
        w = root_increasing_batch(g, 0.0 * ones, ones, 0.5 * ones, scalar=one)
    w = np.where((n == 1) & (c0 <= 0.0), 0.0, w)
    return np.where(a <= n * b, 1.0, w)


class _Rows:
    """Rows ``idx`` of fixed arrays, re-indexed only when the active set of the Newton shrinks.

    :func:`root_increasing_batch` passes the same ``idx`` object until it drops items, and
    starts from all rows (``arange``), for which the full arrays are returned as they are.
    """

    def __init__(self, *arrays: FloatArray) -> None:
        self.full = arrays
        self.idx: IntArray | None = None
        self.rows: tuple[FloatArray, ...] = arrays

    def __call__(self, idx: IntArray) -> tuple[FloatArray, ...]:
        if idx is not self.idx:
            self.idx = idx
            same = idx.shape[0] == self.full[0].shape[0]
            self.rows = self.full if same else tuple(a[idx] for a in self.full)
        return self.rows


def _derivs(
    w: FloatArray,
    A: FloatArray,
    B: FloatArray,
    R: FloatArray,
    n: int,
    BmA: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """``f'(w)``, ``f''(w)`` of the cheap cost, batched: ``w`` (k,), ``A``, ``B``, ``R`` (k, m, m).

    With ``M = B + (1-w) R``, ``Q = (1-w) A + w B + w(1-w) R`` and ``Q' = B - A + (1-2w) R``::

        f'  = -(n-m)/w - tr(M^-1 R) - tr(Q^-1 Q')
        f'' = (n-m)/w^2 - tr((M^-1 R)^2) + tr((Q^-1 Q')^2) + 2 tr(Q^-1 R)

    ``BmA``: ``B - A`` when precomputed (it does not depend on ``w``). The solves call numpy's
    ``solve`` gufunc directly (the same LAPACK ``dgesv`` per matrix as ``np.linalg.solve``,
    under the same floating-point state, :func:`_solve_errstate`).
    """
    m = A.shape[-1]
    wb = w[:, None, None]
    v = 1.0 - wb
    M = B + v * R
    Q = v * A + wb * B + wb * v * R
    dQ = (B - A if BmA is None else BmA) + (1.0 - 2.0 * wb) * R
    with _solve_errstate():  # as np.linalg.solve: a singular matrix raises LinAlgError
        X1 = npfast.solve(M, R)  # M^-1 R
        X2 = npfast.solve(Q, np.concatenate([dQ, R], axis=-1))  # Q^-1 [Q', R]
    G, H = X2[..., :m], X2[..., m:]
    # the method behind np.trace and the C einsum behind np.einsum, without their wrappers
    f1 = -(n - m) / w - X1.trace(0, 1, 2) - G.trace(0, 1, 2)
    f2 = (n - m) / w**2 - npfast.einsum("...ij,...ji->...", X1, X1)
    f2 = f2 + npfast.einsum("...ij,...ji->...", G, G) + 2.0 * H.trace(0, 1, 2)
    return f1, f2


def _raise_singular(err: str, flag: int) -> None:
    raise np.linalg.LinAlgError("Singular matrix")


def _solve_errstate() -> np.errstate:
    """The floating-point state ``np.linalg.solve`` sets: a singular matrix raises LinAlgError."""
    return np.errstate(
        call=_raise_singular, invalid="call", over="ignore", divide="ignore", under="ignore"
    )


def _tr(X: list[list[float]], m: int) -> float:
    """``np.trace`` of an m x m matrix (m <= 3): the same left-to-right sum."""
    t = X[0][0]
    for i in range(1, m):
        t += X[i][i]
    return t


def _sq(X: list[list[float]], m: int) -> float:
    """``np.einsum("ij,ji->", X, X)`` for m <= 3: row sums of ``X_ij X_ji``, then their sum.

    The order of numpy's ``einsum`` kernel for these sizes (checked bit for bit on 3e5 random
    matrices per m, with 1e-160 scales, in ``tests/test_speed_identity_core.py``).
    """
    total = 0.0
    for i in range(m):
        Xi = X[i]
        r = Xi[0] * X[0][i]
        for j in range(1, m):
            r += Xi[j] * X[j][i]
        total = r if i == 0 else total + r
    return total


def _g_one(
    A: FloatArray, B: FloatArray, R: FloatArray, n: int, guard: bool
) -> Callable[[float], tuple[float, float]]:
    """:func:`_derivs` for one problem (``A``, ``B``, ``R`` (m, m), m <= 3) in Python floats.

    The elementwise parts in the same operations and order as :func:`_derivs`, the two
    solves by the same ``solve`` gufunc, the traces and ``einsum`` by :func:`_tr` and
    :func:`_sq`: bit-identical to the batched evaluation at ~1/5 of its per-call overhead.
    ``guard``: set :func:`_solve_errstate` around the solves (else the caller has set it).
    """
    m = A.shape[0]
    Al, Bl, Rl = A.tolist(), B.tolist(), R.tolist()
    BmA = [[Bl[i][j] - Al[i][j] for j in range(m)] for i in range(m)]
    rng = range(m)
    if m == 2:
        return _g_two(Al, Bl, Rl, BmA, R, n, guard)

    def g(w: float) -> tuple[float, float]:
        v, u = 1.0 - w, 1.0 - 2.0 * w
        wv = w * v
        M = [[Bl[i][j] + v * Rl[i][j] for j in rng] for i in rng]
        Q = [[v * Al[i][j] + w * Bl[i][j] + wv * Rl[i][j] for j in rng] for i in rng]
        rhs = [[BmA[i][j] + u * Rl[i][j] for j in rng] + Rl[i] for i in rng]
        if guard:
            with _solve_errstate():
                X1 = npfast.solve(np.array(M), R).tolist()
                X2 = npfast.solve(np.array(Q), np.array(rhs)).tolist()
        else:
            X1 = npfast.solve(np.array(M), R).tolist()
            X2 = npfast.solve(np.array(Q), np.array(rhs)).tolist()
        G = [row[:m] for row in X2]
        f1 = -(n - m) / w - _tr(X1, m) - _tr(G, m)
        f2 = (n - m) / (w * w) - _sq(X1, m) + _sq(G, m) + 2.0 * _tr([r[m:] for r in X2], m)
        return f1, f2

    return g


def _g_two(
    Al: list[list[float]],
    Bl: list[list[float]],
    Rl: list[list[float]],
    BmA: list[list[float]],
    R: FloatArray,
    n: int,
    guard: bool,
) -> Callable[[float], tuple[float, float]]:
    """:func:`_g_one` for ``m = 2`` with the loops unrolled (the same operations, same order)."""
    (a11, a12), (a21, a22) = Al
    (b11, b12), (b21, b22) = Bl
    (r11, r12), (r21, r22) = Rl
    (d11, d12), (d21, d22) = BmA
    c = -(n - 2)
    e = n - 2

    def g(w: float) -> tuple[float, float]:
        v, u = 1.0 - w, 1.0 - 2.0 * w
        wv = w * v
        M = np.array([[b11 + v * r11, b12 + v * r12], [b21 + v * r21, b22 + v * r22]])
        Q = np.array(
            [
                [v * a11 + w * b11 + wv * r11, v * a12 + w * b12 + wv * r12],
                [v * a21 + w * b21 + wv * r21, v * a22 + w * b22 + wv * r22],
            ]
        )
        rhs = np.array(
            [[d11 + u * r11, d12 + u * r12, r11, r12], [d21 + u * r21, d22 + u * r22, r21, r22]]
        )
        if guard:
            with _solve_errstate():
                X1 = npfast.solve(M, R).tolist()
                X2 = npfast.solve(Q, rhs).tolist()
        else:
            X1 = npfast.solve(M, R).tolist()
            X2 = npfast.solve(Q, rhs).tolist()
        (x11, x12), (x21, x22) = X1
        (g11, g12, h11, _), (g21, g22, _, h22) = X2
        f1 = c / w - (x11 + x22) - (g11 + g22)
        sq1 = (x11 * x11 + x12 * x21) + (x21 * x12 + x22 * x22)
        sqg = (g11 * g11 + g12 * g21) + (g21 * g12 + g22 * g22)
        f2 = e / (w * w) - sq1 + sqg + 2.0 * (h11 + h22)
        return f1, f2

    return g


def _omega_one(A: FloatArray, B: FloatArray, R: FloatArray, n: int, probe: bool) -> float:
    """:func:`_dmv_omega_batch`'s Newton for one problem, bit-identical to the batched one.

    ``probe``: first test the slope at ``_W_PROBE`` for ``w* = 0`` (``n == m``).
    """
    g = _g_one(A, B, R, n, guard=False)
    with _solve_errstate():
        if probe and g(_W_PROBE)[0] >= 0.0:
            return 0.0
        return root_increasing_one(g, 0.0, 1.0, 0.5)


@dataclass(frozen=True, kw_only=True, eq=False)
class PECMVBatchResult:
    """Result of :func:`pecmv_batch`: the fields of :class:`PECMVResult` with a leading B axis."""

    P: FloatArray
    K: FloatArray
    X: FloatArray
    C: FloatArray
    updated: FloatArray
    log_det: FloatArray


def _spd_fast(A: FloatArray, B: int | None) -> tuple[FloatArray, FloatArray] | None:
    """What :func:`_spd_batch` returns for a stack that certainly passes it, else ``None``.

    Sufficient test (``None`` only means "run the canonical checks"): non-empty ``(B, n, n)``,
    ``sum a^2 <= MAX_ABS^2`` (finite, in range; NaN/inf fail it), diagonal ``>= MIN_PD_DIAG``,
    symmetric (byte-wise, then the stack is its own symmetrization ``0.5 * (a + a) == a``; or
    within the per-matrix tolerance of :func:`_spd_batch`, computed the same way, and then
    symmetrized the same way) and every matrix factored by the gufunc behind
    ``np.linalg.cholesky`` (a failure leaves that matrix NaN). Returns the symmetrized stack
    and the factors ``np.linalg.cholesky`` gives.
    """
    if A.ndim != 3 or A.shape[1] != A.shape[2] or A.shape[0] == 0 or A.shape[1] == 0:
        return None
    if B is not None and A.shape[0] != B:
        return None
    total2 = float(np.vdot(A, A))
    if not total2 <= _MAX_ABS2 or not A.diagonal(0, 1, 2).min() >= MIN_PD_DIAG:
        return None
    AT = A.transpose(0, 2, 1)
    if A.tobytes() != AT.tobytes():
        d = A - AT
        tol2 = (SYM_RTOL / A.shape[1]) ** 2
        # one matrix well inside the tolerance: the per-matrix sums below differ from these
        # vdots by rounding only (relative 1e-15), far less than the factor 2 margin
        if not (A.shape[0] == 1 and float(np.vdot(d, d)) <= 0.5 * tol2 * total2):
            asym2, norm2 = np.einsum("bij,bij->b", d, d), np.einsum("bij,bij->b", A, A)
            if not np.all(asym2 <= tol2 * norm2):
                return None
        A = 0.5 * (A + AT)
    with np.errstate(all="ignore"):
        L: FloatArray = npfast.cholesky_lo(A)
    return None if np.isnan(L[:, -1, -1]).any() else (A, L)


def _spd_batch(value: ArrayLike, name: str, B: int | None = None) -> tuple[FloatArray, FloatArray]:
    """Validate a (B, n, n) stack of SPD matrices; return it symmetrized with its Cholesky factors.

    Fastest path: :func:`_spd_fast` (the same checks with fewer numpy calls). Fast path: per-matrix
    ``||A - A^T||_F <= SYM_RTOL ||A||_F / n`` (NaN-safe) and one batched Cholesky; anything
    else goes to ``validate_spd`` for the canonical ``ValueError``. Every stack is also
    checked against the valid range (``check_magnitude``, definite).
    """
    A = as_float_array(value, name)
    fast = _spd_fast(A, B)
    if fast is not None:
        return fast
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
        fast = None
        if Rm.shape[-2:] == (m, m) and Rm.ndim in (2, 3):  # a shared R: a stack of one
            fast = _spd_fast(Rm if Rm.ndim == 3 else Rm[None], Bn if Rm.ndim == 3 else 1)
        if fast is not None:  # validate_spd would return the same symmetrized R
            Rm = fast[0] if Rm.ndim == 3 else fast[0][0]
        else:
            Rm = validate_spd(Rm, "R", m, batch=Rm.ndim == 3)
            if Rm.ndim == 3:
                check_shape(Rm, (Bn, m, m), "R")
            check_magnitude(Rm, "R", definite=True)
    except ShapeError as exc:
        args = {"P_i": P_i, "P_j": P_j, "H_i": H_i, "H_j": H_j, "R": R}
        raise (blame_shapes(args, _BATCH_SHAPES, error=exc) or exc) from None
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
    with np.errstate(all="ignore"):  # only pass / fail matters: a failure is NaN-filled
        LB = npfast.cholesky_lo(B)  # as np.linalg.cholesky(B)
    if np.isnan(LB[:, -1, -1]).any():
        raise ValueError(_B_NOT_PD)
    with _solve_errstate():
        trace_ratio = np.trace(npfast.solve(B, A), axis1=1, axis2=2)  # tr(B^-1 A)
    if Bn == 1 and m <= 3:  # one problem: Newton in Python floats (bit-identical)
        if not trace_ratio[0] > n:
            return np.ones(1)
        return np.array([_omega_one(A[0], B[0], Rm[0], n, n == m)])
    w = np.ones(Bn)
    todo = trace_ratio > n
    if n == m:
        zero = todo & (_derivs(np.full(Bn, _W_PROBE), A, B, Rm, n)[0] >= 0.0)
        w[zero] = 0.0
        todo &= ~zero
    if todo.any():
        At, Bt, Rt = A[todo], B[todo], Rm[todo]
        rows = _Rows(At, Bt, Rt, Bt - At)
        k = int(todo.sum())

        def g(x: FloatArray, idx: IntArray) -> tuple[FloatArray, FloatArray]:
            a_, b_, r_, bma = rows(idx)
            return _derivs(x, a_, b_, r_, n, bma)

        def one(i: int) -> Callable[[float], tuple[float, float]]:
            return _g_one(At[i], Bt[i], Rt[i], n, guard=True)

        w[todo] = root_increasing_batch(
            g, np.zeros(k), np.ones(k), np.full(k, 0.5), scalar=one if m <= 3 else None
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
    require_spd(res.P, "pecmv_batch", "the updated covariance P_i+")  # SPD on any BLAS
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
