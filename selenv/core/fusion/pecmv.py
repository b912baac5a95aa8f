"""PECMV: update with the most conservative admissible cross-covariance (eqs. 7-9, 11-12).

PECMV picks the cross-covariance ``X`` of the joint prior ``[[P_i, X], [X^T, P_j]]`` (eq. 7)
that maximises the determinant of agent ``i``'s updated covariance (eq. 8) and updates with it
(eq. 9). By Woodbury the updated marginal is ``P_i - U(X) S(X)^-1 U(X)^T`` with
``U(X) = P_i H_i^T + X H_j^T`` and ``S(X) = H_J P_J(X) H_J^T + R``, both affine in ``X``.

Parametrisation (eqs. 11-12): ``X = L_i C L_j^T`` with ``P = L L^T`` the lower Cholesky
factor, i.e. the paper's ``sqrt(P) = L^T`` (upper triangular, ``P = sqrt(P)^T sqrt(P)``), so
``C = L_i^-1 X L_j^-T``; ``X`` is admissible iff ``||C||_2 <= 1``.

**Exact reduction to m dimensions.** Whiten ``G_i = L_R^-1 H_i L_i``, ``G_j = L_R^-1 H_j L_j``
(m x n). The updated marginal is ``L_i (I - V S^-1 V^T) L_i^T`` with ``V = G_i^T + C G_j^T``
and ``S = V^T V + N(C)``, ``N(C) = I_m + G_j (I - C^T C) G_j^T``, so::

    log det P_i+ = log det P_i + log det N(C) - log det S(C)

Let ``G_i^T = Q_i T_i``, ``G_j^T = Q_j T_j`` (thin QR, ``T`` at most m x m) and
``D = Q_i^T C Q_j``. ``S`` depends on ``C`` only through ``D``, and
``Q_j^T C^T C Q_j >= D^T D`` (as ``Q_i Q_i^T <= I``), so ``C -> Q_i D Q_j^T`` (same norm bound)
never lowers the objective: PECMV is the same problem with ``P_i = I_p``, ``P_j = I_q``,
``R = I_m``, ``H_i = T_i^T``, ``H_j = T_j^T`` and ``X = D`` (p, q <= m) whatever n is.

**Closed forms.** ``log det P_i - log det P_i+ = 2 I(x_i; z)``; with ``s = G_i u_i`` (what z
sees of agent i) and ``e = G_j u_j + v`` (agent j's part plus noise, ``z = s + e``),
``I(s; z) = h(s) - h(e | z) >= h(s) - h(e)``, with equality iff ``e`` is uncorrelated with
``z``. With ``Ahat = G_i G_i^T`` and ``Bhat = G_j G_j^T``:

* no update: if ``Ahat <= Bhat`` (Loewner), ``C = -G_i^T Bhat^-1 G_j`` has ``||C|| <= 1`` and
  makes ``V = 0``: the measurement carries no information on ``x_i`` (``K = 0``). Conversely
  ``V = 0`` needs ``Ahat = G_j C^T C G_j^T <= Bhat``, so the rule is iff.
* interior: ``Cov(s, e) = -(Bhat + I)`` makes ``e`` uncorrelated with ``z`` and attains the
  bound; it is admissible iff ``Dt = -L_A^-1 (Bhat + I) L_B^-T`` (``Ahat = L_A L_A^T``,
  ``Bhat = L_B L_B^T``) has ``||Dt||_2 <= 1``, and then ``C = (L_A^-1 G_i)^T Dt (L_B^-1 G_j)``.
* otherwise the constraint ``||D|| <= 1`` is active and the reduced MAXDET problem (blocks of
  size at most 2m) is solved by Clarabel directly (:func:`~selenv.core.fusion.sdp.solve_reduced`,
  about a millisecond against ~0.1 s for the full cvxpy problem).

For ``m = 1`` (``alpha = ||G_i||``, ``beta = ||G_j||``) these are the closed form of the notes:
no update when ``beta >= alpha``, else ``rho* = min(beta, (beta^2 + 1) / alpha)`` (interior /
boundary), ``C = -(rho* / beta) g_i g_j^T / (alpha beta)``,
``P_i+ = P_i - (alpha - rho*)^2 / (alpha^2 r s) P_i h_i^T h_i P_i`` with
``s = (alpha - rho*)^2 + beta^2 + 1 - rho*^2`` (all in units of r).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import cho_solve
from scipy.linalg.lapack import dpotrf

from selenv.core.fusion.common import (
    Pair,
    blame,
    check_correction,
    chol,
    finite_matrix,
    logdet_from_chol,
    overflow_error,
    pair,
    tri_solve,
    validate_pair,
)
from selenv.core.fusion.sdp import (
    SDP_FEASIBILITY_TOL,
    exact_posterior,
    pecmv_sdp_cvxpy,
    solve_reduced,
)
from selenv.core.linalg import FloatArray, ShapeError, all_finite
from selenv.core.spd import require_spd

__all__ = [
    "PECMV_METHODS",
    "PECMVResult",
    "checked_C",
    "pecmv_from_pair",
    "pecmv_objective",
    "pecmv_update",
    "solve_guarded",
]

PECMV_METHODS = ("auto", "closed_form", "fast", "sdp")
_RULE_RTOL = 1e-12  # relative slack of the Loewner test Ahat <= Bhat


@dataclass(frozen=True, kw_only=True, eq=False)
class PECMVResult:
    """Result of :func:`pecmv_update` (agent ``i``'s posterior).

    Attributes:
        P: (n_i, n_i) updated covariance ``P_PECMV^i+`` (eq. 9b).
        K: (n_i, m) gain ``K_PECMV^i`` (zero when not ``updated``).
        X: (n_i, n_j) the optimiser ``X*`` of eq. (8), admissible (``||C||_2 <= 1``).
        C: (n_i, n_j) ``C* = L_i^-1 X* L_j^-T`` (eq. 12 with ``sqrt(P) = L^T``, ``P = L L^T``).
        updated: False when the no-update rule ``H_i P_i H_i^T <= H_j P_j H_j^T`` applies.
        log_det: ``log det P`` (the optimal value of eq. 8a).
        path: which solver produced ``X``: ``closed_form`` (m = 1), ``no_update``,
            ``interior`` or ``reduced_sdp`` (the fast path for m > 1), ``sdp`` (cvxpy
            reference) or ``given`` (``C`` passed in).
        dx: (n_i,) correction ``K (z - z_hat)`` (eq. 9a), or None without ``residual``.
        x: (n_i,) posterior mean ``x_i + dx``, or None without ``x_i``.
    """

    P: FloatArray
    K: FloatArray
    X: FloatArray
    C: FloatArray
    updated: bool
    log_det: float
    path: str
    dx: FloatArray | None = None
    x: FloatArray | None = None


_NOT_PD = (
    "pecmv_update: the updated covariance P_i+ is not numerically positive definite (its "
    "condition number exceeds 1 / eps ~ 1e16, e.g. H_i P_i H_i^T is ~1e16 times larger than "
    "R, so P_i - U S^-1 U^T cancels); rescale or regularise the problem"
)


def solve_guarded(p: Pair, method: str, C_given: FloatArray | None, func: str) -> PECMVResult:
    """:func:`_solve` with float64 overflow and a conic-solver crash turned into ``ValueError``.

    Clarabel panics (a Rust ``PanicException``, which derives from ``BaseException`` and would
    escape ``except Exception``) on a reduced problem too ill-conditioned for its eigenvalue
    routine, e.g. whitened gains ``||G_i||`` and ``||G_j||`` 1e100 apart.
    """
    try:
        return _solve(p, method, C_given)
    except (OverflowError, ZeroDivisionError, np.linalg.LinAlgError):
        raise overflow_error(func) from None
    except BaseException as exc:
        if type(exc).__name__ != "PanicException":
            raise
        msg = (str(exc).splitlines() or ["panic"])[0]
        raise ValueError(
            f"{func}: the reduced PECMV problem is too ill-conditioned for the conic solver "
            f"(Clarabel panicked: {msg}); the whitened measurement gains of agents i and j "
            "differ by too many orders of magnitude: rescale the problem"
        ) from None


def _assemble(p: Pair, X: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    """``(P, K, log det P)`` of the Kalman update of the joint prior with cross-covariance X."""
    U = p.P_i @ p.H_i.T + X @ p.H_j.T  # U(X) = P_i H_i^T + X H_j^T, (n_i, m)
    V = X.T @ p.H_i.T + p.P_j @ p.H_j.T  # X^T H_i^T + P_j H_j^T, (n_j, m)
    S = p.H_i @ U + p.H_j @ V + p.R  # S(X) = H_J P_J(X) H_J^T + R
    L_S = chol(0.5 * (S + S.T), "S(X) = H P_J(X) H^T + R")
    M = tri_solve(L_S, U.T)  # L_S^-1 U^T
    K = tri_solve(L_S, M, trans=True).T  # K = U S^-1 (eq. 9)
    P = p.P_i - M.T @ M  # P+ = P_i - U S^-1 U^T (eq. 9b by Woodbury)
    P = 0.5 * (P + P.T)
    L_P, info = dpotrf(P, lower=1, clean=1)
    ld = logdet_from_chol(L_P) if info == 0 else float(np.linalg.slogdet(P)[1])
    return P, K, ld


def _whitened(p: Pair) -> tuple[FloatArray, FloatArray]:
    """``G_i = L_R^-1 H_i L_i`` (m, n_i) and ``G_j = L_R^-1 H_j L_j`` (m, n_j)."""
    G_i = tri_solve(p.L_R, p.H_i @ p.L_i)
    G_j = tri_solve(p.L_R, p.H_j @ p.L_j)
    return G_i, G_j


def _no_update(Ahat: FloatArray, Bhat: FloatArray) -> bool:
    """The no-update rule ``Ahat <= Bhat`` (Loewner, relative slack ``_RULE_RTOL``)."""
    scale = max(float(np.trace(Ahat)), float(np.trace(Bhat)), 1e-300)
    return float(np.linalg.eigvalsh(Bhat - Ahat)[0]) >= -_RULE_RTOL * scale


def _fast_C(p: Pair) -> tuple[FloatArray, str]:
    """Optimal ``C`` (n_i, n_j) via the reduction: closed forms, else the reduced SDP."""
    G_i, G_j = _whitened(p)
    Ahat, Bhat = G_i @ G_i.T, G_j @ G_j.T
    L_B, info_B = dpotrf(Bhat, lower=1, clean=1)
    if _no_update(Ahat, Bhat):  # C = -G_i^T Bhat^+ G_j: V = G_i^T + C G_j^T = 0
        if info_B == 0:
            return -G_i.T @ cho_solve((L_B, True), G_j, check_finite=False), "no_update"
        return -G_i.T @ np.linalg.pinv(Bhat, hermitian=True) @ G_j, "no_update"
    L_A, info_A = dpotrf(Ahat, lower=1, clean=1)
    if info_A == 0 and info_B == 0:  # interior candidate Cov(s, e) = -(Bhat + I)
        m = Ahat.shape[0]
        Z = -(Bhat + np.eye(m))
        Dt = tri_solve(L_B, tri_solve(L_A, Z).T).T
        norm = float(np.linalg.norm(Dt, 2))
        if norm <= 1.0 + 1e-12:
            Dt = Dt / max(norm, 1.0)  # round-off only: keep ||C||_2 <= 1 exactly
            F_i = tri_solve(L_A, G_i)  # rows orthonormal: (L_A^-1 G_i)
            F_j = tri_solve(L_B, G_j)
            return F_i.T @ Dt @ F_j, "interior"
    Q_i, T_i = np.linalg.qr(G_i.T)  # G_i^T = Q_i T_i
    Q_j, T_j = np.linalg.qr(G_j.T)
    return Q_i @ solve_reduced(T_i, T_j) @ Q_j.T, "reduced_sdp"


def _scalar(p: Pair) -> PECMVResult:
    """Closed form for ``m = 1`` (see the module docstring), without corrections."""
    h_i, h_j, r = p.H_i[0], p.H_j[0], float(p.R[0, 0])
    sr = math.sqrt(r)
    g_i, g_j = p.L_i.T @ h_i / sr, p.L_j.T @ h_j / sr  # whitened G_i^T, G_j^T
    alpha, beta = math.sqrt(float(g_i @ g_i)), math.sqrt(float(g_j @ g_j))
    ld_Pi = logdet_from_chol(p.L_i)
    n_i, n_j = h_i.size, h_j.size
    if beta >= alpha:  # no update: C = -(alpha / beta) u_i u_j^T makes V = 0
        c = -alpha / beta if beta > 0.0 else 0.0
        C = np.outer(g_i, g_j) * (c / (alpha * beta)) if alpha > 0.0 else np.zeros((n_i, n_j))
        X = p.L_i @ C @ p.L_j.T
        return PECMVResult(
            P=p.P_i.copy(), K=np.zeros((n_i, 1)), X=X, C=C, updated=False, log_det=ld_Pi,
            path="closed_form",
        )  # fmt: skip
    rho = min(beta, (beta * beta + 1.0) / alpha)  # rho* (interior or boundary)
    s = (alpha - rho) ** 2 + beta * beta + 1.0 - rho * rho  # S / r
    Ph = p.P_i @ h_i  # P_i h_i^T
    K = Ph * ((alpha - rho) / (alpha * r * s))  # K = U / S, U = P_i h_i^T (alpha - rho)/alpha
    P = p.P_i - (r * s) * np.outer(K, K)  # P+ = P_i - U U^T / S
    if beta > 0.0:
        C = np.outer(g_i, g_j) * (-rho / (alpha * beta * beta))  # c = -rho/beta, |c| <= 1
        X = np.outer(Ph, p.P_j @ h_j) * (-rho / (alpha * beta * beta * r))  # L_i C L_j^T
    else:
        C, X = np.zeros((n_i, n_j)), np.zeros((n_i, n_j))
    ld = ld_Pi + math.log((beta * beta + 1.0 - rho * rho) / s)  # det(P - u u^T/S) = ...
    return PECMVResult(P=P, K=K[:, None], X=X, C=C, updated=True, log_det=ld, path="closed_form")


def _c_of_x(p: Pair, X: FloatArray) -> FloatArray:
    """``C = L_i^-1 X L_j^-T`` (eq. 12)."""
    return tri_solve(p.L_j, tri_solve(p.L_i, X).T).T


def _solve(p: Pair, method: str, C_given: FloatArray | None = None) -> PECMVResult:
    """PECMV on validated inputs (no state correction)."""
    m = p.H_i.shape[0]
    if C_given is None and method in ("auto", "closed_form", "fast") and m == 1:
        return _scalar(p)
    if C_given is not None:
        C, path = C_given, "given"
    elif method == "closed_form":
        raise ValueError(
            f"method='closed_form' needs a scalar measurement (m = 1), got m = {m}; use 'fast'"
        )
    elif method == "sdp":
        return _sdp(p)
    else:
        C, path = _fast_C(p)
    X = p.L_i @ C @ p.L_j.T  # X = L_i C L_j^T (eq. 11)
    if path == "no_update":
        n_i = p.P_i.shape[0]
        P, K, ld = p.P_i.copy(), np.zeros((n_i, m)), logdet_from_chol(p.L_i)
        return PECMVResult(P=P, K=K, X=X, C=C, updated=False, log_det=ld, path=path)
    P, K, ld = _assemble(p, X)
    updated = bool(np.any(K != 0.0)) if path == "given" else True
    return PECMVResult(P=P, K=K, X=X, C=C, updated=updated, log_det=ld, path=path)


def _sdp(p: Pair) -> PECMVResult:
    """The cvxpy reference: its ``X``, checked admissible, and that X's exact posterior.

    The solver's ``C = L_i^-1 X L_j^-T`` may exceed the contraction bound by round-off; up
    to ``SDP_FEASIBILITY_TOL`` its singular values are clipped to 1, beyond it the answer is
    refused. ``P``, ``K`` and ``log_det`` are then computed from the returned ``X`` in exact
    rational arithmetic (:func:`~selenv.core.fusion.sdp.exact_posterior`), so they are the
    posterior of that ``X`` to float64 rounding however the problem is scaled.
    """
    C = _c_of_x(p, pecmv_sdp_cvxpy(p.P_i, p.P_j, p.H_i, p.H_j, p.R))
    U_, sv, Vt = np.linalg.svd(C, full_matrices=False)
    if not np.all(np.isfinite(sv)) or sv.max(initial=0.0) > 1.0 + SDP_FEASIBILITY_TOL:
        raise ValueError(
            "pecmv_update(method='sdp'): the conic solver's cross-covariance is not admissible "
            f"(||C||_2 = {sv.max(initial=0.0):.9g} > 1 + {SDP_FEASIBILITY_TOL:g}); the full SDP "
            "is too badly scaled for it: use method='fast' (or 'auto'), the exact reduction "
            "to m dimensions"
        )
    C = (U_ * np.minimum(sv, 1.0)) @ Vt  # clip solver round-off: ||C||_2 <= 1
    X = p.L_i @ C @ p.L_j.T  # X = L_i C L_j^T (eq. 11)
    P, K, ld = exact_posterior(p.P_i, p.P_j, p.H_i, p.H_j, p.R, X)
    G_i, G_j = _whitened(p)
    updated = not _no_update(G_i @ G_i.T, G_j @ G_j.T)
    return PECMVResult(P=P, K=K, X=X, C=C, updated=updated, log_det=ld, path="sdp")


def pecmv_update(
    P_i: ArrayLike,
    P_j: ArrayLike,
    H_i: ArrayLike,
    H_j: ArrayLike,
    R: ArrayLike,
    *,
    x_i: ArrayLike | None = None,
    residual: ArrayLike | None = None,
    method: str = "auto",
    C: ArrayLike | None = None,
    validate: bool = True,
) -> PECMVResult:
    """PECMV update of agent ``i`` from its measurement of agent ``j`` (eqs. 8-9).

    Args:
        P_i: (n_i, n_i) SPD prior covariance of agent i.
        P_j: (n_j, n_j) SPD prior covariance of agent j.
        H_i: (m, n_i) measurement Jacobian w.r.t. agent i.
        H_j: (m, n_j) measurement Jacobian w.r.t. agent j.
        R: (m, m) SPD measurement noise.
        x_i: (n_i,) prior mean of agent i (needs ``residual``); gives ``x`` in the result.
        residual: (m,) ``z - z_hat``; gives ``dx = K residual``.
        method: ``"auto"`` (closed form for m = 1, the exact fast path otherwise),
            ``"closed_form"`` (m = 1 only), ``"fast"`` (exact reduction to m dimensions:
            closed forms or a small Clarabel MAXDET; the m = 1 closed form when m = 1) or
            ``"sdp"`` (the full problem in cvxpy with Clarabel: the reference, slow; its
            ``P``, ``K`` and ``log_det`` are the posterior of the returned ``X`` computed in
            exact rational arithmetic; badly scaled problems, which Clarabel cannot solve
            in this form, are a ``ValueError`` pointing to ``"fast"``).
        C: (n_i, n_j) use ``X = L_i C L_j^T`` instead of optimising (e.g. a learned LPECMV
            estimate); needs ``||C||_2 <= 1``.
        validate: check shapes, symmetry, finiteness, definiteness and the valid range
            (default). ``False`` is for hot paths with known-good float64 inputs (as in
            ``kf_update``): it skips those checks, about half the cost of a scalar update;
            types are still checked and non-PD factors still raise.

    Returns:
        :class:`PECMVResult` with ``P``, ``K``, ``X*``, ``C*`` and the no-update flag.

    Raises:
        TypeError: an argument is not real numeric (complex, bool, str, object), or ``method``
            is not a str.
        ValueError: bad shapes (naming the argument that disagrees with the others), NaN/inf,
            non-SPD ``P_i``/``P_j``/``R``, entries outside the valid range
            (:func:`~selenv.core.linalg.check_magnitude`) or a result that overflows float64,
            an unknown ``method``, ``closed_form`` with m > 1, ``x_i`` without ``residual``,
            or a ``C`` that is not a contraction (names the argument); ``method="sdp"``
            when cvxpy/Clarabel fails or returns an inadmissible ``X`` (names the method
            and the cause).
        RuntimeError: if the fast path's reduced conic problem and its barrier fallback
            both fail.
    """
    if not isinstance(method, str):
        raise TypeError(f"method must be a str, got {type(method).__name__}")
    if method not in PECMV_METHODS:
        raise ValueError(f"method must be one of {PECMV_METHODS}, got {method!r}")
    p = pair(P_i, P_j, H_i, H_j, R, validate=validate, x_i=x_i, residual=residual, C=C)
    x_v, r_v = check_correction(x_i, residual, p.P_i.shape[0], p.H_i.shape[0])
    C_given = None
    if C is not None:
        C_given = checked_C(C, p, P_i=P_i, P_j=P_j, H_i=H_i, H_j=H_j)
    return pecmv_from_pair(p, method, C_given, x_v, r_v, check=validate)


def checked_C(C: ArrayLike, p: Pair, **raw: Any) -> FloatArray:
    """``C`` (n_i, n_j) finite, in range and a contraction ``||C||_2 <= 1`` (+ 1e-9 slack).

    ``raw``: the raw ``P_i, P_j, H_i, H_j`` to name the right argument on a shape error.
    """
    try:
        C_given = finite_matrix(C, "C", (p.P_i.shape[0], p.P_j.shape[0]))
    except ShapeError as exc:
        raise blame(exc, **raw, C=C) from None
    norm = float(np.linalg.norm(C_given, 2))
    if norm > 1.0 + 1e-9:
        raise ValueError(f"C must be a contraction (||C||_2 <= 1), got ||C||_2 = {norm:.6g}")
    return C_given


def pecmv_from_pair(
    p: Pair,
    method: str,
    C_given: FloatArray | None,
    x_v: FloatArray | None,
    r_v: FloatArray | None,
    *,
    check: bool = True,
) -> PECMVResult:
    """:func:`pecmv_update` on converted inputs (the shared core of PECMV and LPECMV).

    As :func:`~selenv.core.fusion.dmv.dmv_from_pair`; ``C_given`` from :func:`checked_C`.
    """
    res = solve_guarded(p, method, C_given, "pecmv_update")
    dx = x = None
    if r_v is not None:
        dx = res.K @ r_v  # dx = K (z - z_hat)
        x = None if x_v is None else x_v + dx  # x+ = x- + K (z - z_hat)
    parts = (res.P, res.K, res.X, dx, x)
    if check and not all_finite(*(v for v in parts if v is not None)):
        raise overflow_error("pecmv_update")
    require_spd(res.P, "pecmv_update", "the updated covariance P_i+")  # SPD on any BLAS
    if check and not math.isfinite(res.log_det):
        raise ValueError(_NOT_PD)
    if dx is None:
        return res
    return PECMVResult(
        P=res.P, K=res.K, X=res.X, C=res.C, updated=res.updated, log_det=res.log_det,
        path=res.path, dx=dx, x=x,
    )  # fmt: skip


def pecmv_objective(
    X: ArrayLike, P_i: ArrayLike, P_j: ArrayLike, H_i: ArrayLike, H_j: ArrayLike, R: ArrayLike
) -> float:
    """``log det`` of agent i's updated marginal for cross-covariance ``X`` (eq. 8a).

    Args:
        X: (n_i, n_j) cross-covariance; should be admissible (see
            :func:`~selenv.core.fusion.joint_covariance_is_admissible`).
        P_i: (n_i, n_i) SPD.
        P_j: (n_j, n_j) SPD.
        H_i: (m, n_i).
        H_j: (m, n_j).
        R: (m, m) SPD.

    Returns:
        ``log det(P_i - U(X) S(X)^-1 U(X)^T)``, which PECMV maximises.

    Raises:
        TypeError: an argument is not real numeric.
        ValueError: as :func:`pecmv_update` (names the argument).
    """
    p = validate_pair(P_i, P_j, H_i, H_j, R, X=X)
    try:
        Xm = finite_matrix(X, "X", (p.P_i.shape[0], p.P_j.shape[0]))
    except ShapeError as exc:
        raise blame(exc, P_i=P_i, P_j=P_j, H_i=H_i, H_j=H_j, X=X) from None
    try:
        ld = _assemble(p, Xm)[2]
    except (OverflowError, ZeroDivisionError, np.linalg.LinAlgError):
        raise overflow_error("pecmv_objective") from None
    if math.isnan(ld):
        raise overflow_error("pecmv_objective")
    return ld  # -inf: P_i+ singular for this X (e.g. an inadmissible X)
