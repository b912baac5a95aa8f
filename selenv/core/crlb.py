"""Posterior Cramér-Rao lower bound (PCRLB) recursion for additive Gaussian noise.

Tichavský, Muravchik & Nehorai (1998), quoted by Soubaras & Chahbazian (2023) as eqs. (7)-(8).
For ``x_{k+1} = f(x_k) + w_k``, ``w_k ~ N(0, Q)`` and ``z_{k+1} = h(x_{k+1}) + r``,
``r ~ N(0, R)``, with ``F = df/dx`` and ``H = dh/dx`` (evaluated on the true trajectory, or
at the estimate for the approximation of the paper's Algorithm 3), the Fisher information
``J`` obeys::

    D11 = F^T Q^-1 F,   D12 = -F^T Q^-1 = D21^T,   D22 = Q^-1 + H^T R^-1 H        (8)
    J+  = D22 - D21 (J + D11)^-1 D12                                                (7)

The paper's printed eq. (8) carries sign typos (``D11 = -E[F^T Q^-1 F]``,
``D22 = -Q^-1 - E[...]``); this module implements Tichavský's signs, with which ``J`` stays
positive definite. By the matrix inversion lemma the recursion is equivalent to the covariance
form ``Pc+ = ((F Pc F^T + Q)^-1 + H^T R^-1 H)^-1`` with ``Pc = J^-1``: a Kalman covariance
prediction and update. :func:`pcrlb_step_covariance` computes it that way (Joseph form, no
inverse), which also holds for a singular process noise ``Q`` (e.g. one noise source driving
several states), where the information form does not exist.

Shapes: matrices ``(..., n, n)`` with any leading batch axes, broadcast against each other
(``F``, ``Q``, ``H``, ``R`` may be shared by a batch of ``J`` / ``Pc``). ``H`` is ``(..., m, n)``
and ``R`` ``(..., m, m)``; ``m = 0`` (no measurement) gives the prediction alone.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from selenv.core.linalg import (
    FloatArray,
    as_float_array,
    check_finite,
    cholesky_spd,
    symmetrize,
)

__all__ = ["pcrlb_step_covariance", "pcrlb_step_information"]


def _T(A: Any) -> FloatArray:
    """Transpose of the last two axes."""
    return np.swapaxes(A, -1, -2)


def _check(
    A: ArrayLike, F: ArrayLike, Q: ArrayLike, H: ArrayLike, R: ArrayLike, a_name: str
) -> tuple[FloatArray, ...]:
    """Validate finiteness and the trailing shapes ``(n, n)``, ``(m, n)``, ``(m, m)``."""
    out = []
    for value, name in ((A, a_name), (F, "F"), (Q, "Q"), (H, "H"), (R, "R")):
        arr = check_finite(as_float_array(value, name), name)
        if arr.ndim < 2:
            raise ValueError(f"{name} must have at least 2 dimensions, got shape {arr.shape}")
        out.append(arr)
    A_, F_, Q_, H_, R_ = out
    n = A_.shape[-1]
    m = H_.shape[-2]
    for arr, name, want in (
        (A_, a_name, (n, n)),
        (F_, "F", (n, n)),
        (Q_, "Q", (n, n)),
        (H_, "H", (m, n)),
        (R_, "R", (m, m)),
    ):
        if arr.shape[-2:] != want:
            raise ValueError(f"{name} must have trailing shape {want}, got {arr.shape}")
    return A_, F_, Q_, H_, R_


def pcrlb_step_information(
    J: ArrayLike, F: ArrayLike, Q: ArrayLike, H: ArrayLike, R: ArrayLike
) -> FloatArray:
    """One step of the information recursion, eqs. (7)-(8), literally.

    With ``Q = L L^T`` (Cholesky) and ``A = L^-1 F``: ``D11 = A^T A``, ``D12 = -A^T L^-1``,
    ``D21 = D12^T``, ``D22 = Q^-1 + G^T G`` with ``G = L_R^-1 H`` (``R = L_R L_R^T``); then with
    ``J + D11 = M M^T`` and ``B = M^-1 D12``, ``D21 (J + D11)^-1 D12 = B^T B``. Only triangular
    solves; ``Q^-1`` is formed as ``L^-T L^-1`` because ``D22`` needs it as a matrix.

    Args:
        J: Fisher information at step ``k``, SPD ``(..., n, n)``.
        F: state-transition Jacobian ``df/dx``, ``(..., n, n)``.
        Q: process-noise covariance, SPD ``(..., n, n)`` (a singular ``Q`` has no information
            form: use :func:`pcrlb_step_covariance`).
        H: measurement Jacobian at step ``k + 1``, ``(..., m, n)``; ``m = 0`` allowed.
        R: measurement-noise covariance, SPD ``(..., m, m)``.

    Returns:
        ``J+`` ``(..., n, n)``, symmetrized.

    Raises:
        ValueError: NaN/inf, mismatched shapes, or ``Q``, ``R``, ``J + D11`` not SPD.
    """
    J_, F_, Q_, H_, R_ = _check(J, F, Q, H, R, "J")
    n = J_.shape[-1]
    L = cholesky_spd(Q_, "Q")  # Q = L L^T
    Linv = np.linalg.solve(L, np.broadcast_to(np.eye(n), L.shape))  # L^-1 (triangular solve)
    A = Linv @ F_  # A = L^-1 F
    D11 = _T(A) @ A  # D11 = F^T Q^-1 F
    D12 = -_T(A) @ Linv  # D12 = -F^T Q^-1 = -A^T L^-1
    D22 = _T(Linv) @ Linv  # Q^-1 = L^-T L^-1
    if H_.shape[-2] > 0:
        G = np.linalg.solve(cholesky_spd(R_, "R"), H_)  # G = L_R^-1 H
        D22 = D22 + _T(G) @ G  # D22 = Q^-1 + H^T R^-1 H
    M = cholesky_spd(symmetrize(J_ + D11), "J + D11")  # J + D11 = M M^T
    B = np.linalg.solve(M, np.broadcast_to(D12, np.broadcast_shapes(M.shape, D12.shape)))
    return symmetrize(D22 - _T(B) @ B)  # J+ = D22 - D21 (J + D11)^-1 D12, D21 = D12^T


def pcrlb_step_covariance(
    Pc: ArrayLike, F: ArrayLike, Q: ArrayLike, H: ArrayLike, R: ArrayLike
) -> FloatArray:
    """One step of the bound in covariance form, ``Pc+ = ((F Pc F^T + Q)^-1 + H^T R^-1 H)^-1``.

    Evaluated as a Kalman covariance step without any inverse: ``M = F Pc F^T + Q``,
    ``S = H M H^T + R = L L^T``, ``K = M H^T S^-1`` (Cholesky solves) and the Joseph form
    ``Pc+ = (I - K H) M (I - K H)^T + K R K^T``, which stays symmetric positive semi-definite
    for an ill-conditioned or singular ``Q`` (only ``S`` must be SPD). Equal to
    ``inv(pcrlb_step_information(inv(Pc), ...))`` whenever ``Q`` is SPD (tested).

    Args:
        Pc: bound (``J^-1``) at step ``k``, symmetric PSD ``(..., n, n)``.
        F: state-transition Jacobian, ``(..., n, n)``.
        Q: process-noise covariance, symmetric PSD ``(..., n, n)``; may be singular.
        H: measurement Jacobian at step ``k + 1``, ``(..., m, n)``; ``m = 0`` gives the
            prediction ``F Pc F^T + Q`` alone.
        R: measurement-noise covariance, SPD ``(..., m, m)``.

    Returns:
        ``Pc+`` ``(..., n, n)``, symmetrized.

    Raises:
        ValueError: NaN/inf, mismatched shapes, or ``S = H M H^T + R`` not SPD.
    """
    Pc_, F_, Q_, H_, R_ = _check(Pc, F, Q, H, R, "Pc")
    M = symmetrize(F_ @ Pc_ @ _T(F_) + Q_)  # M = F Pc F^T + Q
    if H_.shape[-2] == 0:
        return M
    HM = H_ @ M  # H M, (..., m, n)
    S = symmetrize(HM @ _T(H_) + R_)  # S = H M H^T + R
    Ls = cholesky_spd(S, "S = H (F Pc F^T + Q) H^T + R")
    K = _T(np.linalg.solve(_T(Ls), np.linalg.solve(Ls, HM)))  # K = M H^T S^-1 (S K^T = H M)
    n = M.shape[-1]
    I_KH = np.eye(n) - K @ H_  # I - K H
    return symmetrize(I_KH @ M @ _T(I_KH) + K @ R_ @ _T(K))  # Joseph form
