"""DMV: discorrelated minimum-variance update of agent i from a relative measurement (eqs. 4-6).

Agent ``i`` measures agent ``j``: ``z = h(x_i, x_j) + v``, ``v ~ N(0, R)``, Jacobians ``H_i``,
``H_j``; the cross-covariance ``P_ij`` is unknown. For every admissible ``P_ij`` and ``w`` in
(0, 1) the joint covariance is bounded by ``blkdiag(P_i / w, P_j / (1 - w))`` (eq. 4), and the
update with that bound is (eq. 5)::

    S(w)    = A / w + B / (1 - w) + R,      A = H_i P_i H_i^T,  B = H_j P_j H_j^T   (m x m)
    Kbar(w) = (P_i / w) H_i^T S(w)^-1
    Pbar(w) = (I - Kbar H_i) P_i / w = (w P_i^-1 + (1-w) H_i^T (B + (1-w) R)^-1 H_i)^-1
    w*      = argmin_{0 <= w <= 1} log det Pbar(w)                                       (6)

``log det Pbar`` needs only m x m determinants (Sylvester)::

    log det Pbar(w) = log det P_i - (n-m) log w + log det(B + (1-w) R)
                      - log det((1-w) A + w B + w (1-w) R)

It is convex in ``w``; its slope at ``w = 1`` is ``tr(B^-1 A) - n``, so ``w* = 1`` (zero gain, no
update) exactly when ``tr(B^-1 A) <= n``. ``Pbar(w*)`` bounds the true covariance of the update
for every admissible ``P_ij`` and has ``log det Pbar(w*) <= log det P_i``, but it is *not*
``<= P_i`` in the Loewner order: for ``w < 1`` the directions of agent i that the measurement
does not see are inflated by ``1 / w`` (PECMV's ``P_i+`` is ``<=`` both). Solvers:

* ``m = 1``: the stationary points are the roots of the cubic (a, b in units of r)::

      n w^3 - [(n-1)(c + d) + 2c] w^2 + [n c d - (n-2) a] w + (n-1) c a = 0,
      c = b + 1,  d = b - a + 1,

  which has exactly one root in (0, 1) when an update happens (``p(0) > 0 > p(1)``, the cost
  being convex), so "the best real root compared with w = 1 (and w = 0 if n = m)" is that
  root; it is found to machine precision by safeguarded Newton on the cubic (no complex
  arithmetic, no cancellation of Cardano's formula). For ``n = 1`` the root ``w = 0`` is
  divided out and ``w = 0`` is the optimum when the remaining quadratic is <= 0 there.
* ``m > 1``: safeguarded Newton on the derivative of the cheap cost (analytic first and
  second derivatives, see :func:`_derivs_single`); for ``m = 2`` in scalar arithmetic with
  explicit 2 x 2 inverses (:func:`_derivs_2x2`), for larger m by two m x m Cholesky solves.

``w = 0`` is reachable only when ``n = m`` (otherwise the cost tends to +inf); it is then the
information-form update ``Pbar(0) = (H_i^T (B + R)^-1 H_i)^-1``. Near ``w = 0`` the update is
computed in that information form (``P_i / w - Kbar S Kbar^T`` would cancel digits). DMV needs
``n_i >= m`` and ``B`` positive definite (agent j uncertain along every measured direction);
otherwise use a Kalman update (``ValueError`` names ``H_i`` / ``H_j``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, overload

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import cho_solve
from scipy.linalg.lapack import dpotrf, dpotrs

from selenv.core.fusion.common import (
    Pair,
    check_correction,
    chol,
    logdet_from_chol,
    overflow_error,
    pair,
    root_increasing,
    tri_solve,
    validate_pair,
)
from selenv.core.linalg import FloatArray, ShapeError, all_finite, as_float_array
from selenv.core.spd import require_spd

__all__ = ["DMVResult", "checked_omega", "dmv_cost", "dmv_from_pair", "dmv_update"]

_B_NOT_PD = (
    "H_j P_j H_j^T must be positive definite for DMV (agent j must be uncertain along every "
    "measured direction, so H_j needs rank m, and H_j P_j H_j^T must not underflow to zero); "
    "use a Kalman update instead"
)

#: ``w`` at which the slope is probed to decide ``w* = 0`` (reachable only when ``n = m``)
_W_PROBE = 1e-12


@dataclass(frozen=True, kw_only=True, eq=False)
class DMVResult:
    """Result of :func:`dmv_update` (agent ``i``'s posterior).

    Attributes:
        P: (n_i, n_i) updated covariance ``Pbar(w*)`` (eq. 5b).
        K: (n_i, m) gain ``Kbar(w*)`` (zero when not ``updated``).
        omega: the optimiser ``w*`` of eq. (6), in [0, 1].
        updated: False when the no-update rule applies (``w* = 1``: ``K = 0``, ``P = P_i``).
        log_det: ``log det P``.
        dx: (n_i,) correction ``K (z - z_hat)`` (eq. 5a), or None without ``residual``.
        x: (n_i,) posterior mean ``x_i + dx``, or None without ``x_i``.
    """

    P: FloatArray
    K: FloatArray
    omega: float
    updated: bool
    log_det: float
    dx: FloatArray | None = None
    x: FloatArray | None = None


# ----------------------------------------------------------------------------- m = 1: the cubic


#: ``a`` or ``b`` above this: the cubic's coefficients are divided by ``max(a, b)^2`` (the
#: products ``c d``, ``c a`` would overflow float64 near ``1e154``; the roots do not change)
_CUBIC_SCALE_AT = 1e100


def _cubic(a: Any, b: Any, n: int) -> tuple[Any, Any, Any, Any]:
    """Coefficients ``(c3, c2, c1, c0)`` of the stationarity cubic; ``a``, ``b`` in units of r.

    Scaled by ``1 / s^2``, ``s = max(a, b)``, where ``s > _CUBIC_SCALE_AT`` (same roots; the
    cubic term may then underflow to 0, which is its true relative size).
    """
    s = np.maximum(np.maximum(a, b), _CUBIC_SCALE_AT) / _CUBIC_SCALE_AT
    if np.ndim(s) == 0 and s == 1.0:
        c = b + 1.0  # b + r
        d = b - a + 1.0  # b - a + r
        return n, -((n - 1) * (c + d) + 2.0 * c), n * c * d - (n - 2) * a, (n - 1) * c * a
    s = np.where(s > 1.0, np.maximum(a, b), 1.0)
    a_s, c, d = a / s, (b + 1.0) / s, (b - a + 1.0) / s
    inv = 1.0 / s
    return (
        n * inv * inv,
        -((n - 1) * (c + d) + 2.0 * c) * inv,
        n * c * d - (n - 2) * a_s * inv,
        (n - 1) * c * a_s,
    )


def _omega_scalar(a: float, b: float, n: int) -> float:
    """``w*`` for ``m = 1`` (``a = A/r``, ``b = B/r``, ``B > 0``): the root of the cubic."""
    if a <= n * b:  # tr(B^-1 A) <= n: no update
        return 1.0
    c3, c2, c1, c0 = _cubic(a, b, n)
    if n == 1:  # p(w) = w (c3 w^2 + c2 w + c1): divide the root w = 0 out
        c3, c2, c1, c0 = 0.0, c3, c2, c1
        if c0 <= 0.0:  # f'(0) >= 0: the minimum is at w = 0
            return 0.0

    def g(w: float) -> tuple[float, float]:  # -p(w) is < 0 near 0 and > 0 at 1 (sign of f')
        return -(((c3 * w + c2) * w + c1) * w + c0), -((3.0 * c3 * w + 2.0 * c2) * w + c1)

    return root_increasing(g, 0.0, 1.0, 0.5)


# ------------------------------------------------------------------- m > 1: Newton on f'(w)


def _derivs_single(
    w: float, A: FloatArray, B: FloatArray, R: FloatArray, n: int
) -> tuple[float, float]:
    """``f'(w)``, ``f''(w)`` of the cheap cost for one problem (LAPACK ``dpotrf``/``dpotrs``).

    With ``M = B + (1-w) R``, ``Q = (1-w) A + w B + w(1-w) R`` and ``Q' = B - A + (1-2w) R``::

        f'  = -(n-m)/w - tr(M^-1 R) - tr(Q^-1 Q')
        f'' = (n-m)/w^2 - tr((M^-1 R)^2) + tr((Q^-1 Q')^2) + 2 tr(Q^-1 R)
    """
    m = A.shape[0]
    L_M = chol(B + (1.0 - w) * R, "H_j P_j H_j^T + (1 - omega) R")
    X1 = dpotrs(L_M, R, lower=1)[0]  # M^-1 R
    L_Q = chol((1.0 - w) * A + w * B + w * (1.0 - w) * R, "Q(omega)")
    X2 = dpotrs(L_Q, np.hstack([B - A + (1.0 - 2.0 * w) * R, R]), lower=1)[0]
    G = X2[:, :m]
    f1 = -(n - m) / w - np.trace(X1) - np.trace(G)
    f2 = (n - m) / w**2 - np.sum(X1 * X1.T) + np.sum(G * G.T) + 2.0 * np.trace(X2[:, m:])
    return float(f1), float(f2)


Sym2 = tuple[float, float, float]  # symmetric 2 x 2 matrix packed as (x11, x12, x22)


def _inv2_times(M: Sym2, X: Sym2) -> tuple[float, float, float, float]:
    """Entries ``(y11, y12, y21, y22)`` of ``M^-1 X`` for symmetric 2 x 2 ``M``, ``X``.

    ``M^-1 = [[m3, -m2], [-m2, m1]] / det M`` with ``M = [[m1, m2], [m2, m3]]``.
    """
    m1, m2, m3 = M
    x1, x2, x3 = X
    det = m1 * m3 - m2 * m2
    return (
        (m3 * x1 - m2 * x2) / det,
        (m3 * x2 - m2 * x3) / det,
        (m1 * x2 - m2 * x1) / det,
        (m1 * x3 - m2 * x2) / det,
    )


def _derivs_2x2(w: float, A: Sym2, B: Sym2, R: Sym2, n: int) -> tuple[float, float]:
    """:func:`_derivs_single` for ``m = 2`` in Python floats (symmetric matrices packed)."""
    v, u = 1.0 - w, 1.0 - 2.0 * w
    M = (B[0] + v * R[0], B[1] + v * R[1], B[2] + v * R[2])  # M = B + (1-w) R
    Q = (  # Q = (1-w) A + w B + w (1-w) R
        v * A[0] + w * B[0] + w * v * R[0],
        v * A[1] + w * B[1] + w * v * R[1],
        v * A[2] + w * B[2] + w * v * R[2],
    )
    dQ = (B[0] - A[0] + u * R[0], B[1] - A[1] + u * R[1], B[2] - A[2] + u * R[2])  # Q'
    x11, x12, x21, x22 = _inv2_times(M, R)  # M^-1 R
    g11, g12, g21, g22 = _inv2_times(Q, dQ)  # Q^-1 Q'
    h11, _, _, h22 = _inv2_times(Q, R)  # Q^-1 R
    f1 = -(n - 2) / w - (x11 + x22) - (g11 + g22)
    f2 = (n - 2) / (w * w) - (x11 * x11 + 2.0 * x12 * x21 + x22 * x22)
    f2 += g11 * g11 + 2.0 * g12 * g21 + g22 * g22 + 2.0 * (h11 + h22)
    return f1, f2


#: ``A``, ``B``, ``R`` are divided by their largest trace when it leaves this range (``f'``
#: and ``tr(B^-1 A)`` do not change; the 2 x 2 determinants would overflow / underflow)
_SCALE_RANGE = (1e-50, 1e50)


def _omega_general(A: FloatArray, B: FloatArray, R: FloatArray, n: int) -> float:
    """``w*`` for one problem (m >= 2) by safeguarded Newton on ``f'``; ``B`` must be PD."""
    m = A.shape[0]
    s = max(float(np.trace(A)), float(np.trace(B)), float(np.trace(R)))
    if not _SCALE_RANGE[0] <= s <= _SCALE_RANGE[1]:  # scale invariant: log det(cX) cancels
        A, B, R = A / s, B / s, R / s
    if m == 2:  # scalar arithmetic: ~10x less overhead than 2 x 2 LAPACK calls
        (a1, a2), (_, a3) = A.tolist()
        (b1, b2), (_, b3) = B.tolist()
        (r1, r2), (_, r3) = R.tolist()
        Ap, Bp, Rp = (a1, a2, a3), (b1, b2, b3), (r1, r2, r3)
        # det B / (b1 b3) = 1 - b2^2 / (b1 b3), in ratios (b1 b3 may under- or overflow)
        if not (b1 > 0.0 and b3 > 0.0 and (1.0 - (b2 / b1) * (b2 / b3)) > 1e-14):
            raise ValueError(_B_NOT_PD)
        # tr(B^-1 A) = (b3 a1 - 2 b2 a2 + b1 a3) / det B, divided through by b1 b3
        trace_ratio = (a1 / b1 - 2.0 * (b2 / b1) * (a2 / b3) + a3 / b3) / (
            1.0 - (b2 / b1) * (b2 / b3)
        )

        def g(w: float) -> tuple[float, float]:
            return _derivs_2x2(w, Ap, Bp, Rp, n)

    else:
        L_B = chol(B, "H_j P_j H_j^T")
        trace_ratio = float(np.trace(dpotrs(L_B, A, lower=1)[0]))

        def g(w: float) -> tuple[float, float]:
            return _derivs_single(w, A, B, R, n)

    if trace_ratio <= n:  # tr(B^-1 A) <= n: no update
        return 1.0
    if n == m and g(_W_PROBE)[0] >= 0.0:
        return 0.0  # f'(0) >= 0 (only reachable when n = m)
    return root_increasing(g, 0.0, 1.0, 0.5)


# ------------------------------------------------------------------------------------ updates


def _check_dims(n: int, m: int) -> None:
    if n < m:
        raise ValueError(
            f"DMV needs n_i >= m (P_i is {n} x {n} but H_i has m = {m} rows): with fewer states "
            "than measurements H_i P_i H_i^T is singular and the bound of eq. (4) degenerates"
        )


def _update_at(
    p: Pair, A: FloatArray, B: FloatArray, w: float, form: str = "auto"
) -> tuple[FloatArray, FloatArray]:
    """``(Pbar(w), Kbar(w))`` of eq. (5) by Cholesky solves; ``P_i`` is never inverted.

    ``form="kalman"``: ``S = A/w + B/(1-w) + R``, ``Kbar = (P_i/w) H_i^T S^-1``,
    ``Pbar = P_i/w - Kbar S Kbar^T``. ``form="information"``: with ``N = B + (1-w) R`` and
    ``G = L_N^-1 H_i L_i``, ``Pbar = L_i (w I + (1-w) G^T G)^-1 L_i^T`` and
    ``Kbar = (1-w) Pbar H_i^T N^-1`` (exact at ``w = 0``). ``"auto"`` takes the information form
    for ``w < 1e-3``, where ``P_i / w - Kbar S Kbar^T`` would cancel digits.
    """
    P_i, H_i = p.P_i, p.H_i
    n, m = P_i.shape[0], H_i.shape[0]
    if w >= 1.0:
        return P_i.copy(), np.zeros((n, m))
    if form == "information" or (form == "auto" and w < 1e-3):
        L_N = chol(B + (1.0 - w) * p.R, "H_j P_j H_j^T + (1 - omega) R")
        G = tri_solve(L_N, H_i @ p.L_i)  # N^-1/2 H_i L_i, (m, n)
        J = w * np.eye(n) + (1.0 - w) * (G.T @ G)  # L_i^T Pbar^-1 L_i
        L_J = chol(0.5 * (J + J.T), "H_i^T (B + R)^-1 H_i (omega = 0 needs rank H_i = n_i)")
        F = tri_solve(L_J, p.L_i.T)  # L_J^-1 L_i^T
        P = F.T @ F  # Pbar = L_i J^-1 L_i^T
        K = (1.0 - w) * cho_solve(
            (L_N, True), H_i @ P, check_finite=False
        ).T  # Kbar^T = (1-w) N^-1 H_i Pbar
        return P, K
    S = A / w + B / (1.0 - w) + p.R  # S(w) = A/w + B/(1-w) + R
    L_S = chol(0.5 * (S + S.T), "S(omega)")
    M = tri_solve(L_S, (H_i @ P_i) / w)  # L_S^-1 H_i P_i / w
    K = tri_solve(L_S, M, trans=True).T  # Kbar = (P_i/w) H_i^T S^-1
    P = P_i / w - M.T @ M  # Pbar = (I - Kbar H_i) P_i / w = P_i/w - Kbar S Kbar^T
    return 0.5 * (P + P.T), K


def _cost(p: Pair, A: FloatArray, B: FloatArray, w: float) -> float:
    """Cheap ``log det Pbar(w)`` (m x m determinants only)."""
    n, m = p.P_i.shape[0], A.shape[0]
    if w >= 1.0:
        return logdet_from_chol(p.L_i)
    if w <= 0.0:  # log det Pbar(0) = -log det(H_i^T (B+R)^-1 H_i), finite only if n <= m
        if n > m:
            return math.inf
        G = tri_solve(chol(B + p.R, "B + R"), p.H_i)
        sign, ld_info = np.linalg.slogdet(G.T @ G)
        return -float(ld_info) if sign > 0 else math.inf
    L_N, info_N = dpotrf(B + (1.0 - w) * p.R, lower=1)  # B + (1-w) R
    L_Q, info_Q = dpotrf((1.0 - w) * A + w * B + w * (1.0 - w) * p.R, lower=1)  # Q(w)
    if info_N != 0 or info_Q != 0:
        return math.inf
    log_w = (n - m) * math.log(w)
    return logdet_from_chol(p.L_i) - log_w + logdet_from_chol(L_N) - logdet_from_chol(L_Q)


def dmv_update(
    P_i: ArrayLike,
    P_j: ArrayLike,
    H_i: ArrayLike,
    H_j: ArrayLike,
    R: ArrayLike,
    *,
    x_i: ArrayLike | None = None,
    residual: ArrayLike | None = None,
    omega: float | None = None,
    validate: bool = True,
) -> DMVResult:
    """DMV update of agent ``i`` from its measurement of agent ``j`` (eqs. 4-6).

    Args:
        P_i: (n_i, n_i) SPD prior covariance of agent i.
        P_j: (n_j, n_j) SPD prior covariance of agent j.
        H_i: (m, n_i) measurement Jacobian w.r.t. agent i.
        H_j: (m, n_j) measurement Jacobian w.r.t. agent j; ``H_j P_j H_j^T`` must be PD.
        R: (m, m) SPD measurement noise.
        x_i: (n_i,) prior mean of agent i (needs ``residual``); gives ``x`` in the result.
        residual: (m,) ``z - z_hat``; gives ``dx = K residual``.
        omega: use this ``w`` in [0, 1] instead of optimising eq. (6) (e.g. a learned LDMV
            estimate); ``updated`` is then ``omega < 1``.
        validate: check shapes, symmetry, finiteness, definiteness and the valid range
            (default). ``False`` is for hot paths with known-good float64 inputs (as in
            ``kf_update``): it skips those checks, about half the cost of a scalar update;
            types are still checked and non-PD factors still raise.

    Returns:
        :class:`DMVResult` with ``P = Pbar(w*)``, ``K = Kbar(w*)``, ``omega = w*``.

    Raises:
        TypeError: an argument is not real numeric (complex, bool, str, object), also
            ``omega``.
        ValueError: bad shapes (naming the argument that disagrees with the others), NaN/inf,
            non-SPD ``P_i``/``P_j``/``R``, entries outside the valid range
            (:func:`~selenv.core.linalg.check_magnitude`) or a result that overflows float64,
            singular ``H_j P_j H_j^T``, ``x_i`` without ``residual``, or ``omega`` outside
            [0, 1] (the message names the argument).
    """
    w_given = None if omega is None else checked_omega(omega)
    p = pair(P_i, P_j, H_i, H_j, R, validate=validate, x_i=x_i, residual=residual)
    x_v, r_v = check_correction(x_i, residual, p.P_i.shape[0], p.H_i.shape[0])
    return dmv_from_pair(p, x_v, r_v, w_given, check=validate)


def dmv_from_pair(
    p: Pair,
    x_v: FloatArray | None,
    r_v: FloatArray | None,
    w_given: float | None,
    *,
    check: bool = True,
) -> DMVResult:
    """:func:`dmv_update` on converted inputs (the shared core of DMV and LDMV).

    ``p`` from ``pair``, ``x_v`` / ``r_v`` from ``check_correction``, ``w_given`` from
    :func:`checked_omega` (``None``: optimise eq. 6). ``check``: refuse a non-finite result
    (float64 overflow) with a ``ValueError``.
    """
    n, m = p.P_i.shape[0], p.H_i.shape[0]
    _check_dims(n, m)
    try:
        P, K, w, ld = _solve(p, w_given)
    except (OverflowError, ZeroDivisionError, np.linalg.LinAlgError):
        raise overflow_error("dmv_update") from None
    dx = x = None
    if r_v is not None:
        dx = K @ r_v  # dx = K (z - z_hat)
        x = None if x_v is None else x_v + dx  # x+ = x- + K (z - z_hat)
    if check and (math.isnan(ld) or not all_finite(P, K, *(v for v in (dx, x) if v is not None))):
        raise overflow_error("dmv_update")
    require_spd(P, "dmv_update", "the updated covariance P_i+")  # SPD on any BLAS
    return DMVResult(P=P, K=K, omega=float(w), updated=w < 1.0, log_det=ld, dx=dx, x=x)


def _solve(p: Pair, w_given: float | None) -> tuple[FloatArray, FloatArray, float, float]:
    """``(P, K, w, log det P)`` of the DMV update on converted inputs."""
    n, m = p.P_i.shape[0], p.H_i.shape[0]
    if m == 1:  # scalar fast path: everything in floats, a and b in units of r
        h_i, h_j, r = p.H_i[0], p.H_j[0], float(p.R[0, 0])
        Ph = p.P_i @ h_i  # P_i h_i^T, (n,)
        a, b = float(h_i @ Ph) / r, float(h_j @ (p.P_j @ h_j)) / r
        if not b > 0.0:
            raise ValueError(_B_NOT_PD)
        w = _omega_scalar(a, b, n) if w_given is None else w_given
        ld_Pi = logdet_from_chol(p.L_i)
        if w >= 1.0:
            P, K, ld = p.P_i.copy(), np.zeros((n, 1)), ld_Pi
        elif w < 1e-3:  # near 0: the information form keeps the digits
            A, B = np.array([[a * r]]), np.array([[b * r]])
            P, K = _update_at(p, A, B, w)
            ld = _cost(p, A, B, w)
        else:
            s = a / w + b / (1.0 - w) + 1.0  # S(w) / r
            K = Ph[:, None] / (w * s * r)  # Kbar = (P_i/w) h_i^T S^-1
            P = p.P_i / w  # Pbar = P_i/w - Kbar S Kbar^T
            P -= (s * r) * K * K.T
            q = (1.0 - w) * a + w * b + w * (1.0 - w)
            ld = ld_Pi - (n - 1) * math.log(w) + math.log(b + 1.0 - w) - math.log(q)
        return P, K, w, ld
    PHt = p.P_i @ p.H_i.T
    A, B = p.H_i @ PHt, p.H_j @ p.P_j @ p.H_j.T
    A, B = 0.5 * (A + A.T), 0.5 * (B + B.T)
    try:
        w = _omega_general(A, B, p.R, n) if w_given is None else w_given
    except ValueError as exc:
        if "H_j P_j H_j^T" in str(exc):
            raise ValueError(_B_NOT_PD) from None
        raise
    P, K = _update_at(p, A, B, w)
    return P, K, w, _cost(p, A, B, w)


def checked_omega(omega: Any) -> float:
    """``omega`` as a float in [0, 1]; a real scalar (not bool, str or complex)."""
    if isinstance(omega, float | int) and not isinstance(omega, bool):
        w = float(omega)
    else:
        arr = as_float_array(omega, "omega")
        if arr.ndim != 0:
            raise ShapeError(f"omega must be a scalar, got shape {arr.shape}", "omega")
        w = float(arr)
    if not 0.0 <= w <= 1.0:
        raise ValueError(f"omega must be in [0, 1], got {omega!r}")
    return w


@overload
def dmv_cost(
    omega: float, P_i: ArrayLike, P_j: ArrayLike, H_i: ArrayLike, H_j: ArrayLike, R: ArrayLike
) -> float: ...
@overload
def dmv_cost(
    omega: FloatArray | Sequence[float],
    P_i: ArrayLike,
    P_j: ArrayLike,
    H_i: ArrayLike,
    H_j: ArrayLike,
    R: ArrayLike,
) -> FloatArray: ...
def dmv_cost(
    omega: ArrayLike, P_i: ArrayLike, P_j: ArrayLike, H_i: ArrayLike, H_j: ArrayLike, R: ArrayLike
) -> FloatArray | float:
    """``log det Pbar(omega)`` of eq. (6) from m x m determinants (see the module docstring).

    Args:
        omega: a weight or an array of weights in [0, 1] (``0`` only when ``n_i <= m``).
        P_i: (n_i, n_i) SPD.
        P_j: (n_j, n_j) SPD.
        H_i: (m, n_i).
        H_j: (m, n_j).
        R: (m, m) SPD.

    Returns:
        A float for a scalar ``omega``, else an array of ``omega``'s shape (``+inf`` where
        ``Pbar`` does not exist).

    Raises:
        TypeError: an argument is not real numeric (complex, bool, str, object).
        ValueError: as :func:`dmv_update`, or ``omega`` outside [0, 1].
    """
    w = as_float_array(omega, "omega")
    if np.any(~((w >= 0.0) & (w <= 1.0))):
        raise ValueError("omega must lie in [0, 1]")
    p = validate_pair(P_i, P_j, H_i, H_j, R)
    A = p.H_i @ p.P_i @ p.H_i.T
    B = p.H_j @ p.P_j @ p.H_j.T
    try:
        out = np.array([_cost(p, A, B, float(v)) for v in w.ravel()]).reshape(w.shape)
    except (OverflowError, ZeroDivisionError, np.linalg.LinAlgError):
        raise overflow_error("dmv_cost") from None
    if np.any(np.isnan(out)) or np.any(out == -np.inf):
        raise overflow_error("dmv_cost")
    return float(out) if out.ndim == 0 else out
