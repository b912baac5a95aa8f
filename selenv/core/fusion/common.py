"""Shared pieces of the fusion module: input validation, 1-D root finders, admissibility.

Not public API; import from :mod:`selenv.core.fusion`. Validation is on the hot path (a DMV
update with a scalar measurement costs a few tens of microseconds, of which
:func:`~selenv.core.linalg.validate_spd` alone would take 30 us per matrix), so the checks here
run a cheap test first and call the canonical validators of :mod:`selenv.core.linalg` only when
that test fails. The error messages are therefore exactly those of ``validate_spd``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg.lapack import dpotrf, dtrtrs

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

__all__ = [
    "FUSION_SHAPES",
    "Pair",
    "blame",
    "check_correction",
    "chol",
    "correction",
    "finite_matrix",
    "joint_covariance_is_admissible",
    "logdet_from_chol",
    "overflow_error",
    "pair",
    "root_increasing",
    "root_increasing_batch",
    "root_increasing_one",
    "spd",
    "tri_solve",
    "validate_pair",
    "vector",
]


IntArray = NDArray[np.intp]

#: shapes of the fusion arguments in symbols, for :func:`blame`
FUSION_SHAPES = {
    "P_i": "n_i n_i",
    "P_j": "n_j n_j",
    "H_i": "m n_i",
    "H_j": "m n_j",
    "R": "m m",
    "x_i": "n_i",
    "residual": "m",
    "C": "n_i n_j",
    "X": "n_i n_j",
}

#: ``norm2 = ||A||_F^2`` inside this interval makes the fast symmetry test exact enough (no
#: overflow, no underflow of the squared asymmetry) and bounds every entry by ``MAX_ABS``
_NORM2_LO, _NORM2_HI = 1e-250, MAX_ABS * MAX_ABS
#: ``min diag L`` above this implies ``min diag A >= MIN_PD_DIAG`` (``A_kk >= L_kk^2``)
_SQRT_MIN_PD_DIAG = math.sqrt(MIN_PD_DIAG)


def overflow_error(func: str) -> ValueError:
    """The error for a computation that overflowed float64 although its inputs were in range."""
    return ValueError(
        f"{func}: the result is not representable in float64 (overflow); the inputs must "
        f"satisfy |entry| <= {MAX_ABS:g} with positive-definite diagonals >= {MIN_PD_DIAG:g}, "
        "and the problem must not be so ill-conditioned that products or inverses of them "
        "exceed that range (rescale the problem, e.g. change units)"
    )


def blame(exc: ShapeError, **args: Any) -> ShapeError:
    """The shape error naming the argument that disagrees with the others, else ``exc``.

    ``args`` are the raw fusion arguments by name (see :data:`FUSION_SHAPES`); ``None`` skips.
    """
    return blame_shapes(args, {k: FUSION_SHAPES[k] for k in args}, error=exc) or exc


def spd(value: Any, name: str, n: int | None = None) -> tuple[FloatArray, FloatArray]:
    """Validate one SPD matrix and return it with its lower Cholesky factor ``(A, L)``.

    Fast path: ``||A - A^T||_F <= SYM_RTOL ||A||_F / d`` (which implies the max-norm test of
    ``validate_spd`` and is NaN-safe: a NaN/inf makes it false) with ``||A||_F^2`` in
    ``[1e-250, MAX_ABS^2]`` (so that every entry is within ``MAX_ABS``), LAPACK ``dpotrf`` and
    ``min diag L >= sqrt(MIN_PD_DIAG)`` (so that ``min diag A >= MIN_PD_DIAG``). Anything that
    fails it goes to ``validate_spd`` and ``check_magnitude``, which raise the canonical
    ``ValueError`` naming ``name`` (or accept a matrix inside their tolerance).

    Raises:
        TypeError: not real numeric (complex, bool, str, object).
        ValueError: wrong shape (a ``ShapeError``), NaN/inf, not symmetric, not positive
            definite, or outside the valid range.
    """
    A = as_float_array(value, name)
    if A.ndim != 2 or A.shape[0] != A.shape[1] or A.shape[0] == 0:
        A = validate_spd(A, name, n)
        if A.shape[0] == 0:
            raise ShapeError(f"{name} must be at least 1 x 1, got shape {A.shape}", name)
    elif n is not None and A.shape[0] != n:
        check_shape(A, (n, n), name)
    norm2 = float(np.vdot(A, A))  # NaN/inf propagate; vdot never warns (``@`` does)
    asym2 = math.nan  # the slow path unless A is finite, in range and symmetric enough
    if _NORM2_LO <= norm2 <= _NORM2_HI:  # finite: A - A^T cannot warn
        d = A - A.T
        asym2 = float(np.vdot(d, d))
    if not asym2 <= (SYM_RTOL / A.shape[0]) ** 2 * norm2:  # NaN compares false
        A = check_magnitude(validate_spd(A, name, n), name, definite=True)
    elif asym2 > 0.0:
        A = 0.5 * (A + A.T)
    L, info = dpotrf(A, lower=1, clean=1)
    if info != 0:
        validate_spd(A, name, n)  # raises "must be positive definite" with the eigenvalue
        raise ValueError(f"{name} must be positive definite (Cholesky failed, info={info})")
    if min(L.diagonal().tolist()) < _SQRT_MIN_PD_DIAG:
        check_magnitude(A, name, definite=True)
    return A, L


def finite_matrix(value: ArrayLike, name: str, shape: tuple[int | None, ...]) -> FloatArray:
    """Finite float64 array of ``shape`` (``None``: any length) with ``|entry| <= MAX_ABS``.

    Raises:
        TypeError: not real numeric.
        ValueError: wrong shape (a ``ShapeError``), NaN/inf or an entry beyond ``MAX_ABS``
            (names ``name``).
    """
    A = as_float_array(value, name)
    if A.ndim != len(shape) or any(
        w is not None and w != g for w, g in zip(shape, A.shape, strict=True)
    ):
        check_shape(A, shape, name)  # raises with the expected shape
    if not float(np.vdot(A, A)) <= _NORM2_HI:  # NaN/inf/overflow fall to the exact checks
        check_magnitude(check_finite(A, name), name)
    return A


def vector(value: ArrayLike, name: str, n: int) -> FloatArray:
    """Finite vector of shape ``(n,)`` (see :func:`finite_matrix`)."""
    return finite_matrix(value, name, (n,))


class Pair(NamedTuple):
    """Validated inputs of a relative-measurement update (see :func:`validate_pair`)."""

    P_i: FloatArray
    L_i: FloatArray
    P_j: FloatArray
    L_j: FloatArray
    H_i: FloatArray
    H_j: FloatArray
    R: FloatArray
    L_R: FloatArray


def validate_pair(
    P_i: ArrayLike, P_j: ArrayLike, H_i: ArrayLike, H_j: ArrayLike, R: ArrayLike, **extra: Any
) -> Pair:
    """Validate the inputs of a relative-measurement update.

    ``P_i`` (n_i, n_i), ``P_j`` (n_j, n_j) and ``R`` (m, m) SPD, ``H_i`` (m, n_i) and ``H_j``
    (m, n_j) finite, all within the valid range of :func:`~selenv.core.linalg.check_magnitude`.
    ``extra``: the caller's other arguments by name (``x_i``, ``residual``, ``C``, ``X``), only
    used to name the right argument when shapes disagree (they are validated by the caller).

    Raises:
        TypeError: an argument is not real numeric (complex, bool, str, object).
        ValueError: names the first bad argument; for shapes, the one that disagrees with the
            others (a ``ShapeError``).
    """
    try:
        Pi, Li = spd(P_i, "P_i")
        Pj, Lj = spd(P_j, "P_j")
        Hi = finite_matrix(H_i, "H_i", (None, Pi.shape[0]))
        if Hi.shape[0] == 0:
            raise ShapeError("H_i must have at least one row (m >= 1), got shape (0, n_i)", "H_i")
        m = Hi.shape[0]
        Hj = finite_matrix(H_j, "H_j", (m, Pj.shape[0]))
        Rm = as_float_array(R, "R")
        r = float(Rm[0, 0]) if m == 1 and Rm.shape == (1, 1) else math.nan
        if MIN_PD_DIAG <= r <= MAX_ABS:  # scalar noise (NaN fails)
            return Pair(Pi, Li, Pj, Lj, Hi, Hj, Rm, np.sqrt(Rm))
        Rm, LR = spd(Rm, "R", m)
    except ShapeError as exc:
        raise blame(exc, P_i=P_i, P_j=P_j, H_i=H_i, H_j=H_j, R=R, **extra) from None
    return Pair(Pi, Li, Pj, Lj, Hi, Hj, Rm, LR)


def pair(
    P_i: ArrayLike,
    P_j: ArrayLike,
    H_i: ArrayLike,
    H_j: ArrayLike,
    R: ArrayLike,
    *,
    validate: bool = True,
    **extra: Any,
) -> Pair:
    """:func:`validate_pair`, or with ``validate=False`` only conversion and the factors.

    ``validate=False`` is for hot paths whose inputs are known good (float64, right shapes,
    symmetric, finite, in range), as in :func:`selenv.core.kalman.kf_update`: it skips the
    shape, symmetry, finiteness and range checks, which dominate the cost of a scalar update;
    the types are still checked (a complex array raises ``TypeError``, it is never truncated)
    and a matrix that is not positive definite still raises (its Cholesky factor is needed).
    """
    if validate:
        return validate_pair(P_i, P_j, H_i, H_j, R, **extra)
    Pi, Pj = as_float_array(P_i, "P_i"), as_float_array(P_j, "P_j")
    Hi, Hj, Rm = as_float_array(H_i, "H_i"), as_float_array(H_j, "H_j"), as_float_array(R, "R")
    if Rm.shape == (1, 1):
        if not float(Rm[0, 0]) > 0.0:
            raise ValueError("R is not positive definite")
        LR = np.sqrt(Rm)
    else:
        LR = chol(Rm, "R")
    return Pair(Pi, chol(Pi, "P_i"), Pj, chol(Pj, "P_j"), Hi, Hj, Rm, LR)


def chol(A: FloatArray, name: str) -> FloatArray:
    """Lower Cholesky factor of an internal SPD matrix (``ValueError`` naming it if not PD)."""
    L, info = dpotrf(A, lower=1, clean=1)
    if info != 0:
        raise ValueError(f"{name} is not positive definite (Cholesky failed, info={info})")
    return L


def tri_solve(L: FloatArray, B: FloatArray, *, trans: bool = False) -> FloatArray:
    """``L^-1 B`` (or ``L^-T B`` with ``trans``) for lower-triangular ``L``, via LAPACK ``dtrtrs``.

    The scipy wrapper costs ~10 us per call in argument checks; this is ~1 us.
    """
    X, info = dtrtrs(L, B, lower=1, trans=1 if trans else 0)
    if info != 0:
        raise ValueError(f"triangular factor is singular (dtrtrs info={info})")
    return X


def logdet_from_chol(L: FloatArray) -> float:
    """``log det(L L^T) = 2 sum log diag L``."""
    return 2.0 * math.fsum(map(math.log, np.diagonal(L).tolist()))


def check_correction(
    x_i: ArrayLike | None, residual: ArrayLike | None, n: int, m: int
) -> tuple[FloatArray | None, FloatArray | None]:
    """Validate the optional ``x_i`` (n,) and ``residual`` (m,) before an update is solved.

    Raises:
        TypeError: not real numeric.
        ValueError: ``x_i`` without ``residual``, a wrong shape, NaN/inf or out of range.
    """
    if residual is None:
        if x_i is not None:
            raise ValueError("residual (z - z_hat, shape (m,)) is required when x_i is given")
        return None, None
    r = vector(residual, "residual", m)
    return (None if x_i is None else vector(x_i, "x_i", n)), r


def correction(
    K: FloatArray, x_i: ArrayLike | None, residual: ArrayLike | None
) -> tuple[FloatArray | None, FloatArray | None]:
    """State correction ``dx = K (z - z_hat)`` (eqs. 5a, 9a) and the posterior mean ``x_i + dx``.

    Returns ``(dx, x)``; ``dx`` is ``None`` without ``residual``; ``x`` is ``None`` without
    ``x_i``. Giving ``x_i`` without ``residual`` raises (there is nothing to correct it with).

    Raises:
        ValueError: as :func:`check_correction`, or a correction that overflows float64.
    """
    n, m = K.shape
    x_v, r_v = check_correction(x_i, residual, n, m)
    if r_v is None:
        return None, None
    dx = K @ r_v  # dx = K (z - z_hat)
    x = None if x_v is None else x_v + dx  # x+ = x- + K (z - z_hat)
    if not (np.all(np.isfinite(dx)) and (x is None or np.all(np.isfinite(x)))):
        raise ValueError(
            "the state correction K (z - z_hat) overflows float64; keep the inputs within "
            f"|entry| <= {MAX_ABS:g} and the problem well conditioned"
        )
    return dx, x


def joint_covariance_is_admissible(
    P_i: ArrayLike, P_j: ArrayLike, X: ArrayLike, *, tol: float = 1e-8
) -> bool:
    """Whether ``[[P_i, X], [X^T, P_j]]`` is a valid (PSD) joint covariance (eq. 8b, Lemma III.1).

    Tested through the contraction ``C = L_i^-1 X L_j^-T`` (``P = L L^T`` Cholesky): the joint
    matrix is PSD iff ``||C||_2 <= 1``; ``tol`` is the relative slack on that norm.

    Args:
        P_i: (n_i, n_i) SPD.
        P_j: (n_j, n_j) SPD.
        X: (n_i, n_j) cross-covariance.
        tol: accept ``||C||_2 <= 1 + tol``.

    Raises:
        TypeError: an argument is not real numeric.
        ValueError: bad shapes (naming the argument that disagrees), NaN/inf, non-SPD
            ``P_i``/``P_j`` or values outside the valid range.
    """
    try:
        Pi, Li = spd(P_i, "P_i")
        Pj, Lj = spd(P_j, "P_j")
        Xm = finite_matrix(X, "X", (Pi.shape[0], Pj.shape[0]))
    except ShapeError as exc:
        raise blame(exc, P_i=P_i, P_j=P_j, X=X) from None
    C = tri_solve(Lj, tri_solve(Li, Xm).T).T
    return bool(np.linalg.norm(C, 2) <= 1.0 + tol)


# --------------------------------------------------------------------------- 1-D root finders


def root_increasing(
    g: Callable[[float], tuple[float, float]],
    lo: float,
    hi: float,
    x0: float,
    xtol: float = 1e-15,
    maxiter: int = 200,
) -> float:
    """Root of ``g`` in ``(lo, hi)`` given ``g < 0`` near ``lo`` and ``g > 0`` near ``hi``.

    Safeguarded Newton (``rtsafe``): a Newton step on ``g(x), g'(x)`` when it stays inside the
    bracket and shrinks it fast enough, a bisection otherwise. ``g`` is never evaluated at the
    end points, so they may be singular. Used on the derivative of a convex 1-D cost
    (CI, DMV), which is increasing, or on a polynomial with one sign change in the bracket.
    """
    x, dxold, dx = x0, hi - lo, hi - lo
    f, df = g(x)
    for _ in range(maxiter):
        if f == 0.0:
            return x
        if f < 0.0:
            lo = x
        else:
            hi = x
        if df > 0.0 and abs(f) <= xtol * max(1.0, abs(x)) * df:  # Newton step below xtol
            return x - f / df
        newton_ok = df > 0.0 and lo < x - f / df < hi and abs(2.0 * f) <= abs(dxold * df)
        dxold = dx
        if newton_ok:
            dx = f / df
            x_new = x - dx
        else:
            dx = 0.5 * (hi - lo)
            x_new = lo + dx
        if x_new == x or abs(dx) <= xtol * max(1.0, abs(x_new)):
            return x_new
        x = x_new
        f, df = g(x)
    return x


def root_increasing_batch(
    g: Callable[[FloatArray, IntArray], tuple[FloatArray, FloatArray]],
    lo: FloatArray,
    hi: FloatArray,
    x0: FloatArray,
    xtol: float = 1e-15,
    maxiter: int = 200,
    scalar: Callable[[int], Callable[[float], tuple[float, float]]] | None = None,
    tail: int = 4,
) -> FloatArray:
    """Vectorised :func:`root_increasing` over a leading axis (same safeguards, per element).

    ``g(x, idx)`` evaluates the function for the items ``idx`` (indices into the leading axis)
    at ``x`` (same length as ``idx``). Converged items are dropped from the active set after
    every pass, so ``g`` only sees the items still iterating; each item's iterates are those
    of the full-batch iteration (``g`` must act row by row, as numpy's batched kernels do), so
    the roots are bit-identical to evaluating every item on every pass.

    ``scalar(i)``: optionally, ``g`` for item ``i`` alone in Python floats, bit-identical to
    the vectorised one; once at most ``tail`` items are left, each finishes its iteration
    through :func:`root_increasing_one`'s loop (same operations per element), which avoids
    paying numpy's per-call overhead for a whole pass on a handful of slow items.
    """
    x, lo, hi = x0.astype(np.float64), lo.astype(np.float64), hi.astype(np.float64)
    # Inside [-1, 1] (the weights w of DMV / PECMV), every iterate whose tolerance test can
    # decide anything lies in its bracket, so max(1, |x|) is exactly 1 and the tests below
    # compare with xtol itself: the same booleans for ~6 fewer numpy calls per pass.
    unit = x.size > 0 and bool(
        lo.min() >= -1.0 and hi.max() <= 1.0 and np.all((lo <= x) & (x <= hi))
    )
    out = x.copy()
    idx = np.arange(x.shape[0])
    dxold = hi - lo
    dx = dxold.copy()
    f, df = g(x, idx)
    passes = 0
    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(maxiter):
            live = f != 0.0  # f == 0: x is the root
            lo = np.where(f < 0.0, x, lo)  # (f < 0 and f > 0 imply live)
            hi = np.where(f > 0.0, x, hi)
            step = f / df
            x_step = x - step
            pos = df > 0.0
            conv = pos & (np.abs(step) <= (xtol if unit else xtol * np.maximum(1.0, np.abs(x))))
            newton = (x_step > lo) & (x_step < hi) & pos
            newton &= np.abs(2.0 * f) <= np.abs(dxold * df)
            newton |= conv
            dxold = dx
            half = 0.5 * (hi - lo)
            dx = np.where(newton, step, half)
            x_new = np.where(newton, x_step, lo + half)
            tol_new = xtol if unit else xtol * np.maximum(1.0, np.abs(x_new))
            done = conv | (x_new == x) | (np.abs(dx) <= tol_new)
            x = np.where(live, x_new, x)
            keep = live & ~done
            if not keep.all():  # drop the finished items
                out[idx] = x
                if not keep.any():
                    return out
                idx, x, lo, hi, dx, dxold = (v[keep] for v in (idx, x, lo, hi, dx, dxold))
            f, df = g(x, idx)
            passes += 1
            if scalar is not None and idx.shape[0] <= tail:
                for j, i in enumerate(idx.tolist()):
                    xj, loj, hij = float(x[j]), float(lo[j]), float(hi[j])
                    dxj, dxoldj, fj, dfj = float(dx[j]), float(dxold[j]), float(f[j]), float(df[j])
                    out[i] = _iterate_one(
                        scalar(i), xj, loj, hij, dxj, dxoldj, fj, dfj, xtol, maxiter - passes
                    )
                return out
    out[idx] = x
    return out


def _max1(a: float) -> float:
    """``np.maximum(1.0, a)`` for a float (NaN propagates, as in numpy)."""
    return a if (a >= 1.0 or a != a) else 1.0


def root_increasing_one(
    g: Callable[[float], tuple[float, float]],
    lo: float,
    hi: float,
    x0: float,
    xtol: float = 1e-15,
    maxiter: int = 200,
) -> float:
    """One item of :func:`root_increasing_batch` in Python floats (bit-identical to it).

    The same operations in the same order as the vectorised iteration on one element (IEEE
    ``+ - * /`` are correctly rounded in both), for batches of one where numpy's per-call
    overhead would dominate. (:func:`root_increasing` differs in its stopping test.)
    """
    f, df = g(x0)
    return _iterate_one(g, x0, lo, hi, hi - lo, hi - lo, f, df, xtol, maxiter)


def _iterate_one(
    g: Callable[[float], tuple[float, float]],
    x: float,
    lo: float,
    hi: float,
    dx: float,
    dxold: float,
    f: float,
    df: float,
    xtol: float,
    maxiter: int,
) -> float:
    """The loop of :func:`root_increasing_one` from a given state (``f, df = g(x)``)."""
    for _ in range(maxiter):
        if f == 0.0:
            return x
        if f < 0.0:
            lo = x
        elif f > 0.0:
            hi = x
        conv = newton = False
        step = 0.0
        if df > 0.0:  # otherwise the step is unused (and f / df could divide by zero)
            step = f / df
            conv = abs(step) <= xtol * _max1(abs(x))
            newton = lo < x - step < hi and abs(2.0 * f) <= abs(dxold * df)
        dxold = dx
        half = 0.5 * (hi - lo)
        if newton or conv:
            dx, x_new = step, x - step
        else:
            dx, x_new = half, lo + half
        done = conv or x_new == x or abs(dx) <= xtol * _max1(abs(x_new))
        x = x_new
        if done:
            return x
        f, df = g(x)
    return x
