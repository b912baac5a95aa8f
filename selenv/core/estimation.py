"""Batch MAP estimation by damped Gauss-Newton (Levenberg-Marquardt) with a Gaussian prior.

Used to estimate theta from a selected set of measurements (Kirchner et al. 2020, Sec. 6: any
estimator can run on the selected measurements; we use MAP instead of their unscented
transform). Minimises::

    J(theta) = (y - h(theta))^T R^-1 (y - h(theta)) + (theta - mu0)^T P0^-1 (theta - mu0)

Each iteration solves the normal equations ``(H^T R^-1 H + P0^-1 + lam D) dx = g`` by Cholesky,
with residuals and Jacobians whitened once by the Cholesky factors of ``R`` (block diagonal,
given per measurement) and ``P0``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from selenv.core.linalg import FloatArray, cholesky_spd, symmetrize

__all__ = ["MAPResult", "gauss_newton_map"]


@dataclass(frozen=True)
class MAPResult:
    """Result of :func:`gauss_newton_map`.

    Attributes:
        theta: ``(d,)`` MAP estimate.
        cov: ``(d, d)`` Laplace covariance ``(H^T R^-1 H + P0^-1)^-1`` at the estimate.
        cost: final value of ``J``.
        iterations: Gauss-Newton iterations taken.
        converged: whether the step norm fell below the tolerance.
    """

    theta: FloatArray
    cov: FloatArray
    cost: float
    iterations: int
    converged: bool


def gauss_newton_map(
    h: Callable[[FloatArray], FloatArray],
    jac: Callable[[FloatArray], FloatArray],
    y: FloatArray,
    R: FloatArray,
    mu0: FloatArray,
    P0: FloatArray,
    *,
    max_iter: int = 50,
    tol: float = 1e-9,
) -> MAPResult:
    """MAP estimate of ``theta`` for ``y_k = h_k(theta) + v_k``, ``v_k ~ N(0, R_k)``.

    Args:
        h: ``theta (d,) -> (N, m)`` predicted measurements.
        jac: ``theta (d,) -> (N, m, d)`` their Jacobians.
        y: ``(N, m)`` measurements.
        R: ``(N, m, m)`` noise covariances (SPD; zero-padded rows need identity).
        mu0: ``(d,)`` prior mean.
        P0: ``(d, d)`` prior covariance (SPD).
        max_iter: iteration cap.
        tol: convergence threshold on ``|dx| / (1 + |theta|)``.
    """
    LR = np.linalg.cholesky(R)  # R_k = L_k L_k^T
    LP = cholesky_spd(P0, "P0")
    d = mu0.shape[0]

    def whitened(theta: FloatArray) -> tuple[FloatArray, float]:
        r = np.linalg.solve(LR, (y - h(theta))[..., None])[..., 0].ravel()  # L^-1 (y - h)
        rp = solve_triangular(LP, theta - mu0, lower=True)  # LP^-1 (theta - mu0)
        return r, float(r @ r + rp @ rp)

    theta = mu0.astype(np.float64).copy()
    r, cost = whitened(theta)
    lam, converged, it = 1e-6, False, 0
    Pinv = cho_solve((LP, True), np.eye(d))  # P0^-1 (prior information, d x d)
    for it in range(1, max_iter + 1):  # noqa: B007
        W = np.linalg.solve(LR, jac(theta)).reshape(-1, d)  # whitened Jacobian
        Hn = W.T @ W + Pinv  # H^T R^-1 H + P0^-1
        g = W.T @ r - cho_solve((LP, True), theta - mu0)  # minus half the gradient
        while True:
            Ld = np.linalg.cholesky(Hn + lam * np.diag(np.diag(Hn)))
            dx = cho_solve((Ld, True), g)
            r_new, c_new = whitened(theta + dx)
            if c_new <= cost or lam > 1e12:
                break
            lam *= 10.0
        if c_new > cost:  # no descent possible: at a (local) minimum
            converged = True
            break
        theta, r, cost = theta + dx, r_new, c_new
        lam = max(lam / 10.0, 1e-12)
        if np.linalg.norm(dx) <= tol * (1.0 + np.linalg.norm(theta)):
            converged = True
            break
    W = np.linalg.solve(LR, jac(theta)).reshape(-1, d)
    cov = symmetrize(cho_solve((np.linalg.cholesky(W.T @ W + Pinv), True), np.eye(d)))
    return MAPResult(theta, cov, cost, it, converged)
