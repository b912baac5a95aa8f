"""Kalman filter, extended Kalman filter and information-filter measurement updates.

Symbols follow FilterPy: state mean ``x`` (n,), covariance ``P`` (n, n), transition ``F`` (n, n),
process noise ``Q`` (n, n), measurement ``z`` (m,), measurement matrix ``H`` (m, n), measurement
noise ``R`` (m, m), innovation ``y`` (m,), innovation covariance ``S`` (m, m), gain ``K`` (n, m).

Batching: ``x`` (and ``z``, ``P``) may carry ONE leading batch axis of length ``B`` -- ``x``
(B, n), ``P`` (B, n, n), ``z`` (B, m). Model matrices ``F``, ``Q``, ``H``, ``R`` are then either
shared (unbatched) or given per batch element with the same ``B``. Every equation is evaluated
loop-free with broadcasting matmuls.

``S`` is factored once by Cholesky, ``S = L L^T``; the gain and the likelihood use triangular
solves with ``L`` and no matrix is ever inverted. The covariance update is the Joseph form, which
stays symmetric positive (semi-)definite even when the gain is computed inaccurately.

Validation (``validate=True``, the default) goes through :mod:`selenv.core.linalg`: real
numeric types only (complex, bool, str, object raise ``TypeError``), shapes (a mismatch names
the argument that disagrees with the others), finiteness, SPD-ness and the valid range
``abs(entry) <= MAX_ABS`` (diagonals of ``P``, ``R`` >= ``MIN_PD_DIAG``); a result that still
overflows float64 raises ``ValueError`` instead of being returned as inf/NaN.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import cho_solve, solve_triangular
from scipy.linalg.lapack import dpotrf, dpotrs, dtrtrs

from selenv.core import npfast
from selenv.core.linalg import (
    MAX_ABS,
    MIN_PD_DIAG,
    FloatArray,
    ShapeError,
    all_finite,
    as_float_array,
    blame_shapes,
    check_finite,
    check_magnitude,
    check_shape,
    cholesky_spd,
    symmetrize,
    validate_spd,
)
from selenv.core.spd import require_spd

__all__ = [
    "KalmanFilter",
    "KalmanUpdate",
    "ekf_update",
    "information_update",
    "kf_predict",
    "kf_update",
]

_LOG_2PI = float(np.log(2.0 * np.pi))
_MAX_ABS2 = MAX_ABS * MAX_ABS


@dataclass(frozen=True, eq=False)
class KalmanUpdate:
    """Result of a Kalman measurement update (leading ``B`` axis present iff the input had it).

    Attributes:
        x: posterior mean, (n,) or (B, n): ``x' = x + K y``.
        P: posterior covariance, (n, n) or (B, n, n), Joseph form
            ``P' = (I - K H) P (I - K H)^T + K R K^T``.
        y: innovation, (m,) or (B, m): ``y = z - H x`` (EKF: ``y = z - h(x)``).
        S: innovation covariance, (m, m) or (B, m, m): ``S = H P H^T + R``.
        K: Kalman gain, (n, m) or (B, n, m): ``K = P H^T S^-1``.
        log_likelihood: ``log N(y; 0, S) = -(y^T S^-1 y + log det S + m log 2 pi) / 2``; a
            float when unbatched, (B,) when batched.
    """

    x: FloatArray
    P: FloatArray
    y: FloatArray
    S: FloatArray
    K: FloatArray
    log_likelihood: float | FloatArray


# --------------------------------------------------------------------------- validation helpers

#: accepted shapes of every argument, in symbols (for :func:`_blame`)
_SHAPES: dict[str, list[str]] = {
    "x": ["n", "B n"],
    "yv": ["n", "B n"],
    "P": ["n n", "B n n"],
    "Y": ["n n", "B n n"],
    "F": ["n n", "B n n"],
    "Q": ["n n", "B n n"],
    "z": ["m", "B m"],
    "h(x)": ["m"],
    "H": ["m n", "B m n"],
    "H_jac(x)": ["m n"],
    "R": ["m m", "B m m"],
}
#: arguments that are batched iff the state is (the model matrices may be shared)
_BATCH_ARGS = ("x", "yv", "P", "Y", "z")


def _blame(exc: ShapeError, *, batched: bool = True, **args: object) -> ShapeError:
    """The shape error naming the argument that disagrees with the others, else ``exc``.

    ``batched=False``: only the unbatched shapes are accepted (``ekf_update``).
    """
    shapes = {k: _SHAPES[k] if batched else _SHAPES[k][:1] for k in args}
    return blame_shapes(args, shapes, batch=_BATCH_ARGS, error=exc) or exc


def _vector(value: ArrayLike, name: str, B: int | None, m: int | None = None) -> FloatArray:
    """Finite, in-range vector of shape (m,), or (B, m) when ``B`` is given (``m=None``: any)."""
    v = as_float_array(value, name)
    check_shape(v, ((B,) if B is not None else ()) + (m,), name)
    return check_magnitude(check_finite(v, name), name)


def _state_vector(value: ArrayLike, name: str) -> tuple[FloatArray, int | None]:
    """Finite state vector (n,) or (B, n), n >= 1; returns it and ``B`` (``None``: unbatched)."""
    v = as_float_array(value, name)
    if v.ndim not in (1, 2) or v.shape[-1] == 0:
        raise ShapeError(f"{name} must have shape (n,) or (B, n) with n >= 1, got {v.shape}", name)
    v = check_magnitude(check_finite(v, name), name)
    return v, (v.shape[0] if v.ndim == 2 else None)


def _matrix(value: ArrayLike, name: str, shape: tuple[int, int], B: int | None) -> FloatArray:
    """Finite, in-range matrix of ``shape``, or a (B, *shape) batch when ``B`` is given."""
    A = as_float_array(value, name)
    batched = B is not None and A.ndim != 2
    check_shape(A, ((B,) if batched else ()) + shape, name)
    return check_magnitude(check_finite(A, name), name)


def _spd(
    value: ArrayLike,
    name: str,
    n: int,
    B: int | None,
    *,
    shared: bool = True,
    semidefinite: bool = False,
) -> FloatArray:
    """SPD (n, n) matrix, or a (B, n, n) batch; ``shared=False`` requires the batch axis."""
    A = as_float_array(value, name)
    batched = B is not None and (not shared or A.ndim != 2)
    A = validate_spd(A, name, n, batch=batched, semidefinite=semidefinite)
    if batched:
        check_shape(A, (B, n, n), name)
    return check_magnitude(A, name, definite=not semidefinite)


def _spd_exact_prechecks(A: FloatArray) -> bool:
    """Cheap part of :func:`_fast_valid_single`'s SPD test: exactly symmetric, diagonal in range.

    Byte-wise symmetry means ``symmetrize(A)`` is ``A`` itself (``0.5 * (a + a) == a``); the
    diagonal bound is that of ``check_magnitude(definite=True)``.
    """
    return A.tobytes() == A.T.tobytes() and min(A.diagonal().tolist()) >= MIN_PD_DIAG


def _chol_ok(A: FloatArray) -> bool:
    """Whether the gufunc behind ``np.linalg.cholesky`` factors ``A`` (call under errstate)."""
    L = npfast.cholesky_lo(A)  # NaN-filled when the factorisation fails
    return bool(L[-1, -1] == L[-1, -1])


def _fast_valid_single(
    x: ArrayLike, P: ArrayLike, z: ArrayLike, H: ArrayLike, R: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray] | None:
    """Unbatched ``kf_update`` inputs that certainly pass its validation, else ``None``.

    One finiteness/range test on all entries at once (``sum a^2 <= MAX_ABS^2``, which NaN and
    inf fail; it implies ``check_finite`` and ``check_magnitude`` of every argument), the
    shapes by attribute comparison and, for ``P`` and ``R``, exact symmetry, the diagonal
    bound and the Cholesky factorisation that ``validate_spd`` runs. Anything
    else (batched input, conversions that fail, borderline values) returns ``None`` and the
    caller runs the canonical checks, which raise the documented errors. The arrays returned
    are exactly those the canonical checks return (``symmetrize`` of an exactly symmetric
    matrix is the matrix itself: ``0.5 * (a + a) == a``).
    """
    try:  # a bad type is reported by the canonical checks, in their order of arguments
        xa, Pa = as_float_array(x, "x"), as_float_array(P, "P")
        za, Ha, Ra = as_float_array(z, "z"), as_float_array(H, "H"), as_float_array(R, "R")
    except TypeError:
        return None
    if xa.ndim != 1 or za.ndim != 1:
        return None
    n, m = xa.shape[0], za.shape[0]
    if n == 0 or m == 0 or Pa.shape != (n, n) or Ha.shape != (m, n) or Ra.shape != (m, m):
        return None
    total = float(np.vdot(xa, xa) + np.vdot(Pa, Pa) + np.vdot(za, za))
    total += float(np.vdot(Ha, Ha) + np.vdot(Ra, Ra))
    if not (total <= _MAX_ABS2 and _spd_exact_prechecks(Pa) and _spd_exact_prechecks(Ra)):
        return None
    with np.errstate(all="ignore"):  # a failed factorisation is NaN-filled, not raised here
        if not (_chol_ok(Pa) and _chol_ok(Ra)):  # the same test as validate_spd's
            return None
    return xa, Pa, za, Ha, Ra


def _state(x: ArrayLike, P: ArrayLike) -> tuple[FloatArray, FloatArray, int | None]:
    """Validate ``x`` (n,) | (B, n) and a matching SPD ``P`` (n, n) | (B, n, n)."""
    x, B = _state_vector(x, "x")
    return x, _spd(P, "P", x.shape[-1], B, shared=False), B


def _overflow(func: str) -> ValueError:
    return ValueError(
        f"{func}: the result is not representable in float64 (overflow); the inputs must "
        f"satisfy |entry| <= {MAX_ABS:g} with diagonals of P, R >= {MIN_PD_DIAG:g}, and the "
        "problem must not be so ill-conditioned that products or inverses of them exceed that "
        "range (rescale the problem, e.g. change units)"
    )


# ------------------------------------------------------------------------- Cholesky solves


def _tri_solve(L: FloatArray, b: FloatArray) -> FloatArray:
    """Solve ``L X = b`` for lower-triangular ``L`` (m, m) | (B, m, m) and ``b`` (..., m, k)."""
    if L.ndim == 2:
        return solve_triangular(L, b, lower=True, check_finite=False)
    return np.linalg.solve(L, b).astype(np.float64, copy=False)  # batched LU solve with L


def _cho_solve(L: FloatArray, b: FloatArray) -> FloatArray:
    """Solve ``(L L^T) X = b`` with Cholesky factor ``L`` (m, m) | (B, m, m), ``b`` (..., m, k)."""
    if L.ndim == 2:
        return cho_solve((L, True), b, check_finite=False)
    return np.linalg.solve(_T(L), np.linalg.solve(L, b))  # X = L^-T (L^-1 b), batched


def _mv(A: FloatArray, v: FloatArray) -> FloatArray:
    """Batched matrix-vector product ``A v``: (..., r, c) x (..., c) -> (..., r)."""
    return (A @ v[..., None])[..., 0]


def _T(A: FloatArray) -> FloatArray:
    """Transpose of the last two axes."""
    return np.swapaxes(A, -1, -2)


# ------------------------------------------------------------------------- filter equations


def _update(
    x: FloatArray, P: FloatArray, y: FloatArray, H: FloatArray, R: FloatArray
) -> KalmanUpdate:
    """Shared KF/EKF update on validated arrays, given the innovation ``y``."""
    if x.ndim == 1:
        return _update_single(x, P, y, H, R)
    n, m = x.shape[-1], y.shape[-1]
    S = symmetrize(H @ P @ _T(H) + R)  # S = H P H^T + R
    if not np.all(np.isfinite(S)):
        raise _overflow("the Kalman update (S = H P H^T + R)")
    L = cholesky_spd(S, "S = H P H^T + R")  # S = L L^T
    K = _T(_cho_solve(L, H @ P))  # K = P H^T S^-1, from S K^T = H P (P, S symmetric)
    x_post = x + _mv(K, y)  # x' = x + K y
    I_KH = np.eye(n) - K @ H  # I - K H
    P_post = symmetrize(I_KH @ P @ _T(I_KH) + K @ R @ _T(K))  # P' = (I-KH) P (I-KH)^T + K R K^T
    w = _tri_solve(L, y[..., None])[..., 0]  # w = L^-1 y, so y^T S^-1 y = w^T w
    logdet_S = 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)  # log det S
    ll = -0.5 * (np.sum(w * w, axis=-1) + logdet_S + m * _LOG_2PI)  # log N(y; 0, S)
    require_spd(P_post, "the Kalman update", "the posterior covariance P")  # SPD on any BLAS
    return KalmanUpdate(x_post, P_post, y, S, K, float(ll) if np.ndim(ll) == 0 else ll)


@functools.cache
def _eye(n: int) -> FloatArray:
    """Read-only identity ``np.eye(n)``, cached per size (saves ~1 us per small update)."""
    eye = np.eye(n)
    eye.flags.writeable = False
    return eye


def _update_single(
    x: FloatArray, P: FloatArray, y: FloatArray, H: FloatArray, R: FloatArray
) -> KalmanUpdate:
    """Unbatched :func:`_update` through LAPACK directly (same equations, ~5x less overhead)."""
    n, m = x.shape[0], y.shape[0]
    HP = H @ P  # (m, n)
    S = HP @ H.T + R
    S = 0.5 * (S + S.T)  # S = H P H^T + R
    L, info = dpotrf(S, lower=1, clean=1)  # S = L L^T
    if info != 0 or not math.isfinite(L[-1, -1]):
        if not np.all(np.isfinite(S)):
            raise _overflow("the Kalman update (S = H P H^T + R)")
        raise ValueError("S = H P H^T + R is not positive definite (Cholesky failed)")
    KT, _ = dpotrs(L, HP, lower=1)  # S K^T = H P  ->  K^T = S^-1 H P
    K = KT.T
    x_post = x + K @ y  # x' = x + K y
    I_KH = _eye(n) - K @ H
    P_post = I_KH @ P @ I_KH.T + K @ R @ KT  # Joseph form
    P_post = 0.5 * (P_post + P_post.T)
    w, _ = dtrtrs(L, y, lower=1)  # w = L^-1 y
    logdet_S = 2.0 * float(np.log(L.diagonal()).sum())  # the same reduction as np.sum
    ll = -0.5 * (float(w @ w) + logdet_S + m * _LOG_2PI)
    require_spd(P_post, "the Kalman update", "the posterior covariance P")  # SPD on any BLAS
    return KalmanUpdate(x_post, P_post, y, S, K, ll)


def kf_predict(
    x: ArrayLike, P: ArrayLike, F: ArrayLike, Q: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Kalman prediction ``x' = F x``, ``P' = F P F^T + Q``.

    Args:
        x: state mean, (n,) or (B, n).
        P: SPD state covariance, (n, n) or (B, n, n) (batched iff ``x`` is).
        F: state transition, (n, n) or (B, n, n).
        Q: SPD process noise covariance, (n, n) or (B, n, n).

    Returns:
        ``(x, P)``: predicted mean (n,) | (B, n) and symmetrized covariance (n, n) | (B, n, n).

    Raises:
        TypeError: an argument is not real numeric (complex, bool, str, object).
        ValueError: wrong shape (naming the argument that disagrees with the others), NaN/inf,
            ``P``/``Q`` not SPD/PSD, entries outside the valid range (``abs(entry) <= MAX_ABS``,
            diagonal of ``P`` >= ``MIN_PD_DIAG``) or a result that overflows float64.
    """
    xa, Pa, Fa, Qa = _checked_model(x, P, F, Q)
    x_prior = _mv(Fa, xa)  # x' = F x
    P_prior = symmetrize(Fa @ Pa @ _T(Fa) + Qa)  # P' = F P F^T + Q
    if not all_finite(x_prior, P_prior):
        raise _overflow("kf_predict")
    return x_prior, P_prior


def _checked_model(
    x: ArrayLike, P: ArrayLike, F: ArrayLike, Q: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Validated ``(x, P, F, Q)`` of :func:`kf_predict` / :class:`KalmanFilter`."""
    try:
        xa, Pa, B = _state(x, P)
        n = xa.shape[-1]
        Fa = _matrix(F, "F", (n, n), B)
        Qa = _spd(Q, "Q", n, B, semidefinite=True)
    except ShapeError as exc:
        raise _blame(exc, x=x, P=P, F=F, Q=Q) from None
    return xa, Pa, Fa, Qa


def kf_update(
    x: ArrayLike,
    P: ArrayLike,
    z: ArrayLike,
    H: ArrayLike,
    R: ArrayLike,
    *,
    validate: bool = True,
) -> KalmanUpdate:
    """Kalman measurement update in Joseph form.

    Implements ``y = z - H x``, ``S = H P H^T + R``, ``K = P H^T S^-1`` (Cholesky solves of
    ``S``), ``x' = x + K y`` and ``P' = (I - K H) P (I - K H)^T + K R K^T`` (symmetrized).

    Args:
        x: prior mean, (n,) or (B, n).
        P: SPD prior covariance, (n, n) or (B, n, n) (batched iff ``x`` is).
        z: measurement, (m,) or (B, m) (batched iff ``x`` is).
        H: measurement matrix, (m, n) or (B, m, n).
        R: SPD measurement noise covariance, (m, m) or (B, m, m).
        validate: check shapes, finiteness, SPD-ness and the valid range (default). ``False``
            is for hot paths whose inputs are known good (float64 arrays of the right
            shapes): it skips those checks, which dominate the cost of small updates; the
            types are still checked (complex raises, it is never truncated) and a non-SPD
            ``S`` still raises.

    Returns:
        Posterior ``x``, ``P`` with the intermediate ``y``, ``S``, ``K`` and ``log_likelihood``.

    Raises:
        TypeError: an argument is not real numeric (complex, bool, str, object).
        ValueError: wrong shape (naming the argument that disagrees with the others), NaN/inf,
            ``P``/``R`` not SPD, entries outside the valid range (``abs(entry) <= MAX_ABS``,
            diagonals of ``P``, ``R`` >= ``MIN_PD_DIAG``) or a result that overflows float64.
    """
    if not validate:
        xa, Pa = as_float_array(x, "x"), as_float_array(P, "P")
        za, Ha, Ra = as_float_array(z, "z"), as_float_array(H, "H"), as_float_array(R, "R")
        return _update(xa, Pa, za - _mv(Ha, xa), Ha, Ra)
    fast = _fast_valid_single(x, P, z, H, R)
    if fast is not None:  # every check below would pass and return these same arrays
        xa, Pa, za, Ha, Ra = fast
        return _checked_result(_update_single(xa, Pa, za - _mv(Ha, xa), Ha, Ra), "kf_update")
    try:
        xa, Pa, B = _state(x, P)
        za = _vector(z, "z", B)
        m, n = za.shape[-1], xa.shape[-1]
        Ha = _matrix(H, "H", (m, n), B)
        Ra = _spd(R, "R", m, B)
    except ShapeError as exc:
        raise _blame(exc, x=x, P=P, z=z, H=H, R=R) from None
    y = za - _mv(Ha, xa)  # y = z - H x
    return _checked_result(_update(xa, Pa, y, Ha, Ra), "kf_update")


def _checked_result(res: KalmanUpdate, func: str) -> KalmanUpdate:
    if not all_finite(res.x, res.P, res.K, res.log_likelihood):
        raise _overflow(func)
    return res


def ekf_update(
    x: ArrayLike,
    P: ArrayLike,
    z: ArrayLike,
    h: Callable[[FloatArray], ArrayLike],
    H_jac: Callable[[FloatArray], ArrayLike],
    R: ArrayLike,
) -> KalmanUpdate:
    """Extended Kalman update, linearised at the prior mean (unbatched only).

    Uses ``y = z - h(x)`` and ``H = dh/dx`` evaluated at ``x``, then the same Joseph-form update
    as :func:`kf_update`.

    Args:
        x: prior mean, (n,).
        P: SPD prior covariance, (n, n).
        z: measurement, (m,).
        h: measurement function, ``h(x) -> (m,)``.
        H_jac: Jacobian of ``h``, ``H_jac(x) -> (m, n)``.
        R: SPD measurement noise covariance, (m, m).

    Returns:
        As for :func:`kf_update`, with ``H = H_jac(x)`` and ``y = z - h(x)``.

    Raises:
        TypeError: ``h`` / ``H_jac`` not callable, or an argument or an output of ``h`` /
            ``H_jac`` not real numeric (complex, bool, str, object).
        ValueError: batched input, a wrong shape (including the outputs of ``h`` and ``H_jac``;
            the message names the argument that disagrees with the others), NaN/inf,
            ``P``/``R`` not SPD, entries outside the valid range or a result that overflows.
    """
    for f, fname in ((h, "h"), (H_jac, "H_jac")):
        if not callable(f):
            raise TypeError(f"{fname} must be callable, got {type(f).__name__}")
    try:
        xa, Pa, B = _state(x, P)
        if B is not None:
            raise ShapeError(
                f"ekf_update is unbatched: x must have shape (n,), got {xa.shape}", "x"
            )
        za = _vector(z, "z", None)
        as_float_array(R, "R")
    except ShapeError as exc:
        raise _blame(exc, batched=False, x=x, P=P, z=z, R=R) from None
    m, n = za.shape[0], xa.shape[0]
    hx_raw, H_raw = h(xa.copy()), H_jac(xa.copy())
    try:
        hx = _vector(hx_raw, "h(x)", None, m)  # h(x), (m,)
        Ha = _matrix(H_raw, "H_jac(x)", (m, n), None)  # H = dh/dx at x, (m, n)
        Ra = _spd(R, "R", m, None)
    except ShapeError as exc:
        args = {"x": xa, "P": Pa, "z": z, "h(x)": hx_raw, "H_jac(x)": H_raw, "R": R}
        raise _blame(exc, batched=False, **args) from None
    y = za - hx  # y = z - h(x)
    return _checked_result(_update(xa, Pa, y, Ha, Ra), "ekf_update")


def information_update(
    Y: ArrayLike, yv: ArrayLike, z: ArrayLike, H: ArrayLike, R: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Information-form measurement update ``Y' = Y + H^T R^-1 H``, ``y' = y + H^T R^-1 z``.

    ``R^-1`` is applied by whitening with its Cholesky factor ``R = L L^T``: with ``G = L^-1 H``
    and ``w = L^-1 z``, ``H^T R^-1 H = G^T G`` and ``H^T R^-1 z = G^T w``.

    Args:
        Y: information matrix ``P^-1``, (n, n) or (B, n, n) (batched iff ``yv`` is). It must be
            symmetric positive semi-definite; only shape and finiteness are checked, so that
            ``Y = 0`` (no prior information) is accepted.
        yv: information vector ``P^-1 x``, (n,) or (B, n).
        z: measurement, (m,) or (B, m) (batched iff ``yv`` is).
        H: measurement matrix, (m, n) or (B, m, n).
        R: SPD measurement noise covariance, (m, m) or (B, m, m).

    Returns:
        ``(Y, yv)``: updated information matrix and vector, same shapes as the inputs.

    Raises:
        TypeError: an argument is not real numeric (complex, bool, str, object).
        ValueError: wrong shape (naming the argument that disagrees with the others), NaN/inf,
            ``R`` not SPD, entries outside the valid range or a result that overflows float64.
    """
    try:
        yva, B = _state_vector(yv, "yv")
        batch = (B,) if B is not None else ()
        n = yva.shape[-1]
        Ya = check_shape(as_float_array(Y, "Y"), (*batch, n, n), "Y")
        Ya = check_magnitude(check_finite(Ya, "Y"), "Y")
        Ya = validate_spd(Ya, "Y", n, batch=B is not None, semidefinite=True)  # Y = 0 is fine
        za = _vector(z, "z", B)
        m = za.shape[-1]
        Ha = _matrix(H, "H", (m, n), B)
        Ra = _spd(R, "R", m, B)
    except ShapeError as exc:
        raise _blame(exc, Y=Y, yv=yv, z=z, H=H, R=R) from None
    L = np.broadcast_to(cholesky_spd(Ra, "R"), (*batch, m, m))  # R = L L^T
    G = _tri_solve(L, np.broadcast_to(Ha, (*batch, m, n)))  # G = L^-1 H
    w = _tri_solve(L, za[..., None])  # w = L^-1 z
    Y_post = Ya + symmetrize(_T(G) @ G)  # Y' = Y + H^T R^-1 H = Y + G^T G
    yv_post = yva + (_T(G) @ w)[..., 0]  # y' = y + H^T R^-1 z = y + G^T w
    if not all_finite(Y_post, yv_post):
        raise _overflow("information_update")
    return Y_post, yv_post


class KalmanFilter:
    """Linear Kalman filter holding its state; steps call :func:`kf_predict` / :func:`kf_update`.

    Args:
        x: initial mean, (n,) or (B, n).
        P: SPD initial covariance, (n, n) or (B, n, n).
        F: state transition, (n, n) or (B, n, n).
        Q: SPD process noise covariance, (n, n) or (B, n, n).

    Attributes:
        x: current mean, (n,) or (B, n).
        P: current covariance, (n, n) or (B, n, n).
        F: state transition used by :meth:`predict`.
        Q: process noise covariance used by :meth:`predict`.
    """

    def __init__(self, x: ArrayLike, P: ArrayLike, F: ArrayLike, Q: ArrayLike) -> None:
        """Validate and store the initial state and the model.

        Raises:
            TypeError, ValueError: as :func:`kf_predict` (names the argument).
        """
        xa, Pa, Fa, Qa = _checked_model(x, P, F, Q)
        self.x, self.P = xa.copy(), Pa.copy()  # the filter owns its state
        self.F: FloatArray = Fa
        self.Q: FloatArray = Qa

    def predict(self) -> tuple[FloatArray, FloatArray]:
        """Advance one step, ``x <- F x``, ``P <- F P F^T + Q``; returns the new ``(x, P)``.

        Raises:
            ValueError: the prediction overflows float64 (the state is left unchanged).
        """
        self.x, self.P = kf_predict(self.x, self.P, self.F, self.Q)
        return self.x, self.P

    def update(self, z: ArrayLike, H: ArrayLike, R: ArrayLike) -> KalmanUpdate:
        """Assimilate measurement ``z`` (m,) | (B, m) with model ``H``, ``R`` (see kf_update).

        Raises:
            TypeError, ValueError: as :func:`kf_update`; the state is left unchanged.
        """
        result = kf_update(self.x, self.P, z, H, R)
        self.x, self.P = result.x, result.P
        return result
