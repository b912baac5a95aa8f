"""Linear-algebra helpers shared by every estimator in selenv.

One shape convention throughout: matrices are ``(..., n, n)`` with any number of leading batch
axes, vectors are ``(..., n)``. Symmetric positive-definite (SPD) matrices are factored with
Cholesky (``A = L L^T``, ``L`` lower triangular) and never inverted where a solve works.

Validation helpers raise ``ValueError`` (bad values) or ``TypeError`` (not array-like) that name
the argument and say what was expected; they never repair their input silently.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solve_triangular
from scipy.linalg.lapack import dpotrf, dtrtri

FloatArray = NDArray[np.float64]

#: relative tolerance for the symmetry check ``|A - A^T| <= SYM_RTOL * max|A|``
SYM_RTOL = 1e-8

__all__ = [
    "FloatArray",
    "as_float_array",
    "check_finite",
    "check_shape",
    "cholesky_small",
    "cholesky_spd",
    "inv_lower_small",
    "logdet_spd",
    "solve_spd",
    "symmetrize",
    "validate_spd",
]


def as_float_array(value: Any, name: str) -> FloatArray:
    """Convert ``value`` to a float64 array, raising ``TypeError`` naming ``name`` if impossible."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be a real numeric array, got {type(value).__name__}") from exc
    return arr


def check_finite(arr: FloatArray, name: str) -> FloatArray:
    """Raise ``ValueError`` if ``arr`` holds NaN or inf; return it unchanged otherwise."""
    if not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise ValueError(f"{name} must be finite, but {bad} entries are NaN or inf")
    return arr


def check_shape(arr: FloatArray, shape: tuple[int | None, ...], name: str) -> FloatArray:
    """Check ``arr.shape`` against ``shape`` where ``None`` matches any length.

    Raises:
        ValueError: naming ``name``, the expected and the actual shape.
    """
    ok = arr.ndim == len(shape) and all(
        want is None or want == got for want, got in zip(shape, arr.shape, strict=True)
    )
    if not ok:
        expected = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {expected}, got {arr.shape}")
    return arr


def symmetrize(A: FloatArray) -> FloatArray:
    """Return ``(A + A^T) / 2`` over the last two axes (removes round-off asymmetry only)."""
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def validate_spd(
    value: Any, name: str, n: int | None = None, *, batch: bool = False, semidefinite: bool = False
) -> FloatArray:
    """Validate a symmetric positive-definite matrix (or a batch of them).

    Args:
        value: array-like of shape ``(n, n)``, or ``(B, n, n)`` when ``batch`` is true.
        name: argument name used in error messages.
        n: required matrix size, or ``None`` for any.
        batch: accept one leading batch axis.
        semidefinite: accept positive semi-definite matrices (e.g. a rank-deficient process
            noise ``Q``); eigenvalues down to ``-SYM_RTOL * max|A|`` are accepted as zero.

    Returns:
        The matrix as float64, exactly symmetrized (round-off only; asymmetry above
        ``SYM_RTOL`` raises instead).

    Raises:
        TypeError: not numeric.
        ValueError: wrong shape, NaN/inf, not symmetric, or not positive definite.
    """
    A = as_float_array(value, name)
    check_shape(A, ((None,) if batch else ()) + (n, n), name)
    if A.shape[-1] != A.shape[-2]:
        raise ValueError(f"{name} must be square, got shape {A.shape}")
    check_finite(A, name)
    scale = max(float(np.max(np.abs(A))), 1e-300) if A.size else 1.0
    asym = float(np.max(np.abs(A - np.swapaxes(A, -1, -2)))) if A.size else 0.0
    if asym > SYM_RTOL * scale:
        raise ValueError(
            f"{name} must be symmetric: max |A - A^T| = {asym:.3g} exceeds "
            f"{SYM_RTOL:g} x max|A| = {SYM_RTOL * scale:.3g}"
        )
    A = symmetrize(A)
    if semidefinite:
        lo = float(np.min(np.linalg.eigvalsh(A))) if A.size else 0.0
        if lo < -SYM_RTOL * scale:
            raise ValueError(
                f"{name} must be positive semi-definite, but its smallest eigenvalue is {lo:.3g}"
            )
        return A
    try:
        np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        eig = np.linalg.eigvalsh(A)
        raise ValueError(
            f"{name} must be positive definite, but its smallest eigenvalue is {eig.min():.3g}"
        ) from None
    return A


def cholesky_spd(A: FloatArray, name: str = "matrix") -> FloatArray:
    """Lower Cholesky factor ``L`` with ``A = L L^T``, batched over leading axes.

    Raises:
        ValueError: if ``A`` is not positive definite (names ``name``).
    """
    try:
        L: FloatArray = np.linalg.cholesky(A).astype(np.float64, copy=False)
    except np.linalg.LinAlgError:
        raise ValueError(f"{name} is not positive definite (Cholesky failed)") from None
    return L


def logdet_spd(A: FloatArray, name: str = "matrix") -> FloatArray | float:
    """``log det A`` of SPD ``A`` via Cholesky: ``2 sum log diag L``; batched over leading axes."""
    L = cholesky_spd(A, name)
    out = 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
    return float(out) if np.ndim(out) == 0 else out


def solve_spd(A: FloatArray, B: FloatArray, name: str = "matrix") -> FloatArray:
    """Solve ``A X = B`` for SPD ``A`` (n, n), ``B`` (n,) or (n, k), by two triangular solves."""
    L = cholesky_spd(A, name)
    Y = solve_triangular(L, B, lower=True, check_finite=False)
    return solve_triangular(L.T, Y, lower=False, check_finite=False)


def cholesky_small(A: FloatArray, name: str = "matrix") -> FloatArray:
    """Lower Cholesky factor of one small SPD matrix straight from LAPACK ``dpotrf``.

    Same result as :func:`cholesky_spd` without NumPy's per-call overhead (about 1 us instead
    of 4 us at d = 7); for the hot path of the env step.

    Raises:
        ValueError: if ``A`` is not positive definite (names ``name``).
    """
    L, info = dpotrf(A, lower=1, clean=1)
    if info != 0:
        raise ValueError(f"{name} is not positive definite (Cholesky failed, info={info})")
    return L


def inv_lower_small(L: FloatArray) -> FloatArray:
    """``L^-1`` of a small non-singular lower-triangular factor (LAPACK ``dtrtri``).

    A triangular solve against the identity; used where the inverse factor itself is the
    object being propagated (``L'^-1 = C^-1 L^-1``), never to solve a linear system.
    """
    Linv, info = dtrtri(L, lower=1)
    if info != 0:
        raise ValueError(f"triangular factor is singular (dtrtri info={info})")
    return Linv
