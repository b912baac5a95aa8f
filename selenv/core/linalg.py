"""Linear-algebra helpers shared by every estimator in selenv.

One shape convention throughout: matrices are ``(..., n, n)`` with any number of leading batch
axes, vectors are ``(..., n)``. Symmetric positive-definite (SPD) matrices are factored with
Cholesky (``A = L L^T``, ``L`` lower triangular) and never inverted where a solve works.

Validation helpers raise ``ValueError`` (bad values) or ``TypeError`` (wrong type: not a real
number, e.g. complex, bool, str, object) that name the argument and say what was expected; they
never repair their input silently (no truncation of complex values, no clipping, no
symmetrizing beyond round-off). This module is the one validation layer the estimators share:
:func:`as_float_array` (types), :func:`check_shape` / :func:`blame_shapes` (shapes, naming the
argument that disagrees with the others), :func:`check_finite`, :func:`check_magnitude` (the
valid range ``MAX_ABS`` / ``MIN_PD_DIAG``) and :func:`validate_spd`; the factorisations
(:func:`cholesky_spd`, :func:`logdet_spd`, :func:`solve_spd`, :func:`cholesky_small`) refuse
NaN/inf and asymmetric input instead of reading one triangle.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Collection, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solve_triangular
from scipy.linalg.lapack import dpotrf, dtrtri

FloatArray = NDArray[np.float64]

#: relative tolerance for the symmetry check ``|A - A^T| <= SYM_RTOL * max|A|``
SYM_RTOL = 1e-8

#: valid range of the estimators' inputs (Kalman, fusion, FIM, CRLB, Riccati, MAP): every
#: entry ``|a| <= MAX_ABS`` and every diagonal entry of a positive-definite input
#: ``>= MIN_PD_DIAG``, see :func:`check_magnitude`
MAX_ABS = 1e100
MIN_PD_DIAG = 1e-100

_F64 = np.dtype(np.float64)
_MAX_ABS2 = MAX_ABS * MAX_ABS

__all__ = [
    "MAX_ABS",
    "MIN_PD_DIAG",
    "SYM_RTOL",
    "FloatArray",
    "ShapeError",
    "all_finite",
    "as_float_array",
    "blame_shapes",
    "check_finite",
    "check_magnitude",
    "check_shape",
    "cholesky_small",
    "cholesky_spd",
    "inv_lower_small",
    "logdet_spd",
    "solve_spd",
    "symmetrize",
    "validate_spd",
]


def _dtype_words(dtype: np.dtype[Any]) -> str:
    return {"b": "bool", "U": "str", "S": "bytes", "O": "object", "M": "datetime64"}.get(
        dtype.kind, str(dtype)
    )


def as_float_array(value: Any, name: str) -> FloatArray:
    """Convert ``value`` to a float64 array; only real numbers (float, int, uint) are accepted.

    The dtype is checked *before* casting, so nothing is truncated: a complex array is refused
    even when every imaginary part is zero (``np.asarray(z, float)`` would drop it with only a
    ``ComplexWarning``), and so are bools, strings, ``None`` and object arrays (``"1.5"`` or
    ``True`` are not numbers here). Returns ``value`` itself when it already is a float64
    ndarray (no copy; callers never write into it).

    Raises:
        TypeError: naming ``name``: complex (``"x must be real, got complex128"``), bool, str,
            bytes, object or other non-real dtype, or a ragged nesting that is not an array.
    """
    if type(value) is np.ndarray:
        arr = value
    else:
        try:
            arr = np.asarray(value)
        except (TypeError, ValueError, OverflowError) as exc:
            raise TypeError(
                f"{name} must be a real numeric array, got {type(value).__name__} that is "
                f"not one ({exc})"
            ) from None
    dt = arr.dtype
    if dt is _F64:
        return arr
    kind = dt.kind
    if kind == "c":
        raise TypeError(f"{name} must be real, got {dt}")
    if kind not in "fiu":
        raise TypeError(f"{name} must be a real numeric array, got dtype {_dtype_words(dt)}")
    return arr.astype(np.float64)


def check_finite(arr: FloatArray, name: str) -> FloatArray:
    """Raise ``ValueError`` if ``arr`` holds NaN or inf; return it unchanged otherwise.

    ``arr`` is normally a float64 array already; anything else is converted by
    :func:`as_float_array` first (and returned converted).

    Raises:
        TypeError: ``arr`` is not real numeric (names ``name``).
        ValueError: NaN or inf entries (names ``name`` and how many).
    """
    if type(arr) is not np.ndarray or arr.dtype is not _F64:
        arr = as_float_array(arr, name)
    # one ``vdot`` (no warning on NaN / overflow); the exact test only when it is not finite
    if not math.isfinite(float(np.vdot(arr, arr))) and not np.isfinite(arr).all():
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise ValueError(f"{name} must be finite, but {bad} entries are NaN or inf")
    return arr


def check_magnitude(arr: FloatArray, name: str, *, definite: bool = False) -> FloatArray:
    """Check the valid range of an estimator input: ``|entry| <= MAX_ABS``.

    With ``definite`` (a positive-definite matrix, or a batch of them, or a vector of
    variances) the diagonal must also be ``>= MIN_PD_DIAG``: its inverse and square root are
    formed. Inside these bounds the products of three inputs and the inverses that the
    estimators form stay representable in float64; outside, they would overflow to inf/NaN
    (or underflow to a singular matrix) deep inside. ``arr`` must be finite.

    Fast path: ``sum(a^2) <= MAX_ABS^2`` bounds every entry (one ``np.vdot``, which, unlike
    ``@``, raises no ``RuntimeWarning`` when it overflows); the exact maximum is only computed
    when that test fails.

    Raises:
        ValueError: naming ``name``, the offending value and the valid range.
    """
    if arr.size == 0:
        return arr
    if not float(np.vdot(arr, arr)) <= _MAX_ABS2:  # vdot: no FP warning on overflow
        big = float(np.max(np.abs(arr)))
        if big > MAX_ABS:
            raise ValueError(
                f"{name} has an entry of magnitude {big:.3g}; the valid range is |entry| <= "
                f"{MAX_ABS:g} (rescale the problem, e.g. change units)"
            )
    if definite:
        diag = np.diagonal(arr, axis1=-2, axis2=-1) if arr.ndim >= 2 else arr
        small = min(diag.ravel().tolist()) if diag.size else MIN_PD_DIAG
        if small < MIN_PD_DIAG:
            raise ValueError(
                f"{name} has a diagonal entry {small:.3g}; a positive-definite {name} needs "
                f"diagonal entries in [{MIN_PD_DIAG:g}, {MAX_ABS:g}] (rescale the problem)"
            )
    return arr


def all_finite(*arrays: Any) -> bool:
    """Whether every array (or float) is finite: one ``np.vdot`` each, exact only on failure.

    ``np.vdot`` flattens and, unlike ``@``, raises no ``RuntimeWarning`` on overflow or NaN.
    """
    for a in arrays:
        if type(a) is float:
            if not math.isfinite(a):
                return False
            continue
        if not math.isfinite(float(np.vdot(a, a))) and not bool(np.all(np.isfinite(a))):
            return False
    return True


class ShapeError(ValueError):
    """A ``ValueError`` about an argument's shape (raised by :func:`check_shape`).

    Validators catch it to run :func:`blame_shapes` over all their arguments, so that the
    argument that disagrees with the others is named, not the one checked last.

    Attributes:
        name: the argument the message is about (``None`` if not recorded).
    """

    def __init__(self, message: str, name: str | None = None) -> None:
        super().__init__(message)
        self.name = name


def check_shape(arr: FloatArray, shape: tuple[int | None, ...], name: str) -> FloatArray:
    """Check ``arr.shape`` against ``shape`` where ``None`` matches any length.

    Raises:
        TypeError: ``arr`` is not real numeric, or ``shape`` is not a tuple of ints / ``None``.
        ShapeError: (a ``ValueError``) naming ``name``, the expected and the actual shape.
    """
    if type(arr) is not np.ndarray:
        arr = as_float_array(arr, name)
    if not isinstance(shape, tuple) or not all(
        s is None or (isinstance(s, int | np.integer) and not isinstance(s, bool)) for s in shape
    ):
        raise TypeError(f"shape must be a tuple of ints or None, got {shape!r}")
    ok = arr.ndim == len(shape) and all(
        want is None or want == got for want, got in zip(shape, arr.shape, strict=True)
    )
    if not ok:
        expected = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ShapeError(f"{name} must have shape {expected}, got {arr.shape}", name)
    return arr


def _fmt(template: tuple[str, ...], values: Mapping[str, int] | None = None) -> str:
    vals = values or {}
    parts = [str(vals.get(s, s)) if s != "*" else "*" for s in template]
    return "(" + ", ".join(parts) + ("," if len(parts) == 1 else "") + ")"


def blame_shapes(
    args: Mapping[str, Any],
    templates: Mapping[str, str | Sequence[str]],
    *,
    batch: Collection[str] = (),
    fixed: Mapping[str, int] | None = None,
    error: ShapeError | None = None,
) -> ShapeError | None:
    """Find the argument whose shape disagrees with the others (for error messages only).

    Every dimension symbol (``n``, ``m``, ``B``, ...) takes the value that most arguments give
    it (one vote per argument), so one wrong argument is blamed by name however the checks are
    ordered. Called by validators after a cheap check failed (``error``); never on the
    success path.

    Args:
        args: argument name -> value (in argument order; ``None`` values are skipped).
        templates: name -> accepted shapes, as space-separated symbols: ``"n n"``,
            ``"B m n"``, ``""`` (a scalar), ``"*"`` (any length), digits (that length), a
            leading ``"..."`` (any leading batch axes). Alternatives must differ in ndim.
        batch: arguments whose template without a leading ``B`` means *unbatched*: they vote
            for "no batch axis" (others, e.g. a shared ``H``, do not).
        fixed: symbols whose value is already known (e.g. ``n`` of a filter's state).
        error: the error the validator raised. It is returned unchanged when it already names
            the argument at fault, and extended with the other side when two sides have
            equally many votes (the wrong one cannot be told apart: both are named).

    Returns:
        A :class:`ShapeError` naming the wrong argument (or, on a tie, every argument
        involved); ``error`` if the diagnosis agrees with it or finds nothing.
    """
    found = _diagnose(args, templates, batch, fixed or {})
    if found is None:
        return error
    kind, names, message = found
    if error is not None and error.name in names:
        if kind == "tie":
            return ShapeError(f"{error} ({message})", error.name)
        return error
    return ShapeError(message, names[0])


_Match = tuple[tuple[str, ...], tuple[int, ...], bool]  # (template core, its axes, has "...")
_Problem = tuple[str, list[str], str]  # (kind, names, message)


def _match_templates(
    args: Mapping[str, Any], templates: Mapping[str, str | Sequence[str]]
) -> tuple[dict[str, _Match], _Problem | None]:
    """The first template alternative each argument's number of axes fits, or an ndim problem."""
    chosen: dict[str, _Match] = {}
    for name, value in args.items():
        if value is None:
            continue
        try:
            shape = tuple(int(s) for s in np.shape(value))
        except (TypeError, ValueError):
            continue
        spec = templates[name]
        alts: list[str] = [spec] if isinstance(spec, str) else list(spec)
        parsed = [tuple(a.split()) for a in alts]
        match = None
        for t in parsed:
            ell = bool(t) and t[0] == "..."
            core = t[1:] if ell else t
            if len(shape) == len(core) or (ell and len(shape) >= len(core)):
                match = (core, shape[len(shape) - len(core) :], ell)
                break
        if match is None:
            want = " or ".join(_fmt(t) for t in parsed)
            return chosen, ("ndim", [name], f"{name} must have shape {want}, got {shape}")
        chosen[name] = match
    return chosen, None


def _vote(
    chosen: Mapping[str, _Match], batch: Collection[str], known: dict[str, int]
) -> tuple[dict[str, list[tuple[str, int]]], dict[str, list[str]]]:
    """Each symbol's length by majority of the arguments (one vote per argument and symbol).

    An argument inconsistent by itself abstains. ``known`` gains the decided lengths; returns
    the votes and the symbols whose vote is a tie (with the arguments involved).
    """
    votes: dict[str, list[tuple[str, int]]] = {}
    for name, (core, shape, _) in chosen.items():
        own: dict[str, set[int]] = {}
        for sym, got in zip(core, shape, strict=True):
            if sym != "*" and not sym.isdigit():
                own.setdefault(sym, set()).add(got)
        if name in batch and "B" not in core:
            own["B"] = {-1}  # "no batch axis"
        for sym, vals in own.items():
            if len(vals) == 1 and sym not in known:
                votes.setdefault(sym, []).append((name, next(iter(vals))))
    ties: dict[str, list[str]] = {}
    for sym, claims in votes.items():
        ranked = Counter(v for _, v in claims).most_common()
        if len(ranked) > 1 and ranked[0][1] == ranked[1][1]:
            ties[sym] = [n for n, _ in claims]
        else:
            known[sym] = ranked[0][0]
    return votes, ties


def _blame(
    args: Mapping[str, Any],
    chosen: Mapping[str, _Match],
    batch: Collection[str],
    known: Mapping[str, int],
    votes: Mapping[str, list[tuple[str, int]]],
    ties: Mapping[str, list[str]],
) -> _Problem | None:
    """The first argument in a tie, or whose shape disagrees with the decided lengths."""
    for name, (core, shape, ell) in chosen.items():
        for sym, involved in ties.items():
            if name in involved:
                what = "the batch axis" if sym == "B" else f"the length {sym}"
                sides = ", ".join(f"{n} has shape {np.shape(args[n])}" for n in involved)
                return "tie", involved, f"{' and '.join(involved)} disagree on {what}: {sides}"
        template = core
        if name in batch and known.get("B") == -1 and core[:1] == ("B",):
            template = core[1:]  # the others are unbatched: so must this be
        elif name in batch and known.get("B", -1) >= 0 and core[:1] != ("B",):
            template = ("B", *core)
        dims = [int(s) if s.isdigit() else known.get(s, -2) for s in template]
        ok = len(dims) == len(shape) and all(w in (-2, g) for w, g in zip(dims, shape, strict=True))
        if not ok:
            others = sorted({n for s in template for n, _ in votes.get(s, []) if n != name})
            why = f" (to match {', '.join(others)})" if others else ""
            shown = _fmt(template, known)
            if ell:
                shown = "(..., " + shown[1:].rstrip(",)") + ")"
            got = np.shape(args[name])
            return "blame", [name], f"{name} must have shape {shown}, got {got}{why}"
    return None


def _diagnose(
    args: Mapping[str, Any],
    templates: Mapping[str, str | Sequence[str]],
    batch: Collection[str],
    fixed: Mapping[str, int],
) -> _Problem | None:
    """``(kind, names, message)`` of the first shape problem of :func:`blame_shapes`.

    Three passes: match each argument to a template by its number of axes, decide every
    symbol's length by majority vote, then blame the first argument that disagrees.
    """
    chosen, problem = _match_templates(args, templates)
    if problem is not None:
        return problem
    known = dict(fixed)
    votes, ties = _vote(chosen, batch, known)
    return _blame(args, chosen, batch, known, votes, ties)


def symmetrize(A: FloatArray) -> FloatArray:
    """Return ``(A + A^T) / 2`` over the last two axes (removes round-off asymmetry only).

    Raises:
        TypeError: ``A`` is not real numeric.
        ValueError: ``A`` is not ``(..., n, n)``.
    """
    if type(A) is not np.ndarray or A.dtype is not _F64 or A.ndim < 2 or A.shape[-1] != A.shape[-2]:
        A = _square(A, "A")
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
        TypeError: not real numeric (complex, bool, str, object), or ``n`` not an int.
        ValueError: wrong shape (a :class:`ShapeError`), NaN/inf, not symmetric, or not
            positive definite.
    """
    if n is not None and (isinstance(n, bool) or not isinstance(n, int | np.integer)):
        raise TypeError(f"n must be an int or None, got {n!r}")
    A = as_float_array(value, name)
    check_shape(A, ((None,) if batch else ()) + (n, n), name)
    if A.shape[-1] != A.shape[-2]:
        raise ShapeError(f"{name} must be square, got shape {A.shape}", name)
    check_finite(A, name)
    scale = _check_symmetric(A, name)
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


def _check_symmetric(A: FloatArray, name: str) -> float:
    """``max |A - A^T| <= SYM_RTOL max|A|`` over the last two axes of a finite ``A``.

    Returns ``max(max|A|, 1e-300)`` (1 for an empty ``A``), the scale of the tolerances.
    """
    if not A.size:
        return 1.0
    scale = max(float(np.max(np.abs(A))), 1e-300)
    asym = float(np.max(np.abs(A - np.swapaxes(A, -1, -2))))
    if asym > SYM_RTOL * scale:
        raise ValueError(
            f"{name} must be symmetric: max |A - A^T| = {asym:.3g} exceeds "
            f"{SYM_RTOL:g} x max|A| = {SYM_RTOL * scale:.3g}"
        )
    return scale


def _square(A: Any, name: str) -> FloatArray:
    """``A`` as a float64 ``(..., n, n)`` array (types and shape checked, values not)."""
    arr = as_float_array(A, name)
    if arr.ndim < 2 or arr.shape[-1] != arr.shape[-2]:
        raise ShapeError(f"{name} must have shape (..., n, n), got {arr.shape}", name)
    return arr


def _checked_input(A: FloatArray, name: str) -> FloatArray:
    """Slow path of the factorisations: finite and symmetric within ``SYM_RTOL``, symmetrized."""
    check_finite(A, name)
    _check_symmetric(A, name)
    return symmetrize(A)


def cholesky_spd(A: FloatArray, name: str = "matrix") -> FloatArray:
    """Lower Cholesky factor ``L`` with ``A = L L^T``, batched over leading axes.

    ``A`` must be symmetric: LAPACK reads one triangle only, so an asymmetric or half-NaN ``A``
    would otherwise be factored as if it were the symmetric matrix of its lower triangle.
    Fast path: an exactly symmetric ``A`` (byte-wise ``A == A^T``, NaN-safe through the
    finiteness test of the factor's diagonal); anything else is checked like
    :func:`validate_spd` (finite, asymmetry within ``SYM_RTOL``) and symmetrized.

    Raises:
        TypeError: ``A`` is not real numeric (names ``name``).
        ValueError: ``A`` is not ``(..., n, n)``, holds NaN/inf, is not symmetric, or is not
            positive definite (names ``name``).
    """
    A = _square(A, name)
    if A.tobytes() != np.swapaxes(A, -1, -2).tobytes():
        A = _checked_input(A, name)
    try:
        L: FloatArray = np.linalg.cholesky(A).astype(np.float64, copy=False)
    except np.linalg.LinAlgError:
        _checked_input(A, name)  # NaN/inf first: they are not "not positive definite"
        raise ValueError(_not_pd(name)) from None
    if not math.isfinite(float(np.sum(np.diagonal(L, axis1=-2, axis2=-1)))):
        _checked_input(A, name)
        raise ValueError(_not_pd(name))
    return L


def _not_pd(name: str) -> str:
    return (
        f"{name} is not positive definite (Cholesky failed; a positive-definite matrix whose "
        "condition number exceeds 1 / eps ~ 1e16 fails too: rescale or regularise it)"
    )


def logdet_spd(A: FloatArray, name: str = "matrix") -> FloatArray | float:
    """``log det A`` of SPD ``A`` via Cholesky: ``2 sum log diag L``; batched over leading axes.

    Raises:
        TypeError, ValueError: as :func:`cholesky_spd` (names ``name``).
    """
    L = cholesky_spd(A, name)
    out = 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
    return float(out) if np.ndim(out) == 0 else out


def solve_spd(A: FloatArray, B: FloatArray, name: str = "matrix") -> FloatArray:
    """Solve ``A X = B`` for SPD ``A`` (n, n), ``B`` (n,) or (n, k), by two triangular solves.

    Raises:
        TypeError: ``A`` or ``B`` not real numeric.
        ValueError: ``A`` as in :func:`cholesky_spd`; ``B`` of the wrong shape or not finite
            (named ``"B"``).
    """
    Am = _square(A, name)
    if Am.ndim != 2:
        raise ShapeError(f"{name} must have shape (n, n), got {Am.shape}", name)
    Bm = as_float_array(B, "B")
    if Bm.ndim not in (1, 2):
        raise ShapeError(f"B must have shape (n,) or (n, k), got {Bm.shape}", "B")
    if Bm.shape[0] != Am.shape[0]:  # two sides, one vote each: both are named
        raise ShapeError(
            f"{name} and B disagree on the length n: {name} has shape {Am.shape}, B has shape "
            f"{Bm.shape} (B must be ({Am.shape[0]},) or ({Am.shape[0]}, k))",
            "B",
        )
    check_finite(Bm, "B")
    L = cholesky_spd(Am, name)
    Y = solve_triangular(L, Bm, lower=True, check_finite=False)
    return solve_triangular(L.T, Y, lower=False, check_finite=False)


def cholesky_small(A: FloatArray, name: str = "matrix") -> FloatArray:
    """Lower Cholesky factor of one small SPD matrix straight from LAPACK ``dpotrf``.

    Same result as :func:`cholesky_spd` without NumPy's per-call overhead (about 2 us instead
    of 5 us at d = 7); for the hot path of the env step. The checks are those of
    :func:`cholesky_spd` at hot-path cost: the type by identity of the dtype, symmetry by a
    byte comparison of ``A`` with ``A^T`` (a NaN/inf then shows up on the factor's diagonal,
    which is tested), and only what fails them takes the slow path.

    Raises:
        TypeError: ``A`` is not real numeric (names ``name``).
        ValueError: ``A`` is not square, holds NaN/inf, is not symmetric, or is not positive
            definite (names ``name``).
    """
    if type(A) is not np.ndarray or A.dtype is not _F64 or A.ndim != 2:
        A = _square(A, name)
        if A.ndim != 2:
            raise ShapeError(f"{name} must have shape (n, n), got {A.shape}", name)
    elif A.shape[0] != A.shape[1]:
        raise ShapeError(f"{name} must be square, got shape {A.shape}", name)
    if A.tobytes() != A.T.tobytes():
        A = _checked_input(A, name)
    L, info = dpotrf(A, lower=1, clean=1)
    if info != 0 or not math.isfinite(sum(L.diagonal().tolist())):
        _checked_input(A, name)  # NaN/inf or asymmetry: the canonical message
        raise ValueError(f"{name} is not positive definite (Cholesky failed, info={info})")
    return L


def inv_lower_small(L: FloatArray) -> FloatArray:
    """``L^-1`` of a small non-singular lower-triangular factor (LAPACK ``dtrtri``).

    A triangular solve against the identity; used where the inverse factor itself is the
    object being propagated (``L'^-1 = C^-1 L^-1``), never to solve a linear system. ``L``
    comes from :func:`cholesky_small` (internal: not validated).

    Raises:
        TypeError: ``L`` is not real numeric.
        ValueError: ``L`` is not square, holds NaN/inf, or is singular.
    """
    if type(L) is not np.ndarray or L.dtype is not _F64 or L.ndim != 2 or L.shape[0] != L.shape[1]:
        L = _square(L, "L")
        if L.ndim != 2:
            raise ShapeError(f"L must have shape (n, n), got {L.shape}", "L")
    if not math.isfinite(sum(L.diagonal().tolist())):
        check_finite(L, "L")
    Linv, info = dtrtri(L, lower=1)
    if info != 0:
        raise ValueError(f"L (a triangular factor) is singular (dtrtri info={info})")
    if not all_finite(Linv):
        check_finite(L, "L")
        raise ValueError("L (a triangular factor) is too close to singular: L^-1 overflows")
    return Linv
