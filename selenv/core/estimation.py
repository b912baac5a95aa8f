"""Batch MAP estimation by damped Gauss-Newton (Levenberg-Marquardt) with a Gaussian prior.

Used to estimate theta from a selected set of measurements (Kirchner et al. 2020, Sec. 6: any
estimator can run on the selected measurements; we use MAP instead of their unscented
transform). Minimises::

    J(theta) = (y - h(theta))^T R^-1 (y - h(theta)) + (theta - mu0)^T P0^-1 (theta - mu0)

Each iteration solves the normal equations ``(H^T R^-1 H + P0^-1 + lam D) dx = g`` by Cholesky,
with residuals and Jacobians whitened once by the Cholesky factors of ``R`` (block diagonal,
given per measurement) and ``P0``.

Validation: real types only (complex, bool, str, object raise ``TypeError``), shapes (a
mismatch names the argument that disagrees with the others, including the outputs of ``h`` and
``jac``), finiteness, SPD ``R_k`` and ``P0``, and the valid range of
:func:`~selenv.core.linalg.check_magnitude`; a computation that overflows float64 raises
``ValueError``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import cho_solve, solve_triangular

from selenv.core.linalg import (
    MAX_ABS,
    FloatArray,
    ShapeError,
    as_float_array,
    blame_shapes,
    check_finite,
    check_magnitude,
    check_shape,
    cholesky_spd,
    symmetrize,
    validate_spd,
)

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
        max_iter: iteration cap, an int >= 1.
        tol: convergence threshold on ``|dx| / (1 + |theta|)``, a finite number >= 0.

    Raises:
        TypeError: ``h`` / ``jac`` not callable, an array (or an output of ``h`` / ``jac``)
            not real numeric, ``max_iter`` not an int or ``tol`` not a number.
        ValueError: shapes that disagree (naming the argument), NaN/inf (also in the outputs
            of ``h`` / ``jac``), ``R_k`` or ``P0`` not SPD, entries outside the valid range,
            ``max_iter < 1``, ``tol < 0``, or a computation that overflows float64.
    """
    for f, name in ((h, "h"), (jac, "jac")):
        if not callable(f):
            raise TypeError(f"{name} must be callable, got {type(f).__name__}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, int | np.integer):
        raise TypeError(f"max_iter must be an int, got {type(max_iter).__name__}")
    if max_iter < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    if isinstance(tol, bool) or not isinstance(tol, int | float | np.integer | np.floating):
        raise TypeError(f"tol must be a real number, got {type(tol).__name__}")
    if not 0.0 <= tol < math.inf:
        raise ValueError(f"tol must be a finite number >= 0, got {tol!r}")
    y, R, mu0, P0 = _inputs(y, R, mu0, P0)
    N, m, d = R.shape[0], R.shape[1], mu0.shape[0]

    def h_checked(theta: FloatArray) -> FloatArray:
        return _output(h(theta.copy()), "h(theta)", (N, m), y=y, R=R, mu0=mu0, P0=P0)

    def jac_checked(theta: FloatArray) -> FloatArray:
        return _output(jac(theta.copy()), "jac(theta)", (N, m, d), y=y, R=R, mu0=mu0, P0=P0)

    try:
        return _gauss_newton(h_checked, jac_checked, y, R, mu0, P0, int(max_iter), float(tol))
    except (OverflowError, ZeroDivisionError):
        raise _overflow() from None
    except np.linalg.LinAlgError:
        raise ValueError(
            "gauss_newton_map: the normal equations H^T R^-1 H + P0^-1 are not numerically "
            "positive definite (condition number beyond 1 / eps ~ 1e16, e.g. a Jacobian 1e8 "
            "times larger than the prior scale along an unobserved direction); rescale or "
            "regularise the problem"
        ) from None


_SHAPES = {
    "y": "N m",
    "R": "N m m",
    "mu0": "d",
    "P0": "d d",
    "h(theta)": "N m",
    "jac(theta)": "N m d",
}


def _overflow() -> ValueError:
    return ValueError(
        "gauss_newton_map: the iteration is not representable in float64 (overflow); keep "
        f"|entry| <= {MAX_ABS:g} (also in h and jac) and the problem well conditioned "
        "(rescale the problem)"
    )


def _inputs(
    y: ArrayLike, R: ArrayLike, mu0: ArrayLike, P0: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Validated ``y`` (N, m), ``R`` (N, m, m) SPD, ``mu0`` (d,), ``P0`` (d, d) SPD."""
    raw = {"y": y, "R": R, "mu0": mu0, "P0": P0}
    arrs = {name: as_float_array(value, name) for name, value in raw.items()}
    ya, Ra, mua, P0a = arrs.values()
    try:
        check_shape(ya, (None, None), "y")
        N, m = ya.shape
        check_shape(Ra, (N, m, m), "R")
        check_shape(mua, (None,), "mu0")
        check_shape(P0a, (mua.shape[0], mua.shape[0]), "P0")
    except ShapeError as exc:
        raise (blame_shapes(raw, _SHAPES, error=exc) or exc) from None
    ya = check_magnitude(check_finite(ya, "y"), "y")
    mua = check_magnitude(check_finite(mua, "mu0"), "mu0")
    Ra = check_magnitude(validate_spd(Ra, "R", m, batch=True), "R", definite=True)
    P0a = check_magnitude(validate_spd(P0a, "P0"), "P0", definite=True)
    return ya, Ra, mua, P0a


def _output(value: object, name: str, shape: tuple[int, ...], **given: FloatArray) -> FloatArray:
    """An output of ``h`` / ``jac``: real, of ``shape``, finite and in range (names it)."""
    arr = as_float_array(value, name)
    try:
        check_shape(arr, shape, name)
    except ShapeError as exc:
        raise (blame_shapes({**given, name: value}, _SHAPES, error=exc) or exc) from None
    return check_magnitude(check_finite(arr, name), name)


def _gauss_newton(
    h: Callable[[FloatArray], FloatArray],
    jac: Callable[[FloatArray], FloatArray],
    y: FloatArray,
    R: FloatArray,
    mu0: FloatArray,
    P0: FloatArray,
    max_iter: int,
    tol: float,
) -> MAPResult:
    """:func:`gauss_newton_map` on validated inputs (``h`` / ``jac`` check their outputs)."""
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
    if not (np.all(np.isfinite(theta)) and np.all(np.isfinite(cov)) and math.isfinite(cost)):
        raise _overflow()
    return MAPResult(theta, cov, cost, it, converged)
