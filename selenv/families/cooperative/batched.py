"""Batched filter math of the cooperative-localization family (Chen & Kia 2022, Sec. IV).

The one implementation of a ``CLScheduling`` step: :class:`~selenv.families.cooperative.scenario.
CLSimulation` (the single env, its agents and the rollout) calls these functions with a batch of
one realisation (``B = 1``), :class:`~selenv.families.cooperative.vector.CLSchedulingVectorEnv`
with its ``B`` sub-envs. Shapes: ``B`` realisations, ``A`` agents, ``n`` states, ``n_input``
inputs, ``K`` relative measurements (rows), ``m`` = 1 (range) or 2 (range + bearing).

| function | equation |
|---|---|
| :func:`ins_propagate` | strapdown ``x+ = f(x, u)`` with ``F = df/dx``, ``G = df/du`` |
| :func:`predict` | EKF prediction ``x+ = f(x, u)``, ``P+ = F P F^T + G diag(s^2) G^T`` |
| :func:`kalman_update` | Joseph-form Kalman update ``P+ = (I-KH) P (I-KH)^T + K R K^T`` |
| :func:`zupt_updates`, :func:`beacon_updates` | the uncontrolled updates of every step |
| :func:`relative_terms` | ``(H_i, H_j, z - h(x_i, x_j))`` of relative range (+ bearing) |
| :func:`fuse` | agent i's update of eqs. (4)-(6) (``dmv``), the naive EKF, the others per row |
| :func:`pair_gains` | ``log det(I + N^-1 A)``, the observation's cheap gain of every pair |

Bit-for-bit contract: :func:`predict` performs per row the operations of
:func:`selenv.families.landmarks.models.propagate_with_jacobians` (``ins``) or
:meth:`~selenv.families.cooperative.models.AgentModel.jacobians` (``unicycle``) and
``F P F^T + Q``: the stacked ``@`` calls the same BLAS kernel per matrix as the 2-D one, and
for up to :data:`SMALL_TRIG` angles the sines and cosines are those of :mod:`math` (larger
batches take numpy's vectorised ones, equal wherever numpy uses the C library's, as on common
builds). The other functions equal the former per-row calls to rounding (rtol 1e-9).
"""

from __future__ import annotations

import math

import numpy as np

from selenv.core.linalg import FloatArray
from selenv.families.cooperative.models import AgentModel
from selenv.families.landmarks import models as lm

__all__ = [
    "SMALL_TRIG",
    "beacon_updates",
    "dmv_fuse",
    "fuse",
    "ins_propagate",
    "kalman_update",
    "logdets",
    "naive_fuse",
    "pair_gains",
    "predict",
    "relative_jacobians",
    "relative_terms",
    "zupt_updates",
]

#: up to this many angles the trigonometric functions are evaluated with :mod:`math`
SMALL_TRIG = 96
_G_E = np.array([0.0, 0.0, -lm.GRAVITY])
#: DMV weights below this are updated in the information form (per row, as dmv_update does)
_W_INFORMATION = 1e-3
#: the relative-measurement rules of :func:`fuse`
_METHODS = (
    "naive", "ci", "dmv", "pecmv", "ldmv", "lpecmv", "lpecmv_full", "lpecmv_objective",
)  # fmt: skip


def _cos_sin(a: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``(cos a, sin a)`` of any shape (:mod:`math` per element for small arrays)."""
    if a.size <= SMALL_TRIG:
        flat = a.ravel().tolist()
        c = np.array([math.cos(v) for v in flat]).reshape(a.shape)
        s = np.array([math.sin(v) for v in flat]).reshape(a.shape)
        return c, s
    return np.cos(a), np.sin(a)


def _mv(M: FloatArray, v: FloatArray) -> FloatArray:
    """Stacked matrix-vector product (..., r, c) x (..., c) -> (..., r) (one BLAS gemv each)."""
    return (M @ v[..., None])[..., 0]


def _T(M: FloatArray) -> FloatArray:
    """Transpose of the last two axes (a view)."""
    return np.swapaxes(M, -1, -2)


def _sym(M: FloatArray) -> FloatArray:
    """``(M + M^T) / 2`` of the last two axes."""
    return 0.5 * (M + _T(M))


# -- prediction ---------------------------------------------------------------------------------
def ins_propagate(
    x: FloatArray, u: FloatArray, h: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Strapdown step of every row: ``(x+ (N, 9), F (N, 9, 9), G (N, 9, 6))``.

    ``x`` (N, 9) = (p, v, theta), ``u`` (N, 6) = (f_b, w_b), ``h = dt``; with ``C = C_b^e``,
    ``E = E(theta)`` and ``A`` the rows ``(dC/dtheta_i) f_b``:
    ``p+ = p + v dt + a dt^2 / 2``, ``v+ = v + a dt``, ``a = C f_b + g_e``,
    ``theta+ = theta + E w_b dt``;
    ``F = [[I, dt I, dt^2/2 A^T], [0, I, dt A^T], [0, 0, I + dt [dE/droll w, dE/dpitch w, 0]]]``
    and ``G = [[dt^2/2 C, 0], [dt C, 0], [0, dt E]]`` (row by row the operations of
    :func:`selenv.families.landmarks.models.propagate_with_jacobians`).
    """
    N = x.shape[0]
    c, s = _cos_sin(x[:, 6:9])
    cr, cp, cy = c[:, 0], c[:, 1], c[:, 2]
    sr, sp, sy = s[:, 0], s[:, 1], s[:, 2]
    z, one = np.zeros(N), np.ones(N)
    tp, c2 = sp / cp, cp * cp
    sr_sp, cr_sp = sr * sp, cr * sp  # the left factor of sr * sp * sy (evaluated left to right)
    entries = (  # the entries of C, E, dC/droll, dC/dpitch, dC/dyaw, dE/droll, dE/dpitch
        *(cp * sy, sr_sp * sy + cr * cy, cr_sp * sy - sr * cy),  # C (rows E, N, -D)
        *(cp * cy, sr_sp * cy - cr * sy, cr_sp * cy + sr * sy),
        *(sp, -sr * cp, -cr * cp),
        *(one, sr * tp, cr * tp),  # E
        *(z, cr, -sr),
        *(z, sr / cp, cr / cp),
        *(z, cr_sp * sy - sr * cy, -sr_sp * sy - cr * cy),  # dC/droll
        *(z, cr_sp * cy + sr * sy, -sr_sp * cy + cr * sy),
        *(z, -cr * cp, sr * cp),
        *(-sp * sy, sr * cp * sy, cr * cp * sy),  # dC/dpitch
        *(-sp * cy, sr * cp * cy, cr * cp * cy),
        *(cp, sr_sp, cr_sp),
        *(cp * cy, sr_sp * cy - cr * sy, cr_sp * cy + sr * sy),  # dC/dyaw
        *(-cp * sy, -sr_sp * sy - cr * cy, -cr_sp * sy + sr * cy),
        *(z, z, z),
        *(z, cr * tp, -sr * tp),  # dE/droll
        *(z, -sr, -cr),
        *(z, cr / cp, -sr / cp),
        *(z, sr / c2, cr / c2),  # dE/dpitch
        *(z, z, z),
        *(z, sr_sp / c2, cr_sp / c2),
    )
    mats = np.stack(entries, -1).reshape(N, 7, 3, 3)
    C, E, dC, dEr, dEp = mats[:, 0], mats[:, 1], mats[:, 2:5], mats[:, 5], mats[:, 6]
    f, w = u[:, 0:3], u[:, 3:6]
    A = (dC @ f[:, None, :, None])[..., 0]  # (N, 3 angles, 3): row i = (dC/dtheta_i) f
    hh = 0.5 * h * h
    F = np.broadcast_to(lm._f_template(h), (N, 9, 9)).copy()
    F[:, 0:3, 6:9] = hh * _T(A)
    F[:, 3:6, 6:9] = h * _T(A)
    F[:, 6:9, 6] += h * _mv(dEr, w)
    F[:, 6:9, 7] += h * _mv(dEp, w)
    G = np.zeros((N, 9, 6))
    G[:, 0:3, 0:3] = hh * C
    G[:, 3:6, 0:3] = h * C
    G[:, 6:9, 3:6] = h * E
    p, v, th = x[:, 0:3], x[:, 3:6], x[:, 6:9]
    a = _mv(C, f) + _G_E  # a = C_b^e f_b + g_e
    out = np.empty((N, 9))
    out[:, 0:3] = p + v * h + 0.5 * a * h * h
    out[:, 3:6] = v + a * h
    out[:, 6:9] = th + _mv(E, w) * h
    return out, F, G


def _unicycle_propagate(
    x: FloatArray, u: FloatArray, h: float, scale: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Unicycle ``(x+ (N, 3), F (N, 3, 3), Q (N, 3, 3))``: ``p+ = p + v dt (cos, sin) psi``.

    ``F = [[1, 0, -v dt s], [0, 1, v dt c], [0, 0, 1]]``, ``Q = G diag(s^2) G^T`` with
    ``G = [[dt c, 0], [dt s, 0], [0, dt]]`` (:meth:`AgentModel.jacobians`).
    """
    N = x.shape[0]
    c, s = _cos_sin(x[:, 2])
    v, w = u[:, 0], u[:, 1]
    F = np.zeros((N, 3, 3))
    F[:, 0, 0] = F[:, 1, 1] = F[:, 2, 2] = 1.0
    F[:, 0, 2] = -v * h * s
    F[:, 1, 2] = v * h * c
    G = np.zeros((N, 3, 2))
    G[:, 0, 0], G[:, 1, 0], G[:, 2, 1] = h * c, h * s, h
    Gs = G * scale[:, None, :]
    Q = _sym(Gs @ _T(Gs))
    out = np.stack([x[:, 0] + v * h * c, x[:, 1] + v * h * s, x[:, 2] + w * h], -1)
    return out, F, Q


def predict(
    model: AgentModel,
    x: FloatArray,
    P: FloatArray,
    u: FloatArray,
    dt: float,
    sigma: FloatArray,
) -> None:
    """EKF prediction of every agent of every realisation, in place.

    ``x+ = f(x, u)``, ``P+ = sym(F P F^T + Q)``, ``Q = G diag(s^2) G^T`` (the input noise
    through ``G = df/du``; ``s`` = (accel, gyro) or (speed, turn rate) per agent).

    Args:
        model: the agents' :class:`AgentModel`.
        x: (B, A, n) estimates (updated).
        P: (B, A, n, n) covariances (updated).
        u: (B, A, n_input) measured inputs.
        dt: step (s).
        sigma: (A, 2) input noise per agent in SI units.
    """
    B, A, n = x.shape
    xs, Ps, us = x.reshape(B * A, n), P.reshape(B * A, n, n), u.reshape(B * A, -1)
    if model.name == "ins":
        scale = np.repeat(np.asarray(sigma, dtype=np.float64), 3, axis=1)  # (A, 6)
        x_new, F, G = ins_propagate(xs, us, dt)
        Gs = G * np.tile(scale, (B, 1))[:, None, :]  # G diag(sa, sa, sa, sg, sg, sg)
        Q = _sym(Gs @ _T(Gs))
    else:
        scale = np.tile(np.asarray(sigma, dtype=np.float64), (B, 1))
        x_new, F, Q = _unicycle_propagate(xs, us, dt, scale)
    x[...] = x_new.reshape(B, A, n)
    P[...] = _sym(F @ Ps @ _T(F) + Q).reshape(B, A, n, n)


# -- Kalman updates -----------------------------------------------------------------------------
def kalman_update(
    x: FloatArray, P: FloatArray, y: FloatArray, H: FloatArray, R: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Joseph-form Kalman update of every row (as :func:`selenv.core.kalman.kf_update`).

    ``S = sym(H P H^T + R)``, ``K = P H^T S^-1`` (a solve, ``m = 1``: a division),
    ``x+ = x + K y``, ``P+ = sym((I - K H) P (I - K H)^T + K R K^T)``.

    Args:
        x: (N, n) prior means.
        P: (N, n, n) prior covariances.
        y: (N, m) innovations ``z - h(x)``.
        H: (N, m, n) or (m, n) Jacobians.
        R: (N, m, m) or (m, m) noise covariances.

    Returns:
        ``(x+ (N, n), P+ (N, n, n))``.
    """
    n, m = x.shape[-1], y.shape[-1]
    HP = H @ P  # (N, m, n)
    S = _sym(HP @ _T(H) + R)
    KT = np.asarray(HP / S if m == 1 else np.linalg.solve(S, HP), np.float64)  # S K^T = H P
    K = _T(KT)
    x_new = x + _mv(K, y)
    I_KH = np.eye(n) - K @ H
    P_new = _sym(I_KH @ P @ _T(I_KH) + K @ R @ KT)
    return x_new, P_new


def zupt_updates(
    x: FloatArray, P: FloatArray, v_true: FloatArray, noise: FloatArray, sigma: float
) -> None:
    """Velocity pseudo-measurements ``z = v + N(0, sigma^2 I3)`` of every agent, in place.

    Args:
        x: (B, A, 9) estimates (updated).
        P: (B, A, 9, 9) covariances (updated).
        v_true: (B, A, 3) true velocities.
        noise: (B, A, 3) their noise draws.
        sigma: ZUPT noise (m/s).
    """
    B, A, n = x.shape
    H = np.zeros((3, n))
    H[:, 3:6] = np.eye(3)
    y = (v_true + noise - x[..., 3:6]).reshape(B * A, 3)
    xn, Pn = kalman_update(x.reshape(B * A, n), P.reshape(B * A, n, n), y, H, sigma**2 * np.eye(3))
    x[...], P[...] = xn.reshape(B, A, n), Pn.reshape(B, A, n, n)


def _ranges(d: FloatArray) -> FloatArray:
    """``|d|`` of every row of ``d`` (K, dim): one ``ddot`` each (the 1-D ``np.linalg.norm``)."""
    return np.sqrt((d[:, None, :] @ d[:, :, None])[:, 0, 0])


def beacon_updates(
    model: AgentModel,
    x: FloatArray,
    P: FloatArray,
    truth: FloatArray,
    agents: tuple[int, ...],
    beacons: FloatArray,
    noise: FloatArray,
    sigma: float,
) -> None:
    """EKF range updates of ``agents`` to every beacon (in beacon order), in place.

    ``z = |p - b| + N(0, sigma^2)``, ``H = (p_hat - b)^T / |p_hat - b|`` on the position.

    Args:
        model: the agents' model.
        x: (B, A, n) estimates (updated).
        P: (B, A, n, n) covariances (updated).
        truth: (B, A, n) true states.
        agents: the beacon agents (in order; an agent listed twice is updated twice).
        beacons: (nb, 3) positions.
        noise: (B, A, nb) range noise draws.
        sigma: range noise (m).
    """
    if not agents:
        return
    rounds: list[list[int]] = []  # each round: distinct agents, updated together
    for i in agents:
        for r in rounds:
            if i not in r:
                r.append(i)
                break
        else:
            rounds.append([i])
    B, _, n = x.shape
    dim = model.dim
    R = np.array([[sigma**2]])
    for ag in rounds:
        idx = np.asarray(ag, dtype=np.intp)
        xs, Ps = x[:, idx].reshape(-1, n), P[:, idx].reshape(-1, n, n)
        ts, ns = truth[:, idx].reshape(-1, n), noise[:, idx].reshape(-1, beacons.shape[0])
        for b, beacon in enumerate(beacons):
            z = _ranges(ts[:, :dim] - beacon[:dim]) + ns[:, b]
            d = xs[:, :dim] - beacon[:dim]
            r_hat = _ranges(d)
            H = np.zeros((xs.shape[0], 1, n))
            H[:, 0, :dim] = d / r_hat[:, None]
            xs, Ps = kalman_update(xs, Ps, (z - r_hat)[:, None], H, R)
        x[:, idx] = xs.reshape(B, len(ag), n)
        P[:, idx] = Ps.reshape(B, len(ag), n, n)


# -- relative measurements ----------------------------------------------------------------------
def relative_jacobians(
    model: AgentModel, x_i: FloatArray, x_j: FloatArray, bearing: bool
) -> tuple[FloatArray, FloatArray]:
    """``(H_i, H_j)`` (K, m, n) of relative range (+ bearing) at the estimates (K, n).

    Range ``|p_i - p_j|``: ``H_i = (p_i - p_j)^T / r`` on the position, ``H_j = -H_i``;
    bearing ``atan2(dy, dx)`` of ``d = p_j - p_i``: ``H_j = (-d_y, d_x) / |d|^2``, ``H_i = -H_j``.
    """
    return _relative(model, x_i, x_j, bearing)[1:]


def _relative(
    model: AgentModel, x_i: FloatArray, x_j: FloatArray, bearing: bool
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(h (K, m), H_i, H_j)``: relative range (+ bearing) and its Jacobians."""
    K, dim, n = x_i.shape[0], model.dim, model.n
    d = x_i[:, :dim] - x_j[:, :dim]
    r = _ranges(d)
    H_i = np.zeros((K, 1, n))
    H_i[:, 0, :dim] = d / r[:, None]
    H_j = -H_i
    if not bearing:
        return r[:, None], H_i, H_j
    e = x_j[:, :2] - x_i[:, :2]
    q = (e[:, None, :] @ e[:, :, None])[:, 0, 0]
    Hb_j = np.zeros((K, 1, n))
    Hb_j[:, 0, 0], Hb_j[:, 0, 1] = -e[:, 1] / q, e[:, 0] / q
    h = np.stack([r, np.arctan2(e[:, 1], e[:, 0])], -1)
    return h, np.concatenate([H_i, -Hb_j], 1), np.concatenate([H_j, Hb_j], 1)


def relative_terms(
    model: AgentModel,
    x_i: FloatArray,
    x_j: FloatArray,
    t_i: FloatArray,
    t_j: FloatArray,
    noise: FloatArray,
    bearing: bool,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(H_i, H_j (K, m, n), residual (K, m))`` of relative measurements now.

    ``z = h(t_i, t_j) + noise`` from the true states ``t`` (K, n), ``residual = z - h(x_i, x_j)``
    (the bearing wrapped to ``[-pi, pi)``), Jacobians at the estimates ``x`` (K, n).
    """
    z = _relative(model, t_i, t_j, bearing)[0] + noise
    h, H_i, H_j = _relative(model, x_i, x_j, bearing)
    res = z - h
    if bearing:
        res[:, 1] = lm.wrap_angle(res[:, 1])
    return H_i, H_j, res


def pair_gains(
    P_i: FloatArray,
    P_j: FloatArray,
    H_i: FloatArray,
    H_j: FloatArray,
    R: FloatArray,
    dim: int | None = None,
) -> FloatArray:
    """(K,) ``log det(I + N^-1 A)``, ``A = H_i P_i H_i^T``, ``N = H_j P_j H_j^T + R``.

    The naive-EKF information gain of each pair (the observation's cheap proxy); ``P`` (K, n, n),
    ``H`` (K, m, n), ``R`` (m, m). ``dim``: the Jacobians are zero beyond column ``dim`` (the
    relative measurements see the position only), so only the ``(dim, dim)`` position blocks
    of ``P`` are read (the same value; ``None``: all ``n`` columns). ``m = 1``:
    ``log(1 + A / N)``, the 1 x 1 determinant.
    """
    if P_i.shape[0] == 0:
        return np.zeros(0)
    if dim is not None:
        P_i, P_j = P_i[:, :dim, :dim], P_j[:, :dim, :dim]
        H_i, H_j = H_i[:, :, :dim], H_j[:, :, :dim]
    A = H_i @ P_i @ _T(H_i)
    N = H_j @ P_j @ _T(H_j) + R
    if A.shape[1] == 1:
        return np.log(1.0 + A[:, 0, 0] / N[:, 0, 0])
    return np.asarray(np.linalg.slogdet(np.eye(A.shape[1]) + np.linalg.solve(N, A))[1])


def logdets(P: FloatArray) -> FloatArray:
    """``log det P = 2 sum log diag chol(P)`` over the last two axes of SPD ``P`` (..., n, n).

    The fast path of :func:`selenv.core.linalg.logdet_spd` (``P`` exactly symmetric, as every
    covariance here is after its symmetrisation): the same LAPACK factor, the same values.
    """
    L = np.linalg.cholesky(P)
    return 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)


def naive_fuse(
    x_i: FloatArray,
    P_i: FloatArray,
    P_j: FloatArray,
    H_i: FloatArray,
    H_j: FloatArray,
    R: FloatArray,
    residual: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """EKF pretending the beliefs are independent: noise ``H_j P_j H_j^T + R`` (rows (K, ...))."""
    return kalman_update(x_i, P_i, residual, H_i, H_j @ P_j @ _T(H_j) + R)


def dmv_fuse(
    x_i: FloatArray,
    P_i: FloatArray,
    P_j: FloatArray,
    H_i: FloatArray,
    H_j: FloatArray,
    R: FloatArray,
    residual: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """DMV update of every row (eqs. 4-6): ``(x+ (K, n), P+ (K, n, n))``.

    ``w*`` of eq. (6) for all rows at once (``m = 1``: the stationarity cubic,
    :func:`selenv.core.fusion.batch.dmv_omega_batch`'s solver); then, with
    ``S(w) = A / w + B / (1 - w) + R``: ``Kbar = (P_i / w) H_i^T S^-1``,
    ``Pbar = P_i / w - Kbar S Kbar^T`` (eq. 5), ``x+ = x_i + Kbar residual``; no update where
    ``w* = 1``; rows with ``w* < 1e-3`` take :func:`selenv.core.fusion.dmv_update`'s
    information form (one call per such row).

    Args:
        x_i: (K, n) prior means of the agents i.
        P_i: (K, n, n) prior covariances of the agents i.
        P_j: (K, n, n) prior covariances of the agents j.
        H_i: (K, m, n) Jacobians w.r.t. agent i.
        H_j: (K, m, n) Jacobians w.r.t. agent j.
        R: (m, m) measurement noise.
        residual: (K, m) ``z - h(x_i, x_j)`` (angles wrapped).

    Raises:
        ValueError: ``H_j P_j H_j^T`` not positive definite (as ``dmv_update``).
    """
    from selenv.core import fusion
    from selenv.core.fusion.batch import _dmv_omega_batch, _omega_scalar_batch
    from selenv.core.fusion.dmv import _B_NOT_PD

    K, n, m = x_i.shape[0], x_i.shape[1], H_i.shape[1]
    x_new, P_new = x_i.copy(), P_i.copy()
    if K == 0:
        return x_new, P_new
    if m == 1:
        r = float(R[0, 0])
        h_i, h_j = H_i[:, 0], H_j[:, 0]
        Ph = _mv(P_i, h_i)  # P_i h_i^T, (K, n)
        a = (h_i[:, None, :] @ Ph[:, :, None])[:, 0, 0] / r
        b = (h_j[:, None, :] @ _mv(P_j, h_j)[:, :, None])[:, 0, 0] / r
        if not np.all(b > 0.0):
            raise ValueError(_B_NOT_PD)
        w = np.ones(K)
        upd = a > n * b  # tr(B^-1 A) > n: an update happens
        if upd.any():
            w[upd] = _omega_scalar_batch(a[upd], b[upd], n)
        kal = (w < 1.0) & (w >= _W_INFORMATION)
        if kal.any():
            wk, ak, bk = w[kal], a[kal], b[kal]
            s = ak / wk + bk / (1.0 - wk) + 1.0  # S(w) / r
            Kb = Ph[kal] / (wk * s * r)[:, None]  # Kbar = (P_i/w) h_i^T S^-1
            Pk = P_i[kal] / wk[:, None, None]
            Pk -= (s * r)[:, None, None] * Kb[:, :, None] * Kb[:, None, :]
            P_new[kal] = Pk
            x_new[kal] = x_i[kal] + Kb * residual[kal]
    else:
        w = _dmv_omega_batch(P_i, P_i, P_j, P_j, H_i, H_j, np.broadcast_to(R, (K, m, m)).copy())
        kal = (w < 1.0) & (w >= _W_INFORMATION)
        if kal.any():
            wk = w[kal][:, None, None]
            Pk, Hk = P_i[kal], H_i[kal]
            A = Hk @ Pk @ _T(Hk)
            Bm = H_j[kal] @ P_j[kal] @ _T(H_j[kal])
            S = _sym(A / wk + Bm / (1.0 - wk) + R)  # S(w)
            L = np.asarray(np.linalg.cholesky(S), np.float64)
            M = np.asarray(np.linalg.solve(L, (Hk @ Pk) / wk), np.float64)  # L_S^-1 H_i P_i / w
            Kb = _T(np.asarray(np.linalg.solve(_T(L), M), np.float64))  # Kbar = (P_i/w) H_i^T S^-1
            P_new[kal] = _sym(Pk / wk - _T(M) @ M)
            x_new[kal] = x_i[kal] + _mv(Kb, residual[kal])
    for k in np.flatnonzero(w < _W_INFORMATION):  # near 0: the information form, per row
        res = fusion.dmv_update(
            P_i[k], P_j[k], H_i[k], H_j[k], R, x_i=x_i[k], residual=residual[k], omega=w[k]
        )
        x_new[k], P_new[k] = np.asarray(res.x), res.P
    return x_new, P_new


def _fuse_one(
    method: str,
    x_i: FloatArray,
    P_i: FloatArray,
    P_j: FloatArray,
    H_i: FloatArray,
    H_j: FloatArray,
    R: FloatArray,
    residual: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """One row of ``ci``, ``pecmv`` and the learned rules (scipy / cvxpy / torch per call)."""
    from selenv.core import fusion

    if method == "ci":  # bound (4) with the weight that minimises the trace (CI's criterion)
        from scipy.optimize import minimize_scalar  # deferred: a slow import

        args = (P_i, P_j, H_i, H_j, R)
        trace = lambda w: float(np.trace(fusion.dmv_update(*args, omega=w, validate=False).P))  # noqa: E731
        best = minimize_scalar(trace, bounds=(1e-4, 1.0 - 1e-9), method="bounded")
        if best.fun >= float(np.trace(P_i)):  # omega = 1: no update
            return x_i.copy(), P_i.copy()
        ci = fusion.dmv_update(*args, x_i=x_i, residual=residual, omega=float(best.x))
        return np.asarray(ci.x), np.asarray(ci.P)
    if method == "pecmv":
        pecmv = fusion.pecmv_update(P_i, P_j, H_i, H_j, R, x_i=x_i, residual=residual)
        return np.asarray(pecmv.x), np.asarray(pecmv.P)
    if method == "ldmv":
        ld = fusion.ldmv_update(P_i, P_j, H_i, H_j, R, x_i=x_i, residual=residual)
        return np.asarray(ld.x), np.asarray(ld.P)
    if method in ("lpecmv", "lpecmv_full", "lpecmv_objective"):
        lp = fusion.lpecmv_update(P_i, P_j, H_i, H_j, R, x_i=x_i, residual=residual, variant=method)
        return np.asarray(lp.x), np.asarray(lp.P)
    raise ValueError(f"method must be one of {_METHODS}, got {method!r}")


def fuse(
    method: str,
    x_i: FloatArray,
    P_i: FloatArray,
    P_j: FloatArray,
    H_i: FloatArray,
    H_j: FloatArray,
    R: FloatArray,
    residual: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Agent ``i``'s posterior of every row from a relative measurement of unknown correlation.

    ``naive`` and ``dmv`` are batched (:func:`naive_fuse`, :func:`dmv_fuse`); ``ci``,
    ``pecmv`` and the learned rules run one row at a time (a scalar search, an SDP, a network).

    Args:
        method: ``naive``, ``ci``, ``dmv``, ``pecmv``, ``ldmv``, ``lpecmv``, ``lpecmv_full``
            or ``lpecmv_objective``.
        x_i: (K, n) prior means of the agents i.
        P_i: (K, n, n) prior covariances of the agents i.
        P_j: (K, n, n) prior covariances of the agents j.
        H_i: (K, m, n) Jacobians w.r.t. agent i.
        H_j: (K, m, n) Jacobians w.r.t. agent j.
        R: (m, m) measurement noise.
        residual: (K, m) ``z - h(x_i, x_j)`` (angles wrapped).

    Returns:
        ``(x+ (K, n), P+ (K, n, n))``.

    Raises:
        ValueError: an unknown ``method`` (named), or a fusion's own error.
    """
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    if method == "naive":
        return naive_fuse(x_i, P_i, P_j, H_i, H_j, R, residual)
    if method == "dmv":
        return dmv_fuse(x_i, P_i, P_j, H_i, H_j, R, residual)
    if x_i.shape[0] == 0:
        return x_i.copy(), P_i.copy()
    out = [
        _fuse_one(method, x_i[k], P_i[k], P_j[k], H_i[k], H_j[k], R, residual[k])
        for k in range(x_i.shape[0])
    ]
    return np.stack([o[0] for o in out]), np.stack([o[1] for o in out])
