"""Covariance intersection (CI) of two estimates with unknown correlation, and its variants.

Two estimates ``(a, A)`` and ``(b, B)`` of the same n-dimensional state, correlated in an
unknown way, are fused as::

    CI:           P^-1 = w A^-1 + (1-w) B^-1,   x = P (w A^-1 a + (1-w) B^-1 b)
    inverse CI:   P^-1 = A^-1 + B^-1 - (w A + (1-w) B)^-1                  (Noack et al. 2017)
                  x = P (K a + L b),  K = A^-1 - w G^-1,  L = B^-1 - (1-w) G^-1,  G = w A + (1-w) B

with ``w`` in [0, 1] chosen by one of

==================  =========================================================================
``optimal``         argmin log det P(w) of CI (convex in w; exact 1-D Newton on the derivative)
``fast``            Niehsen: ``w = tr B / (tr A + tr B)``
``improved_fast``   Fraenken & Hupper: ``w = [det S - det B^-1 + det A^-1] / (2 det S)``,
                    ``S = A^-1 + B^-1``
``inverse``         inverse CI with argmin log det of its covariance (also convex in w)
==================  =========================================================================

Every variant is evaluated in the basis that diagonalises ``A`` and ``B`` together: with
``B = L L^T`` (Cholesky) and ``L^-1 A L^-T = V diag(mu) V^T`` (``eigh``), ``T = L V`` gives
``B = T T^T`` and ``A = T diag(mu) T^T``, so that::

    CI:   P(w) = T diag(mu / (w + (1-w) mu)) T^T,
          log det P(w) = log det B - sum log(1 + w (1/mu - 1))      (convex in w)
    ICI:  P(w) = T diag(1 / d) T^T,  d = 1/mu + 1 - 1 / (w mu + 1 - w)

No matrix is inverted; the cost is one Cholesky, one ``eigh`` and a few triangular solves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from selenv.core.fusion.common import logdet_from_chol, root_increasing, spd, tri_solve, vector
from selenv.core.linalg import FloatArray

__all__ = ["CI_METHODS", "CIResult", "covariance_intersection"]

CI_METHODS = ("optimal", "fast", "improved_fast", "inverse")


@dataclass(frozen=True, kw_only=True, eq=False)
class CIResult:
    """Result of :func:`covariance_intersection`.

    Attributes:
        x: (n,) fused mean.
        P: (n, n) fused covariance.
        omega: the weight ``w`` in [0, 1] given to the first estimate ``(a, A)``.
        log_det: ``log det P``.
    """

    x: FloatArray
    P: FloatArray
    omega: float
    log_det: float


def _ci_weight(mu: FloatArray) -> float:
    """``argmin_w -sum log(1 + w g)``, ``g = 1/mu - 1``: the optimal CI weight (convex in w)."""
    g = 1.0 / mu - 1.0
    if -float(np.sum(g)) >= 0.0:  # f'(0) = -sum g >= 0: B alone
        return 0.0
    if float(np.sum(mu)) - mu.size <= 0.0:  # f'(1) = sum mu - n <= 0: A alone
        return 1.0

    def fprime(w: float) -> tuple[float, float]:
        u = g / (1.0 + w * g)  # d/dw log(1 + w g)
        return -float(np.sum(u)), float(np.sum(u * u))  # f'(w), f''(w)

    return root_increasing(fprime, 0.0, 1.0, 0.5)


def _ici_weight(mu: FloatArray) -> float:
    """``argmin_w -sum log d(w)``, ``d = 1/mu + 1 - 1/(1 + w (mu - 1))`` (inverse CI, convex)."""
    c = mu - 1.0
    if -float(np.sum(mu * c)) >= 0.0:  # f'(0) >= 0
        return 0.0
    if -float(np.sum(c / mu**2)) <= 0.0:  # f'(1) <= 0
        return 1.0

    def fprime(w: float) -> tuple[float, float]:
        e = 1.0 + w * c  # w mu + 1 - w
        d = 1.0 / mu + 1.0 - 1.0 / e
        u = c / (e * e * d)  # d'/d
        return -float(np.sum(u)), float(np.sum(u * u + 2.0 * c * c / (e**3 * d)))

    return root_increasing(fprime, 0.0, 1.0, 0.5)


def covariance_intersection(
    a: ArrayLike, A: ArrayLike, b: ArrayLike, B: ArrayLike, *, method: str = "optimal"
) -> CIResult:
    """Fuse two estimates with unknown cross-correlation by covariance intersection.

    Args:
        a: (n,) first mean.
        A: (n, n) SPD covariance of ``a``.
        b: (n,) second mean.
        B: (n, n) SPD covariance of ``b``.
        method: ``"optimal"`` (CI, argmin log det), ``"fast"`` (Niehsen), ``"improved_fast"``
            (Fraenken & Hupper) or ``"inverse"`` (inverse CI, Noack et al. 2017, argmin log det);
            see the module table.

    Returns:
        Fused mean, covariance, weight ``omega`` (on ``A``) and ``log det P``.

    Raises:
        ValueError: bad ``method``, shapes, NaN/inf, or ``A``/``B`` not SPD (names the argument).
    """
    if method not in CI_METHODS:
        raise ValueError(f"method must be one of {CI_METHODS}, got {method!r}")
    Am, _ = spd(A, "A")
    n = Am.shape[0]
    Bm, L = spd(B, "B", n)
    av, bv = vector(a, "a", n), vector(b, "b", n)
    M = tri_solve(L, tri_solve(L, Am).T)  # L^-1 A L^-T
    mu, V = np.linalg.eigh(0.5 * (M + M.T))  # L^-1 A L^-T = V diag(mu) V^T
    mu = np.maximum(mu, np.finfo(float).tiny)
    T = L @ V  # B = T T^T, A = T diag(mu) T^T
    ah = V.T @ tri_solve(L, av)  # T^-1 a
    bh = V.T @ tri_solve(L, bv)  # T^-1 b
    logdet_B = logdet_from_chol(L)
    if method == "inverse":
        w = _ici_weight(mu)
        e = w * mu + 1.0 - w  # G = w A + (1-w) B = T diag(e) T^T
        d = 1.0 / mu + 1.0 - 1.0 / e  # P^-1 = T^-T diag(d) T^-1
        k, l_ = 1.0 / mu - w / e, 1.0 - (1.0 - w) / e  # K, L of ICI in the basis
        x = T @ ((k * ah + l_ * bh) / d)  # x = P (K a + L b)
        P = (T / d) @ T.T
        return CIResult(
            x=x, P=0.5 * (P + P.T), omega=w, log_det=logdet_B - float(np.sum(np.log(d)))
        )
    if method == "optimal":
        w = _ci_weight(mu)
    elif method == "fast":
        trA, trB = float(np.trace(Am)), float(np.trace(Bm))
        w = trB / (trA + trB)  # Niehsen
    else:  # improved_fast, in logs: det(A^-1 + B^-1) = det B^-1 prod(1 + 1/mu)
        s1 = float(np.sum(np.log1p(1.0 / mu)))  # log [det(A^-1 + B^-1) / det B^-1]
        s2 = float(np.sum(np.log1p(mu)))  # log [det(A^-1 + B^-1) / det A^-1]
        w = 0.5 * (1.0 - np.exp(-s1) + np.exp(-s2))  # Fraenken & Hupper
    den = w + (1.0 - w) * mu  # P = T diag(mu / den) T^T
    gain = mu / den
    x = T @ ((w * ah + (1.0 - w) * mu * bh) / den)  # x = P (w A^-1 a + (1-w) B^-1 b)
    P = (T * gain) @ T.T
    return CIResult(
        x=x, P=0.5 * (P + P.T), omega=float(w), log_det=logdet_B + float(np.sum(np.log(gain)))
    )
