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

Validation: real types only (complex, bool, str, object raise ``TypeError``), trailing shapes
(a mismatch names the argument that disagrees with the others), broadcastable leading axes,
finiteness and the valid range ``|entry| <= MAX_ABS`` of
:func:`~selenv.core.linalg.check_magnitude`; a result that overflows float64 raises
``ValueError``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from selenv.core.linalg import (
    MAX_ABS,
    FloatArray,
    ShapeError,
    as_float_array,
    blame_shapes,
    check_finite,
    check_magnitude,
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
    """Types, trailing shapes ``(n, n)``, ``(m, n)``, ``(m, m)``, batch axes, finite, in range."""
    raw = {a_name: A, "F": F, "Q": Q, "H": H, "R": R}
    arrs = {name: as_float_array(value, name) for name, value in raw.items()}
    try:
        for name, arr in arrs.items():
            if arr.ndim < 2:
                raise ShapeError(
                    f"{name} must have at least 2 dimensions, got shape {arr.shape}", name
                )
        n, m = arrs[a_name].shape[-1], arrs["H"].shape[-2]
        want = {a_name: (n, n), "F": (n, n), "Q": (n, n), "H": (m, n), "R": (m, m)}
        for name, arr in arrs.items():
            if arr.shape[-2:] != want[name]:
                raise ShapeError(
                    f"{name} must have trailing shape {want[name]}, got {arr.shape}", name
                )
    except ShapeError as exc:
        templates = {a_name: "... n n", "F": "... n n", "Q": "... n n", "H": "... m n"}
        templates["R"] = "... m m"
        raise (blame_shapes(raw, templates, error=exc) or exc) from None
    seen: tuple[int, ...] = ()
    for name, arr in arrs.items():
        try:
            seen = np.broadcast_shapes(seen, arr.shape[:-2])
        except ValueError:
            raise ShapeError(
                f"{name} has leading (batch) axes {arr.shape[:-2]} that do not broadcast with "
                f"those of the arguments before it, {seen}",
                name,
            ) from None
    for name, arr in arrs.items():
        check_magnitude(check_finite(arr, name), name)
    return tuple(arrs.values())


def _finite(out: FloatArray, func: str) -> FloatArray:
    if not np.all(np.isfinite(out)):
        raise ValueError(
            f"{func}: the result is not representable in float64 (overflow); the inputs must "
            f"satisfy |entry| <= {MAX_ABS:g} and the problem must not be so ill-conditioned "
            "that products or inverses of them exceed that range (rescale the problem)"
        )
    return out


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
        TypeError: an argument is not real numeric (complex, bool, str, object).
        ValueError: NaN/inf, mismatched shapes (naming the argument that disagrees with the
            others), entries outside the valid range, ``Q``, ``R``, ``J + D11`` not SPD, or a
            result that overflows float64.
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
    J_next = symmetrize(D22 - _T(B) @ B)  # J+ = D22 - D21 (J + D11)^-1 D12, D21 = D12^T
    return _finite(J_next, "pcrlb_step_information")


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
        TypeError: an argument is not real numeric (complex, bool, str, object).
        ValueError: NaN/inf, mismatched shapes (naming the argument that disagrees with the
            others), entries outside the valid range, ``S = H M H^T + R`` not SPD, or a result
            that overflows float64.
    """
    Pc_, F_, Q_, H_, R_ = _check(Pc, F, Q, H, R, "Pc")
    M = symmetrize(F_ @ Pc_ @ _T(F_) + Q_)  # M = F Pc F^T + Q
    if H_.shape[-2] == 0:
        return _finite(M, "pcrlb_step_covariance")
    if not np.all(np.isfinite(M)):
        _finite(M, "pcrlb_step_covariance")
    HM = H_ @ M  # H M, (..., m, n)
    S = symmetrize(HM @ _T(H_) + R_)  # S = H M H^T + R
    if not np.all(np.isfinite(S)):
        _finite(S, "pcrlb_step_covariance")
    Ls = cholesky_spd(S, "S = H (F Pc F^T + Q) H^T + R")
    K = _T(np.linalg.solve(_T(Ls), np.linalg.solve(Ls, HM)))  # K = M H^T S^-1 (S K^T = H M)
    n = M.shape[-1]
    I_KH = np.eye(n) - K @ H_  # I - K H
    Pc_next = symmetrize(I_KH @ M @ _T(I_KH) + K @ R_ @ _T(K))  # Joseph form
    return _finite(Pc_next, "pcrlb_step_covariance")
