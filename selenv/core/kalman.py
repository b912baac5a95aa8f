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
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import cho_solve, solve_triangular
from scipy.linalg.lapack import dpotrf, dpotrs, dtrtrs

from selenv.core.linalg import (
    FloatArray,
    as_float_array,
    check_finite,
    check_shape,
    cholesky_spd,
    symmetrize,
    validate_spd,
)

__all__ = [
    "KalmanFilter",
    "KalmanUpdate",
    "ekf_update",
    "information_update",
    "kf_predict",
    "kf_update",
]

_LOG_2PI = float(np.log(2.0 * np.pi))


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


def _vector(value: ArrayLike, name: str, B: int | None, m: int | None = None) -> FloatArray:
    """Finite vector of shape (m,), or (B, m) when ``B`` is given (``m=None``: any length)."""
    v = as_float_array(value, name)
    check_shape(v, ((B,) if B is not None else ()) + (m,), name)
    return check_finite(v, name)


def _state_vector(value: ArrayLike, name: str) -> tuple[FloatArray, int | None]:
    """Finite state vector (n,) or (B, n), n >= 1; returns it and ``B`` (``None``: unbatched)."""
    v = as_float_array(value, name)
    if v.ndim not in (1, 2) or v.shape[-1] == 0:
        raise ValueError(f"{name} must have shape (n,) or (B, n) with n >= 1, got {v.shape}")
    return check_finite(v, name), (v.shape[0] if v.ndim == 2 else None)


def _matrix(value: ArrayLike, name: str, shape: tuple[int, int], B: int | None) -> FloatArray:
    """Finite matrix of ``shape``, or a (B, *shape) batch of them when ``B`` is given."""
    A = as_float_array(value, name)
    batched = B is not None and A.ndim != 2
    check_shape(A, ((B,) if batched else ()) + shape, name)
    return check_finite(A, name)


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
    return A


def _state(x: ArrayLike, P: ArrayLike) -> tuple[FloatArray, FloatArray, int | None]:
    """Validate ``x`` (n,) | (B, n) and a matching SPD ``P`` (n, n) | (B, n, n)."""
    x, B = _state_vector(x, "x")
    return x, _spd(P, "P", x.shape[-1], B, shared=False), B


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
    L = cholesky_spd(S, "S = H P H^T + R")  # S = L L^T
    K = _T(_cho_solve(L, H @ P))  # K = P H^T S^-1, from S K^T = H P (P, S symmetric)
    x_post = x + _mv(K, y)  # x' = x + K y
    I_KH = np.eye(n) - K @ H  # I - K H
    P_post = symmetrize(I_KH @ P @ _T(I_KH) + K @ R @ _T(K))  # P' = (I-KH) P (I-KH)^T + K R K^T
    w = _tri_solve(L, y[..., None])[..., 0]  # w = L^-1 y, so y^T S^-1 y = w^T w
    logdet_S = 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)  # log det S
    ll = -0.5 * (np.sum(w * w, axis=-1) + logdet_S + m * _LOG_2PI)  # log N(y; 0, S)
    return KalmanUpdate(x_post, P_post, y, S, K, float(ll) if np.ndim(ll) == 0 else ll)


def _update_single(
    x: FloatArray, P: FloatArray, y: FloatArray, H: FloatArray, R: FloatArray
) -> KalmanUpdate:
    """Unbatched :func:`_update` through LAPACK directly (same equations, ~5x less overhead)."""
    n, m = x.shape[0], y.shape[0]
    HP = H @ P  # (m, n)
    S = HP @ H.T + R
    S = 0.5 * (S + S.T)  # S = H P H^T + R
    L, info = dpotrf(S, lower=1, clean=1)  # S = L L^T
    if info != 0:
        raise ValueError("S = H P H^T + R is not positive definite (Cholesky failed)")
    KT, _ = dpotrs(L, HP, lower=1)  # S K^T = H P  ->  K^T = S^-1 H P
    K = KT.T
    x_post = x + K @ y  # x' = x + K y
    I_KH = np.eye(n) - K @ H
    P_post = I_KH @ P @ I_KH.T + K @ R @ KT  # Joseph form
    P_post = 0.5 * (P_post + P_post.T)
    w, _ = dtrtrs(L, y, lower=1)  # w = L^-1 y
    logdet_S = 2.0 * float(np.sum(np.log(np.diagonal(L))))
    ll = -0.5 * (float(w @ w) + logdet_S + m * _LOG_2PI)
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
        ValueError: wrong shape, NaN/inf, or ``P``/``Q`` not SPD (the message names the argument).
    """
    x, P, B = _state(x, P)
    n = x.shape[-1]
    F = _matrix(F, "F", (n, n), B)
    Q = _spd(Q, "Q", n, B, semidefinite=True)
    x_prior = _mv(F, x)  # x' = F x
    P_prior = symmetrize(F @ P @ _T(F) + Q)  # P' = F P F^T + Q
    return x_prior, P_prior


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
        validate: check shapes, finiteness and SPD-ness (default). ``False`` is for hot paths
            whose inputs are known good (float64 arrays of the right shapes): it skips the
            checks, which dominate the cost of small updates; a non-SPD ``S`` still raises.

    Returns:
        Posterior ``x``, ``P`` with the intermediate ``y``, ``S``, ``K`` and ``log_likelihood``.

    Raises:
        ValueError: wrong shape, NaN/inf, or ``P``/``R`` not SPD (the message names the argument).
    """
    if not validate:
        xa, Pa, Ha, Ra = (np.asarray(a, dtype=np.float64) for a in (x, P, H, R))
        return _update(xa, Pa, np.asarray(z, dtype=np.float64) - _mv(Ha, xa), Ha, Ra)
    x, P, B = _state(x, P)
    z = _vector(z, "z", B)
    m, n = z.shape[-1], x.shape[-1]
    H = _matrix(H, "H", (m, n), B)
    R = _spd(R, "R", m, B)
    y = z - _mv(H, x)  # y = z - H x
    return _update(x, P, y, H, R)


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
        ValueError: batched input, a wrong shape (including the outputs of ``h`` and ``H_jac``),
            NaN/inf, or ``P``/``R`` not SPD.
    """
    x, P, B = _state(x, P)
    if B is not None:
        raise ValueError(f"ekf_update is unbatched: x must have shape (n,), got {x.shape}")
    z = _vector(z, "z", None)
    m, n = z.shape[0], x.shape[0]
    hx = _vector(h(x.copy()), "h(x)", None, m)  # h(x), (m,)
    H = _matrix(H_jac(x.copy()), "H_jac(x)", (m, n), None)  # H = dh/dx at x, (m, n)
    R = _spd(R, "R", m, None)
    y = z - hx  # y = z - h(x)
    return _update(x, P, y, H, R)


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
        ValueError: wrong shape, NaN/inf, or ``R`` not SPD (the message names the argument).
    """
    yv, B = _state_vector(yv, "yv")
    batch = (B,) if B is not None else ()
    n = yv.shape[-1]
    Y = check_finite(check_shape(as_float_array(Y, "Y"), (*batch, n, n), "Y"), "Y")
    z = _vector(z, "z", B)
    m = z.shape[-1]
    H = _matrix(H, "H", (m, n), B)
    R = _spd(R, "R", m, B)
    L = np.broadcast_to(cholesky_spd(R, "R"), (*batch, m, m))  # R = L L^T
    G = _tri_solve(L, np.broadcast_to(H, (*batch, m, n)))  # G = L^-1 H
    w = _tri_solve(L, z[..., None])  # w = L^-1 z
    Y_post = Y + symmetrize(_T(G) @ G)  # Y' = Y + H^T R^-1 H = Y + G^T G
    yv_post = yv + (_T(G) @ w)[..., 0]  # y' = y + H^T R^-1 z = y + G^T w
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
        self.x, self.P, B = _state(x, P)
        n = self.x.shape[-1]
        self.F: FloatArray = _matrix(F, "F", (n, n), B)
        self.Q: FloatArray = _spd(Q, "Q", n, B, semidefinite=True)

    def predict(self) -> tuple[FloatArray, FloatArray]:
        """Advance one step, ``x <- F x``, ``P <- F P F^T + Q``; returns the new ``(x, P)``."""
        self.x, self.P = kf_predict(self.x, self.P, self.F, self.Q)
        return self.x, self.P

    def update(self, z: ArrayLike, H: ArrayLike, R: ArrayLike) -> KalmanUpdate:
        """Assimilate measurement ``z`` (m,) | (B, m) with model ``H``, ``R`` (see kf_update)."""
        result = kf_update(self.x, self.P, z, H, R)
        self.x, self.P = result.x, result.P
        return result
