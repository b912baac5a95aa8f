"""The few numpy internals used on hot paths, each behind one guarded import with a public fallback.

``np.linalg.solve`` / ``np.linalg.cholesky`` spend a few microseconds in Python wrappers around
their gufuncs (``numpy.linalg._umath_linalg.solve`` / ``cholesky_lo``), and ``np.einsum``
around ``c_einsum``; for the many tiny problems of the filters that overhead dominates. These
names are private to numpy: if an import fails or a name is missing (another numpy release),
every function here falls back to the public one with the same results. ``FAST`` switches the
fast paths off (the tests run both paths against each other).

Tested with numpy 2.4 (the version CI installs); the fallbacks are exercised on every run by
``tests/test_numpy_fallbacks.py``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from selenv.core.linalg import FloatArray

__all__ = ["FAST", "cholesky_lo", "einsum", "has_fast_paths", "solve"]

_ul: Any = None
_c_einsum: Any = None
try:  # numpy >= 1.x: the gufuncs behind np.linalg
    from numpy.linalg import _umath_linalg as _ul
except ImportError:  # pragma: no cover - depends on the numpy release
    pass
try:  # numpy >= 2.0: np.einsum without ``optimize`` calls this
    from numpy._core.multiarray import c_einsum as _c_einsum
except ImportError:  # pragma: no cover - depends on the numpy release
    pass

_GESV: Callable[..., FloatArray] | None = getattr(_ul, "solve", None)
_CHOLESKY_LO: Callable[..., FloatArray] | None = getattr(_ul, "cholesky_lo", None)
_EINSUM: Callable[..., Any] | None = _c_einsum

#: use the private fast paths where they exist (tests set it to False to run the fallbacks)
FAST = True


def has_fast_paths() -> dict[str, bool]:
    """Which private fast paths this numpy provides (``solve``, ``cholesky_lo``, ``einsum``)."""
    return {
        "solve": _GESV is not None,
        "cholesky_lo": _CHOLESKY_LO is not None,
        "einsum": _EINSUM is not None,
    }


def solve(a: FloatArray, b: FloatArray) -> FloatArray:
    """``np.linalg.solve(a, b)`` for float64 stacks ``a`` ``(..., p, p)``, ``b`` ``(..., p, k)``.

    The fast path (LAPACK ``dgesv`` per matrix, the kernel ``np.linalg.solve`` calls) must run
    inside an ``np.errstate(call=..., invalid="call")`` that raises ``LinAlgError`` on a
    singular matrix, as ``np.linalg.solve`` sets it; the fallback raises ``LinAlgError`` itself.
    """
    if FAST and _GESV is not None:
        return _GESV(a, b, signature="dd->d")
    return np.asarray(np.linalg.solve(a, b), dtype=np.float64)


def cholesky_lo(a: FloatArray) -> FloatArray:
    """Lower Cholesky factors of float64 ``a`` ``(..., n, n)``; NaN-filled where one fails.

    Like the gufunc behind ``np.linalg.cholesky`` with floating-point errors ignored: an item
    that is not positive definite gives a NaN-filled factor instead of an exception. Call it
    inside ``np.errstate(invalid="ignore")`` to silence the fast path's warning.
    """
    if FAST and _CHOLESKY_LO is not None:
        return _CHOLESKY_LO(a, signature="d->d")
    try:
        return np.asarray(np.linalg.cholesky(a), dtype=np.float64)
    except np.linalg.LinAlgError:
        out = np.full(a.shape, np.nan)
        for idx in np.ndindex(*a.shape[:-2]):
            try:
                out[idx] = np.linalg.cholesky(a[idx])
            except np.linalg.LinAlgError:
                pass  # stays NaN, as the gufunc leaves it
        return out


def einsum(subscripts: str, *operands: FloatArray) -> Any:
    """``np.einsum(subscripts, *operands)`` (no ``optimize``), without its Python wrapper."""
    if FAST and _EINSUM is not None:
        return _EINSUM(subscripts, *operands)
    return np.einsum(subscripts, *operands)
