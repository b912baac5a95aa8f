"""A rounding-proof certificate that a returned covariance is positive definite.

Every fused or updated covariance that the core returns (Kalman / EKF updates, covariance
intersection, DMV, PECMV, their batched forms and the learned surrogates LDMV / LPECMV) passes
:func:`require_spd` first. The test is the one of Rump (2006, "Verification of positive
definiteness", BIT 46): if the floating-point Cholesky factorisation of ``C - tau I``
succeeds, where ``C = D^-1/2 A D^-1/2`` is the correlation matrix of ``A`` (unit diagonal,
``D = diag A``) and ``tau`` exceeds the accumulated rounding of the factorisation and of the
scaling (``~ (n + 1) n u + 2 n u`` for unit ``u = 2^-53``), then ``A`` -- the float64 matrix
actually returned -- is symmetric positive definite in exact arithmetic, with
``lambda_min(C) >= tau - O(n^2 u) > 0``. Which BLAS kernel computed the factorisation, and in
which order it summed, does not matter: the bound holds for every order, with or without fused
multiply-adds.

``tau`` is :data:`SPD_MARGIN` (``1e-12``, i.e. a correlation condition number below ~1e12)
for every ``n <= 45`` and ``4 (n + 2)^2 u`` beyond. The margin is far above the rounding of
the factorisation itself, so a matrix whose correlation matrix has its smallest eigenvalue a
factor 1e3 away from ``tau`` gets the same verdict on every machine.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg.lapack import dpotrf

from selenv.core.linalg import FloatArray

__all__ = ["SPD_MARGIN", "is_certified_spd", "require_spd", "spd_margin"]

#: smallest eigenvalue that the correlation matrix of a returned covariance must exceed
SPD_MARGIN = 1e-12

_U = 2.0**-53  # unit roundoff of float64


def spd_margin(n: int) -> float:
    """The shift ``tau`` of the certificate for an ``n x n`` matrix (see the module docstring)."""
    return max(SPD_MARGIN, 4.0 * (n + 2) ** 2 * _U)


def _shifted_correlation(A: FloatArray) -> FloatArray | None:
    """``D^-1/2 A D^-1/2 - tau I`` of ``A`` ``(..., n, n)``, or None if a diagonal is not > 0."""
    d = np.diagonal(A, axis1=-2, axis2=-1)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        if not bool(np.all(d > 0.0)) or not bool(np.all(np.isfinite(d))):
            return None  # NaN compares false: refused here too
        s = 1.0 / np.sqrt(d)
        C = A * s[..., :, None] * s[..., None, :]
    n = A.shape[-1]
    idx = np.arange(n)
    C[..., idx, idx] -= spd_margin(n)
    return C


def is_certified_spd(A: FloatArray) -> bool | np.ndarray:
    """Whether ``A`` ``(n, n)`` is certified SPD (a bool); ``(B, n, n)``: a ``(B,)`` bool array.

    ``A`` is read as symmetric (the lower triangle is used) and is not validated: it must be a
    float64 array. NaN / inf and non-positive diagonals are never certified.
    """
    if A.ndim == 2:  # the hot path: a few us (no errstate unless an entry could overflow)
        d = A.diagonal()
        dmin = float(d.min())
        if not dmin > 0.0 or not math.isfinite(float(d.max())):  # NaN compares false
            return False
        s = 1.0 / np.sqrt(d)
        if float(np.abs(A).max()) / dmin >= 1e300:  # C could overflow: the careful path
            Cs = _shifted_correlation(A)
            if Cs is None or not bool(np.all(np.isfinite(Cs))):
                return False
            C = Cs
        else:
            C = (A * s) * s[:, None]
            C.flat[:: A.shape[0] + 1] -= spd_margin(A.shape[0])
        _, info = dpotrf(C, lower=1, clean=0, overwrite_a=1)
        return bool(info == 0)
    flat = A.reshape(-1, *A.shape[-2:])
    out = np.zeros(flat.shape[0], dtype=bool)
    Cb = _shifted_correlation(flat)
    if Cb is None:  # find the bad items one by one (rare: only on failure)
        out[:] = [bool(is_certified_spd(a)) for a in flat]
        return out.reshape(A.shape[:-2])
    try:
        np.linalg.cholesky(Cb)
        out[:] = True
    except np.linalg.LinAlgError:
        out[:] = [bool(is_certified_spd(a)) for a in flat]
    return out.reshape(A.shape[:-2])


def require_spd(A: FloatArray, func: str, what: str = "the updated covariance") -> FloatArray:
    """Return ``A`` if it is certified SPD (see :func:`is_certified_spd`), else raise.

    Args:
        A: ``(n, n)`` or ``(B, n, n)`` float64 covariance(s) about to be returned.
        func: the public function, for the message.
        what: what ``A`` is, for the message.

    Raises:
        ValueError: ``A`` (or batch item ``b``) is not numerically positive definite.
    """
    ok = is_certified_spd(A)
    if A.ndim == 2 and ok:
        return A
    if A.ndim != 2 and bool(np.all(ok)):
        return A
    where = "" if A.ndim == 2 else f" (batch item {int(np.flatnonzero(~np.ravel(ok))[0])})"
    raise ValueError(
        f"{func}: {what}{where} is not numerically positive definite: its correlation matrix "
        f"D^-1/2 P D^-1/2 has an eigenvalue below {spd_margin(A.shape[-1]):.1e} (condition "
        "number above ~1e12) or a diagonal entry is not positive, so rounding decides its "
        "sign; rescale or regularise the problem (e.g. a larger R or a smaller prior P)"
    )
