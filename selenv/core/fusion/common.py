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
from numpy.typing import ArrayLike
from scipy.linalg.lapack import dpotrf, dtrtrs

from selenv.core.linalg import (
    SYM_RTOL,
    FloatArray,
    as_float_array,
    check_finite,
    check_shape,
    validate_spd,
)

__all__ = [
    "Pair",
    "chol",
    "correction",
    "finite_matrix",
    "joint_covariance_is_admissible",
    "logdet_from_chol",
    "pair",
    "root_increasing",
    "root_increasing_batch",
    "spd",
    "tri_solve",
    "validate_pair",
    "vector",
]


def spd(value: Any, name: str, n: int | None = None) -> tuple[FloatArray, FloatArray]:
    """Validate one SPD matrix and return it with its lower Cholesky factor ``(A, L)``.

    Fast path: ``||A - A^T||_F <= SYM_RTOL ||A||_F / d`` (which implies the max-norm test of
    ``validate_spd`` and is NaN-safe: a NaN/inf makes it false) and LAPACK ``dpotrf``. Anything
    that fails it goes to ``validate_spd``, which raises the canonical ``ValueError`` naming
    ``name`` (or accepts a matrix inside its tolerance).
    """
    A = as_float_array(value, name)
    if A.ndim != 2 or A.shape[0] != A.shape[1] or A.shape[0] == 0:
        A = validate_spd(A, name, n)
        if A.shape[0] == 0:
            raise ValueError(f"{name} must be at least 1 x 1, got shape {A.shape}")
    elif n is not None and A.shape[0] != n:
        check_shape(A, (n, n), name)
    d = A - A.T
    fa = A.ravel()
    asym2, norm2 = float(d.ravel() @ d.ravel()), float(fa @ fa)
    if not asym2 <= (SYM_RTOL / A.shape[0]) ** 2 * norm2:  # NaN-safe
        A = validate_spd(A, name, n)
    elif asym2 > 0.0:
        A = 0.5 * (A + A.T)
    L, info = dpotrf(A, lower=1, clean=1)
    if info != 0:
        validate_spd(A, name, n)  # raises "must be positive definite" with the eigenvalue
        raise ValueError(f"{name} must be positive definite (Cholesky failed, info={info})")
    return A, L


def finite_matrix(value: ArrayLike, name: str, shape: tuple[int | None, ...]) -> FloatArray:
    """Finite float64 array of ``shape`` (``None`` matches any length); ``ValueError`` names it."""
    A = as_float_array(value, name)
    if A.ndim != len(shape) or any(
        w is not None and w != g for w, g in zip(shape, A.shape, strict=True)
    ):
        check_shape(A, shape, name)  # raises with the expected shape
    flat = A.ravel()
    if not np.isfinite(float(flat @ flat)):  # NaN/inf propagate; overflow falls to the check
        check_finite(A, name)
    return A


def vector(value: ArrayLike, name: str, n: int) -> FloatArray:
    """Finite vector of shape ``(n,)``."""
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
    P_i: ArrayLike, P_j: ArrayLike, H_i: ArrayLike, H_j: ArrayLike, R: ArrayLike
) -> Pair:
    """Validate the inputs of a relative-measurement update.

    ``P_i`` (n_i, n_i), ``P_j`` (n_j, n_j) and ``R`` (m, m) SPD, ``H_i`` (m, n_i) and ``H_j``
    (m, n_j) finite; ``m`` is taken from ``H_i``. ``ValueError`` names the first bad argument.
    """
    Pi, Li = spd(P_i, "P_i")
    Pj, Lj = spd(P_j, "P_j")
    Hi = finite_matrix(H_i, "H_i", (None, Pi.shape[0]))
    if Hi.shape[0] == 0:
        raise ValueError("H_i must have at least one row (m >= 1), got shape (0, n_i)")
    m = Hi.shape[0]
    Hj = finite_matrix(H_j, "H_j", (m, Pj.shape[0]))
    Rm = as_float_array(R, "R")
    if m == 1 and Rm.shape == (1, 1) and 0.0 < float(Rm[0, 0]) < math.inf:  # scalar noise
        return Pair(Pi, Li, Pj, Lj, Hi, Hj, Rm, np.sqrt(Rm))
    Rm, LR = spd(Rm, "R", m)
    return Pair(Pi, Li, Pj, Lj, Hi, Hj, Rm, LR)


def pair(
    P_i: ArrayLike,
    P_j: ArrayLike,
    H_i: ArrayLike,
    H_j: ArrayLike,
    R: ArrayLike,
    *,
    validate: bool = True,
) -> Pair:
    """:func:`validate_pair`, or with ``validate=False`` only conversion and the factors.

    ``validate=False`` is for hot paths whose inputs are known good (float64, right shapes,
    symmetric, finite), as in :func:`selenv.core.kalman.kf_update`: it skips the shape,
    symmetry and finiteness checks, which dominate the cost of a scalar update; a matrix that
    is not positive definite still raises (its Cholesky factor is needed anyway).
    """
    if validate:
        return validate_pair(P_i, P_j, H_i, H_j, R)
    Pi, Pj, Hi, Hj, Rm = (np.asarray(a, dtype=np.float64) for a in (P_i, P_j, H_i, H_j, R))
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


def correction(
    K: FloatArray, x_i: ArrayLike | None, residual: ArrayLike | None
) -> tuple[FloatArray | None, FloatArray | None]:
    """State correction ``dx = K (z - z_hat)`` (eqs. 5a, 9a) and the posterior mean ``x_i + dx``.

    Returns ``(dx, x)``; ``dx`` is ``None`` without ``residual``; ``x`` is ``None`` without
    ``x_i``. Giving ``x_i`` without ``residual`` raises (there is nothing to correct it with).
    """
    n, m = K.shape
    if residual is None:
        if x_i is not None:
            raise ValueError("residual (z - z_hat, shape (m,)) is required when x_i is given")
        return None, None
    dx = K @ vector(residual, "residual", m)  # dx = K (z - z_hat)
    if x_i is None:
        return dx, None
    return dx, vector(x_i, "x_i", n) + dx  # x+ = x- + K (z - z_hat)


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
    """
    Pi, Li = spd(P_i, "P_i")
    Pj, Lj = spd(P_j, "P_j")
    Xm = finite_matrix(X, "X", (Pi.shape[0], Pj.shape[0]))
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
    g: Callable[[FloatArray], tuple[FloatArray, FloatArray]],
    lo: FloatArray,
    hi: FloatArray,
    x0: FloatArray,
    xtol: float = 1e-15,
    maxiter: int = 200,
) -> FloatArray:
    """Vectorised :func:`root_increasing` over a leading axis (same safeguards, per element)."""
    x, lo, hi = x0.astype(np.float64), lo.astype(np.float64), hi.astype(np.float64)
    dxold = hi - lo
    dx = dxold.copy()
    active = np.ones(x.shape, dtype=bool)
    f, df = g(x)
    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(maxiter):
            active &= f != 0.0
            lo = np.where(active & (f < 0.0), x, lo)
            hi = np.where(active & (f > 0.0), x, hi)
            step = f / df
            conv = (df > 0.0) & (np.abs(step) <= xtol * np.maximum(1.0, np.abs(x)))
            newton = (x - step > lo) & (x - step < hi) & (df > 0.0)
            newton &= np.abs(2.0 * f) <= np.abs(dxold * df)
            newton |= conv
            dxold = dx
            dx = np.where(newton, step, 0.5 * (hi - lo))
            x_new = np.where(newton, x - step, lo + 0.5 * (hi - lo))
            done = conv | (x_new == x) | (np.abs(dx) <= xtol * np.maximum(1.0, np.abs(x_new)))
            x = np.where(active, x_new, x)
            active &= ~done
            if not active.any():
                break
            f, df = g(x)
    return x
