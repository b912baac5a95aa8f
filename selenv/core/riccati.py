"""Covariance-only Kalman recursions (the Riccati difference equation), batched.

For a linear Gaussian model the filter covariance does not depend on the measurements, so the
posterior MSE of a filter can be computed ahead of time by iterating prediction and update on
``P`` alone (Greiff et al. 2022, eqs. (11b) and (12c); Algorithm 1 runs exactly this over a
window of ``tau`` steps for every candidate cluster).

Symbols follow :mod:`selenv.core.kalman`: ``P`` (B, n, n) covariances stacked over a leading batch
axis, ``F`` (n, n) transition and ``Q`` (n, n) process noise shared by the batch, ``H`` (p, n)
measurement matrix shared by the batch, ``R`` (p, p) shared or (B, p, p) per batch element;
:func:`riccati_pass` also takes a time-varying ``R_k`` (B, steps, p, p), one per step (eq. 1b of
Greiff et al.: the noise of a receiver changes with its reception conditions).

The update uses the symmetric form ``P' = P - (H P)^T S^-1 (H P)`` with ``S = H P H^T + R``
(optimal gain; the Joseph form of :func:`selenv.core.kalman.kf_update` exists for suboptimal
gains and agrees with it to rounding, which the tests check). ``S^-1 (H P)`` is a batched solve,
never an inverse. Inputs of :func:`riccati_step` are assumed validated by the caller (the
scenario builds them; it is the per-step hot path and checks nothing); the public
:func:`riccati_pass` validates types (real only), shapes (naming the argument that disagrees
with the others), finiteness and the valid range ``|entry| <= MAX_ABS`` of
:func:`~selenv.core.linalg.check_magnitude` once per call, and refuses a history that
overflows float64.
"""

from __future__ import annotations

import numpy as np

from selenv.core.linalg import (
    MAX_ABS,
    FloatArray,
    ShapeError,
    as_float_array,
    blame_shapes,
    check_finite,
    check_magnitude,
    check_shape,
)

__all__ = ["riccati_pass", "riccati_step"]


def riccati_step(
    P: FloatArray, F: FloatArray, Q: FloatArray, H: FloatArray, R: FloatArray
) -> FloatArray:
    """One prediction and update of the covariance, batched (no validation: hot path).

    ``P^- = F P F^T + Q`` (eq. 11b), ``S = H P^- H^T + R``,
    ``P^+ = P^- - (H P^-)^T S^-1 (H P^-)`` (eqs. 12a, 12c).

    Args:
        P: posterior covariances at ``k-1``, (B, n, n).
        F: transition (n, n).
        Q: process noise (n, n).
        H: measurement matrix (p, n).
        R: measurement noise (p, p) or (B, p, p).

    Returns:
        Posterior covariances at ``k``, (B, n, n), symmetrized.
    """
    Pm = F @ P @ F.T + Q  # (11b)
    HP = H @ Pm  # (B, p, n)
    S = HP @ H.T + R  # innovation covariance (B, p, p)
    Pp = Pm - np.swapaxes(HP, -1, -2) @ np.linalg.solve(S, HP)  # (12a) + (12c)
    return 0.5 * (Pp + np.swapaxes(Pp, -1, -2))


def singular_step_error(t: int) -> ValueError:
    """The ``ValueError`` of a pass whose ``S = H P H^T + R`` is singular at step ``t``."""
    return ValueError(
        f"riccati_pass: S = H P H^T + R is singular at step {t}; R must be positive "
        "definite (or H P H^T must be)"
    )


def history_overflow_error(steps: int) -> ValueError:
    """The ``ValueError`` of a pass whose covariance history overflows float64."""
    return ValueError(
        "riccati_pass: the covariance history is not representable in float64 (overflow); "
        f"keep |entry| <= {MAX_ABS:g} and the model stable enough over {steps} steps "
        "(rescale the problem)"
    )


def riccati_pass(
    P0: FloatArray,
    F: FloatArray,
    Q: FloatArray,
    H: FloatArray,
    R: FloatArray,
    steps: int,
) -> FloatArray:
    """Iterate :func:`riccati_step` ``steps`` times from ``P0``; return the whole history.

    Args:
        P0: prior (posterior at the window start), (B, n, n).
        F: transition (n, n).
        Q: process noise (n, n).
        H: measurement matrix (p, n).
        R: measurement noise: (p, p) or (B, p, p) for every step, or (B, steps, p, p) with
            ``R[:, t - 1]`` the noise of the measurement at step ``t = 1 .. steps``.
        steps: number of prediction-update steps, >= 0.

    Returns:
        ``(B, steps + 1, n, n)``: ``P0`` then the posterior after each step (a time-invariant
        ``R`` gives the same numbers as the same ``R`` repeated per step).

    Raises:
        TypeError: an array argument is not real numeric (complex, bool, str, object), or
            ``steps`` is not an int.
        ValueError: wrong shapes (naming the argument that disagrees with the others), NaN/inf,
            entries outside the valid range, a negative ``steps``, a singular innovation
            covariance ``S``, or a history that overflows float64.
    """
    if isinstance(steps, bool) or not isinstance(steps, int | np.integer):
        raise TypeError(f"steps must be an int >= 0, got {steps!r}")
    if steps < 0:
        raise ValueError(f"steps must be an int >= 0, got {steps!r}")
    steps = int(steps)
    raw = {"P0": P0, "F": F, "Q": Q, "H": H, "R": R}
    arrs = {name: as_float_array(value, name) for name, value in raw.items()}
    try:
        P0, F, Q, H, R = _shapes(arrs, steps)
    except ShapeError as exc:
        templates: dict[str, str | list[str]] = {"P0": "B n n", "F": "n n", "Q": "n n"}
        templates["H"] = "p n"
        templates["R"] = ["p p", "B p p", "B steps p p"]
        err = blame_shapes(raw, templates, fixed={"steps": steps}, error=exc)
        raise (err or exc) from None
    for name, arr in zip(raw, (P0, F, Q, H, R), strict=True):
        check_magnitude(check_finite(arr, name), name)
    B, n, p = P0.shape[0], P0.shape[1], H.shape[0]
    per_step = R.shape == (B, steps, p, p)
    out = np.empty((B, steps + 1, n, n))
    out[:, 0] = P0
    P = P0
    for t in range(1, steps + 1):
        try:
            P = riccati_step(P, F, Q, H, R[:, t - 1] if per_step else R)  # R_t of (12a)
        except np.linalg.LinAlgError:
            raise singular_step_error(t) from None
        out[:, t] = P
    if not np.all(np.isfinite(out)):
        raise history_overflow_error(steps)
    return out


def _shapes(arrs: dict[str, FloatArray], steps: int) -> tuple[FloatArray, ...]:
    """Shape checks of :func:`riccati_pass` (raise :class:`ShapeError` naming the argument)."""
    P0, F, Q, H, R = arrs.values()
    if P0.ndim != 3 or P0.shape[1] != P0.shape[2]:
        raise ShapeError(f"P0 must have shape (B, n, n), got {P0.shape}", "P0")
    B, n = P0.shape[0], P0.shape[1]
    check_shape(F, (n, n), "F")
    check_shape(Q, (n, n), "Q")
    if H.ndim != 2 or H.shape[1] != n:
        raise ShapeError(f"H must have shape (p, {n}), got {H.shape}", "H")
    p = H.shape[0]
    if R.shape not in ((p, p), (B, p, p), (B, steps, p, p)):
        raise ShapeError(
            f"R must have shape ({p}, {p}), ({B}, {p}, {p}) or, per step, "
            f"({B}, {steps}, {p}, {p}); got {R.shape}",
            "R",
        )
    return P0, F, Q, H, R
