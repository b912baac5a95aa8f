"""Strapdown IMU and angle-of-arrival models of Soubaras & Chahbazian (2023), Section IV.

**Frames.** ``[e]`` is East-North-Up (ENU), fixed to the ground and treated as inertial. The
body frame ``[b]`` points forward, right, down (FRD). Euler angles ``theta = (roll, pitch,
yaw)`` are the aerospace z-y-x angles of ``[b]`` with respect to North-East-Down (yaw is the
heading, clockwise from North; positive roll lowers the right wing; positive pitch raises the
nose)::

    C_b^e(theta) = C_ned^enu R_z(yaw) R_y(pitch) R_x(roll),   C_e^b = (C_b^e)^T,
    C_ned^enu = [[0, 1, 0], [1, 0, 0], [0, 0, -1]],

with the right-handed elementary rotations ``R_x(a) = [[1, 0, 0], [0, c, -s], [0, s, c]]``,
``R_y(a) = [[c, 0, s], [0, 1, 0], [-s, 0, c]]``, ``R_z(a) = [[c, -s, 0], [s, c, 0], [0, 0, 1]]``.

**State** ``x = (p, v, theta)`` (9,): ENU position (m), ENU velocity (m/s), Euler angles (rad).
**IMU input** ``u = (f_b, w_b)`` (6,): specific force (m/s^2) and angular rate (rad/s), in
``[b]``. Propagation over one step ``dt`` (the filter runs at 10 Hz)::

    a      = C_b^e(theta) f_b + g_e,        g_e = (0, 0, -GRAVITY)
    p+     = p + v dt + a dt^2 / 2
    v+     = v + a dt
    theta+ = theta + E(theta) w_b dt,       E = [[1, sr tp, cr tp], [0, cr, -sr], [0, sr/cp, cr/cp]]

(``sr = sin roll``, ``cp = cos pitch``, ``tp = tan pitch``: the z-y-x Euler kinematics).
IMU noise ``n ~ N(0, diag(sa^2 I3, sg^2 I3))`` on the measured ``u`` maps to the process noise
``Q = G diag(sa^2 I3, sg^2 I3) G^T`` with ``G = dx+/du`` (exact at first order). ``Q`` has rank
6 of 9 (the accelerometer drives position and velocity through one source), so it is positive
SEMI-definite; the EKF prediction and the covariance-form CRLB accept that.

**Angles of arrival** of landmark ``n`` at ``p_n`` (eqs. 16-17)::

    Delta = C_e^b (p_n - p),  rho = |(Delta_x, Delta_y)|,
    y^n = (azimuth, elevation) = (atan2(Delta_y, Delta_x), atan2(-Delta_z, rho)).

*Sign fix of eq. (16):* the paper prints ``atan2(Delta_z, rho)``, but the second row of its
``Psi`` (eq. 21) is the derivative of ``atan2(-Delta_z, rho)`` (the body z axis points down,
so a landmark above the horizon has ``Delta_z < 0``). We use ``-Delta_z`` so that the model
and eq. (21) agree; elevation is then positive upwards. ``Psi = d y / d Delta`` (2, 3).

**Error state of eq. (20).** ``H^n = Psi^n [[Delta^n]_x, 0_3, -I_3]`` is the Jacobian with
respect to ``e = (phi, dv, dp^b)`` (attitude, velocity, position: the paper's order) where the
true state is the estimate perturbed as::

    C_b^e = C_b^e_hat expm([phi]_x)   (i.e. C_e^b = (I - [phi]_x) C_e^b_hat to first order),
    p = p_hat + C_b^e_hat dp^b,       v = v_hat + dv,

a small rotation ``phi`` in the body frame and a position error resolved in ``[b]``. Then
``Delta = Delta_hat + [Delta]_x phi - dp^b + O(|e|^2)``. It relates to the exact Jacobian with
respect to ``x`` by ``H_paper = H_exact T`` with ``T = dx/de`` from :func:`paper_error_to_state`.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from selenv.core.linalg import FloatArray, as_float_array, check_finite

__all__ = [
    "C_NED_TO_ENU",
    "GRAVITY",
    "STATE_DIM",
    "aoa_angles",
    "aoa_angles_jacobian",
    "body_rates_from_euler_rates",
    "body_vectors",
    "dcm_batch",
    "euler_rate_matrix",
    "euler_to_dcm",
    "euler_to_dcm_derivatives",
    "measure",
    "measurement_jacobian",
    "paper_error_to_state",
    "paper_jacobian",
    "process_noise",
    "propagate",
    "propagate_steps",
    "propagate_with_jacobians",
    "propagation_jacobians",
    "skew",
    "state_difference",
    "strapdown_batch",
    "wrap_angle",
]

#: standard gravity (m/s^2); ``g_e = (0, 0, -GRAVITY)`` in ENU
GRAVITY = 9.80665
#: state dimension: position, velocity, Euler angles
STATE_DIM = 9
#: ``C_ned^enu``: swaps North and East and flips Down (its own inverse)
C_NED_TO_ENU: FloatArray = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
C_NED_TO_ENU.setflags(write=False)
_G_E = np.array([0.0, 0.0, -GRAVITY])


# -- small helpers ------------------------------------------------------------------------------
def wrap_angle(a: ArrayLike) -> FloatArray:
    """Wrap angles (any shape) to ``[-pi, pi)``: ``(a + pi) mod 2 pi - pi``."""
    return np.mod(np.asarray(a, dtype=np.float64) + np.pi, 2.0 * np.pi) - np.pi


def state_difference(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """``a - b`` for states (..., 9) with the Euler-angle part wrapped to ``[-pi, pi)``."""
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    d[..., 6:9] = wrap_angle(d[..., 6:9])
    return d


def skew(v: ArrayLike) -> FloatArray:
    """Cross-product matrix ``[v]_x`` with ``[v]_x w = v x w``; ``v`` (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def _state(x: ArrayLike) -> FloatArray:
    xa = check_finite(as_float_array(x, "x"), "x")
    if xa.shape != (STATE_DIM,):
        raise ValueError(f"x must have shape ({STATE_DIM},) = (p, v, theta), got {xa.shape}")
    return xa


def _input(u: ArrayLike) -> FloatArray:
    ua = check_finite(as_float_array(u, "u"), "u")
    if ua.shape != (6,):
        raise ValueError(f"u must have shape (6,) = (f_b, w_b), got {ua.shape}")
    return ua


def _landmarks(landmarks: ArrayLike) -> FloatArray:
    lm = check_finite(as_float_array(landmarks, "landmarks"), "landmarks")
    if lm.ndim != 2 or lm.shape[1] != 3:
        raise ValueError(f"landmarks must have shape (N, 3), got {lm.shape}")
    return lm


def _dt(dt: float) -> float:
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
    return float(dt)


#: ``(sin roll, cos roll, sin pitch, cos pitch, sin yaw, cos yaw)`` of one angle triple
_Trig = tuple[float, float, float, float, float, float]


# -- attitude -----------------------------------------------------------------------------------
def _trig(theta: Any) -> tuple[float, float, float, float, float, float]:
    """``(sr, cr, sp, cp, sy, cy)`` of one angle triple, with scalar ``math`` (no array ops)."""
    r, p, y = float(theta[0]), float(theta[1]), float(theta[2])
    return math.sin(r), math.cos(r), math.sin(p), math.cos(p), math.sin(y), math.cos(y)


def euler_to_dcm(theta: ArrayLike) -> FloatArray:
    """``C_b^e = C_ned^enu R_z(yaw) R_y(pitch) R_x(roll)``; ``theta`` (..., 3) -> (..., 3, 3).

    Rows of ``C_b^ned``: ``N = (cp cy, sr sp cy - cr sy, cr sp cy + sr sy)``,
    ``E = (cp sy, sr sp sy + cr cy, cr sp sy - sr cy)``, ``D = (-sp, sr cp, cr cp)``;
    ``C_b^e`` stacks ``(E, N, -D)``.
    """
    th = np.asarray(theta, dtype=np.float64)
    if th.ndim == 1:
        return _dcm(_trig(th))
    c, s = np.cos(th), np.sin(th)
    ca, cb, cc = c[..., 0], c[..., 1], c[..., 2]  # cos roll, pitch, yaw
    sa, sb, sc = s[..., 0], s[..., 1], s[..., 2]
    north = np.stack([cb * cc, sa * sb * cc - ca * sc, ca * sb * cc + sa * sc], -1)
    east = np.stack([cb * sc, sa * sb * sc + ca * cc, ca * sb * sc - sa * cc], -1)
    up = np.stack([sb, -sa * cb, -ca * cb], -1)
    return np.stack([east, north, up], -2)  # C_ned^enu C_b^ned: rows E, N, -D


def _dcm(t: _Trig) -> FloatArray:
    """:func:`euler_to_dcm` of one triple from its ``_trig`` values."""
    sr, cr, sp, cp, sy, cy = t
    return np.array(
        [
            [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
            [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
            [sp, -sr * cp, -cr * cp],
        ]
    )


def euler_to_dcm_derivatives(theta: ArrayLike) -> FloatArray:
    """``dC_b^e / dtheta_i`` for one angle triple: (3, 3, 3), index ``i`` first.

    Entry-wise derivatives of :func:`euler_to_dcm` (equal to ``dR_x/da = R_x [e_x]_x`` etc. in
    the product ``C_ned^enu R_z R_y R_x``; the tests check both and finite differences).
    """
    return _dcm_derivatives(_trig(np.asarray(theta, dtype=np.float64)))


def _dcm_derivatives(t: _Trig) -> FloatArray:
    """:func:`euler_to_dcm_derivatives` from the ``_trig`` values."""
    sr, cr, sp, cp, sy, cy = t
    return np.array(
        [
            [  # d/droll
                [0.0, cr * sp * sy - sr * cy, -sr * sp * sy - cr * cy],
                [0.0, cr * sp * cy + sr * sy, -sr * sp * cy + cr * sy],
                [0.0, -cr * cp, sr * cp],
            ],
            [  # d/dpitch
                [-sp * sy, sr * cp * sy, cr * cp * sy],
                [-sp * cy, sr * cp * cy, cr * cp * cy],
                [cp, sr * sp, cr * sp],
            ],
            [  # d/dyaw: dE/dyaw = N, dN/dyaw = -E, U does not depend on yaw
                [cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
                [-cp * sy, -sr * sp * sy - cr * cy, -cr * sp * sy + sr * cy],
                [0.0, 0.0, 0.0],
            ],
        ]
    )


def euler_rate_matrix(theta: ArrayLike) -> FloatArray:
    """``E(theta)`` (3, 3) with ``d theta / dt = E(theta) w_b`` (z-y-x Euler kinematics)."""
    return _rate_matrix(_trig(np.asarray(theta, dtype=np.float64)))


def _rate_matrix(t: _Trig) -> FloatArray:
    """:func:`euler_rate_matrix` from the ``_trig`` values."""
    sr, cr, sp, cp, _, _ = t
    tp = sp / cp
    return np.array([[1.0, sr * tp, cr * tp], [0.0, cr, -sr], [0.0, sr / cp, cr / cp]])


def _rate_matrix_derivatives(t: _Trig) -> tuple[FloatArray, FloatArray]:
    """``dE/droll``, ``dE/dpitch`` (each (3, 3)) from the ``_trig`` values; ``E`` has no yaw."""
    sr, cr, sp, cp, _, _ = t
    tp, c2 = sp / cp, cp * cp
    dEr = np.array([[0.0, cr * tp, -sr * tp], [0.0, -sr, -cr], [0.0, cr / cp, -sr / cp]])
    dEp = np.array([[0.0, sr / c2, cr / c2], [0.0, 0.0, 0.0], [0.0, sr * sp / c2, cr * sp / c2]])
    return dEr, dEp


def body_rates_from_euler_rates(theta: ArrayLike, theta_dot: ArrayLike) -> FloatArray:
    """``w_b = E(theta)^-1 theta_dot`` in closed form (3,).

    ``E^-1 = [[1, 0, -sp], [0, cr, sr cp], [0, -sr, cr cp]]`` (no matrix inversion).
    """
    sr, cr, sp, cp, _, _ = _trig(np.asarray(theta, dtype=np.float64))
    td = np.asarray(theta_dot, dtype=np.float64)
    Einv = np.array([[1.0, 0.0, -sp], [0.0, cr, sr * cp], [0.0, -sr, cr * cp]])
    return Einv @ td


# -- IMU propagation ----------------------------------------------------------------------------
def propagate(x: ArrayLike, u: ArrayLike, dt: float) -> FloatArray:
    """One strapdown step ``x+ = f(x, u)`` (module docstring), (9,) -> (9,)."""
    xa, ua, h = _state(x), _input(u), _dt(dt)
    t = _trig(xa[6:9])
    return _propagate(xa, ua, h, _dcm(t), _rate_matrix(t))


def _propagate(
    xa: FloatArray, ua: FloatArray, h: float, C: FloatArray, E: FloatArray
) -> FloatArray:
    """:func:`propagate` of checked inputs, given ``C = C_b^e(theta)`` and ``E(theta)``."""
    p, v, th = xa[0:3], xa[3:6], xa[6:9]
    a = C @ ua[0:3] + _G_E  # a = C_b^e f_b + g_e
    out = np.empty(STATE_DIM)
    out[0:3] = p + v * h + 0.5 * a * h * h  # p+ = p + v dt + a dt^2 / 2
    out[3:6] = v + a * h  # v+ = v + a dt
    out[6:9] = th + E @ ua[3:6] * h  # theta+ = theta + E w_b dt
    return out


def propagate_steps(x: ArrayLike, u: ArrayLike, dt: float, steps: int) -> FloatArray:
    """``x_0 = x, x_{t+1} = f(x_t, u)`` with one input held: (steps + 1, 9).

    :func:`propagate` repeated (the same values bit for bit), with the inputs checked once.
    """
    xa, ua, h = _state(x), _input(u), _dt(dt)
    out = np.empty((int(steps) + 1, STATE_DIM))
    out[0] = xa
    for t in range(int(steps)):
        tr = _trig(out[t, 6:9])
        out[t + 1] = _propagate(out[t], ua, h, _dcm(tr), _rate_matrix(tr))
    return out


def propagation_jacobians(x: ArrayLike, u: ArrayLike, dt: float) -> tuple[FloatArray, FloatArray]:
    """Analytic ``F = dx+/dx`` (9, 9) and ``G = dx+/du`` (9, 6) of :func:`propagate`.

    With ``A = d(C_b^e f_b)/dtheta`` (3, 3), column ``i`` being ``(dC/dtheta_i) f_b``::

        F = [[I, dt I, dt^2/2 A], [0, I, dt A], [0, 0, I + dt [dE/droll w, dE/dpitch w, 0]]]
        G = [[dt^2/2 C, 0], [dt C, 0], [0, dt E]]
    """
    xa, ua, h = _state(x), _input(u), _dt(dt)
    t = _trig(xa[6:9])
    return _jacobians(xa, ua, h, _dcm(t), _rate_matrix(t), t)


def _jacobians(
    xa: FloatArray, ua: FloatArray, h: float, C: FloatArray, E: FloatArray, t: _Trig
) -> tuple[FloatArray, FloatArray]:
    """:func:`propagation_jacobians` of checked inputs, given ``C``, ``E``, ``_trig`` at theta."""
    f, w = ua[0:3], ua[3:6]
    A = _dcm_derivatives(t) @ f  # (3 angles, 3): row i = (dC/dtheta_i) f
    dEr, dEp = _rate_matrix_derivatives(t)
    F = _f_template(h).copy()  # I with the dt I block (the same bits as building it here)
    F[0:3, 6:9] = 0.5 * h * h * A.T
    F[3:6, 6:9] = h * A.T
    F[6:9, 6] += h * (dEr @ w)
    F[6:9, 7] += h * (dEp @ w)
    G = np.zeros((STATE_DIM, 6))
    G[0:3, 0:3] = 0.5 * h * h * C
    G[3:6, 0:3] = h * C
    G[6:9, 3:6] = h * E
    return F, G


@functools.lru_cache(maxsize=8)
def _f_template(h: float) -> FloatArray:
    """Read-only ``F`` skeleton of :func:`_jacobians`: ``I`` (9, 9) with ``F[0:3, 3:6] = h I``.

    ``h`` is a checked ``dt > 0``, so equal keys give the same bits (no signed zeros).
    """
    F = np.eye(STATE_DIM)
    F[0:3, 3:6] = h * np.eye(3)
    F.flags.writeable = False
    return F


@functools.lru_cache(maxsize=8)
def _noise_scale(accel_sigma: float, gyro_sigma: float) -> FloatArray:
    """Read-only ``(sa, sa, sa, sg, sg, sg)`` of :func:`process_noise` for positive sigmas."""
    scale = np.repeat([accel_sigma, gyro_sigma], 3)
    scale.flags.writeable = False
    return scale


def propagate_with_jacobians(
    x: ArrayLike, u: ArrayLike, dt: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(x+, F, G)``: :func:`propagate` and :func:`propagation_jacobians` at one ``(x, u)``.

    The same values bit for bit, with the inputs checked and ``C``, ``E`` formed once.
    """
    xa, ua, h = _state(x), _input(u), _dt(dt)
    t = _trig(xa[6:9])
    C, E = _dcm(t), _rate_matrix(t)
    F, G = _jacobians(xa, ua, h, C, E, t)
    return _propagate(xa, ua, h, C, E), F, G


def process_noise(G: ArrayLike, accel_sigma: float, gyro_sigma: float) -> FloatArray:
    """``Q = G diag(sa^2 I3, sg^2 I3) G^T`` (9, 9), symmetric PSD (rank <= 6).

    Args:
        G: ``dx+/du`` (9, 6) from :func:`propagation_jacobians`.
        accel_sigma: accelerometer noise ``sa`` per sample (m/s^2).
        gyro_sigma: gyro noise ``sg`` per sample (rad/s).
    """
    Ga = np.asarray(G, dtype=np.float64)
    sa, sg = float(accel_sigma), float(gyro_sigma)
    if sa > 0.0 and sg > 0.0:  # cached (positive: no signed zero or NaN in the key)
        scale = _noise_scale(sa, sg)
    else:
        scale = np.repeat([sa, sg], 3)
    Gs = Ga * scale  # G diag(sa, sa, sa, sg, sg, sg)
    Q = Gs @ Gs.T
    return 0.5 * (Q + Q.T)


# -- angles of arrival --------------------------------------------------------------------------
def body_vectors(x: ArrayLike, landmarks: ArrayLike) -> FloatArray:
    """``Delta^n = C_e^b (p_n - p)`` for every landmark (eq. 17): (N, 3)."""
    xa, lm = _state(x), _landmarks(landmarks)
    return (lm - xa[0:3]) @ euler_to_dcm(xa[6:9])  # rows d^T C_b^e = (C_e^b d)^T


def aoa_angles(delta: ArrayLike) -> FloatArray:
    """``(atan2(D_y, D_x), atan2(-D_z, rho))`` of body vectors ``delta`` (..., 3) -> (..., 2)."""
    d = np.asarray(delta, dtype=np.float64)
    rho = np.hypot(d[..., 0], d[..., 1])
    return np.stack([np.arctan2(d[..., 1], d[..., 0]), np.arctan2(-d[..., 2], rho)], -1)


def aoa_angles_jacobian(delta: ArrayLike) -> FloatArray:
    """``Psi = d(azimuth, elevation) / d Delta`` (eq. 21), (..., 3) -> (..., 2, 3).

    Row 1: ``(-D_y, D_x, 0) / rho^2``; row 2: ``(D_x D_z, D_y D_z, -rho^2) / (rho |D|^2)``.
    Singular at ``rho = 0`` (landmark on the body z axis).
    """
    d = np.asarray(delta, dtype=np.float64)
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    rho2 = dx * dx + dy * dy
    rho = np.sqrt(rho2)
    r2 = rho2 + dz * dz  # |Delta|^2
    Psi = np.empty((*d.shape[:-1], 2, 3))
    Psi[..., 0, 0] = -dy / rho2
    Psi[..., 0, 1] = dx / rho2
    Psi[..., 0, 2] = 0.0
    c = dz / (rho * r2)
    Psi[..., 1, 0] = dx * c
    Psi[..., 1, 1] = dy * c
    Psi[..., 1, 2] = -rho / r2
    return Psi


def measure(x: ArrayLike, landmarks: ArrayLike) -> FloatArray:
    """Noise-free angles of arrival ``h(x)`` of every landmark (eq. 16, sign fix): (N, 2)."""
    return aoa_angles(body_vectors(x, landmarks))


def measurement_jacobian(x: ArrayLike, landmarks: ArrayLike) -> FloatArray:
    """Exact ``dh/dx`` (N, 2, 9) with respect to the state ``x = (p, v, theta)``.

    ``dDelta/dp = -C_e^b``, ``dDelta/dv = 0``, ``dDelta/dtheta_i = (dC_b^e/dtheta_i)^T (p_n - p)``,
    then ``H = Psi dDelta/dx``.
    """
    xa, lm = _state(x), _landmarks(landmarks)
    th = xa[6:9]
    d = lm - xa[0:3]  # p_n - p, (N, 3)
    C = euler_to_dcm(th)
    delta = d @ C  # Delta = C_e^b d
    Psi = aoa_angles_jacobian(delta)  # (N, 2, 3)
    dD_dth = np.einsum("iab,na->nbi", euler_to_dcm_derivatives(th), d)  # (N, 3, 3 angles)
    H = np.zeros((lm.shape[0], 2, STATE_DIM))
    H[:, :, 0:3] = -(Psi @ C.T)  # Psi dDelta/dp = -Psi C_e^b
    H[:, :, 6:9] = Psi @ dD_dth
    return H


def paper_jacobian(x: ArrayLike, landmarks: ArrayLike) -> FloatArray:
    """Eq. (20): ``H^n = Psi^n [[Delta^n]_x, 0_3, -I_3]`` (N, 2, 9).

    Columns follow the paper's error state ``(phi, dv, dp^b)`` (module docstring), NOT the
    state order ``(p, v, theta)``; ``paper_jacobian = measurement_jacobian @ T`` with ``T`` from
    :func:`paper_error_to_state`.
    """
    delta = body_vectors(x, landmarks)
    Psi = aoa_angles_jacobian(delta)
    H = np.zeros((delta.shape[0], 2, STATE_DIM))
    H[:, :, 0:3] = Psi @ skew(delta)  # Psi [Delta]_x
    H[:, :, 6:9] = -Psi  # Psi (-I)
    return H


def paper_error_to_state(x: ArrayLike) -> FloatArray:
    """``T = dx/de`` (9, 9): state perturbation ``(dp, dv, dtheta)`` per paper error ``e``.

    ``dp = C_b^e dp^b``, ``dv = dv``, ``dtheta = E(theta) phi`` (a body-frame rotation ``phi``
    moves the Euler angles as the body rate does: ``theta_dot = E w_b``).
    """
    xa = _state(x)
    T = np.zeros((STATE_DIM, STATE_DIM))
    T[0:3, 6:9] = euler_to_dcm(xa[6:9])
    T[3:6, 3:6] = np.eye(3)
    T[6:9, 0:3] = euler_rate_matrix(xa[6:9])
    return T


# -- batched strapdown (the filter of B episodes at once) -----------------------------------------
def dcm_batch(theta: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``C_b^e`` (B, 3, 3) and ``dC_b^e/dtheta_i`` (B, 3, 3, 3) (``i`` second) of angles (B, 3).

    The entries of :func:`euler_to_dcm` and :func:`euler_to_dcm_derivatives`, batched.
    """
    s, c = np.sin(theta), np.cos(theta)
    sr, sp, sy = s[:, 0], s[:, 1], s[:, 2]
    cr, cp, cy = c[:, 0], c[:, 1], c[:, 2]
    srsp, crsp = sr * sp, cr * sp
    B = theta.shape[0]
    C = np.empty((B, 3, 3))  # rows E, N, -D of C_b^ned
    C[:, 0, 0], C[:, 0, 1], C[:, 0, 2] = cp * sy, srsp * sy + cr * cy, crsp * sy - sr * cy
    C[:, 1, 0], C[:, 1, 1], C[:, 1, 2] = cp * cy, srsp * cy - cr * sy, crsp * cy + sr * sy
    C[:, 2, 0], C[:, 2, 1], C[:, 2, 2] = sp, -sr * cp, -cr * cp
    D = np.zeros((B, 3, 3, 3))
    D[:, 0, 0, 1], D[:, 0, 0, 2] = crsp * sy - sr * cy, -srsp * sy - cr * cy  # d/droll
    D[:, 0, 1, 1], D[:, 0, 1, 2] = crsp * cy + sr * sy, -srsp * cy + cr * sy
    D[:, 0, 2, 1], D[:, 0, 2, 2] = -cr * cp, sr * cp
    D[:, 1, 0, 0], D[:, 1, 0, 1], D[:, 1, 0, 2] = -sp * sy, sr * cp * sy, cr * cp * sy  # d/dpitch
    D[:, 1, 1, 0], D[:, 1, 1, 1], D[:, 1, 1, 2] = -sp * cy, sr * cp * cy, cr * cp * cy
    D[:, 1, 2, 0], D[:, 1, 2, 1], D[:, 1, 2, 2] = cp, srsp, crsp
    D[:, 2, 0:2] = C[:, 1::-1]  # d/dyaw: dE/dyaw = N, dN/dyaw = -E, U has no yaw
    D[:, 2, 1] *= -1.0
    return C, D


def strapdown_batch(
    x: FloatArray, u: FloatArray, dt: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(x+, F, G)`` of :func:`propagate` and :func:`propagation_jacobians`, batched over B.

    The same equations (module docstring and :func:`propagation_jacobians`) for ``B`` states at
    once: ``x`` (B, 9), ``u`` (B, 6) -> ``x+`` (B, 9), ``F = dx+/dx`` (B, 9, 9),
    ``G = dx+/du`` (B, 9, 6). Internal: the inputs are checked float64 arrays.
    """
    B, h = x.shape[0], float(dt)
    th = x[:, 6:9]
    s, c = np.sin(th[:, 0:2]), np.cos(th[:, 0:2])
    sr, sp, cr, cp = s[:, 0], s[:, 1], c[:, 0], c[:, 1]
    tp, c2 = sp / cp, cp * cp
    C, D = dcm_batch(th)
    f, w = u[:, 0:3], u[:, 3:6]
    E = np.zeros((B, 3, 3))  # d theta / dt = E w_b (euler_rate_matrix)
    E[:, 0, 0], E[:, 0, 1], E[:, 0, 2] = 1.0, sr * tp, cr * tp
    E[:, 1, 1], E[:, 1, 2] = cr, -sr
    E[:, 2, 1], E[:, 2, 2] = sr / cp, cr / cp
    a = (C @ f[:, :, None])[:, :, 0] + _G_E  # a = C_b^e f_b + g_e
    xp = np.empty((B, STATE_DIM))
    xp[:, 0:3] = x[:, 0:3] + x[:, 3:6] * h + 0.5 * a * h * h  # p+ = p + v dt + a dt^2 / 2
    xp[:, 3:6] = x[:, 3:6] + a * h  # v+ = v + a dt
    xp[:, 6:9] = th + (E @ w[:, :, None])[:, :, 0] * h  # theta+ = theta + E w_b dt
    At = (D @ f[:, None, :, None])[..., 0]  # (B, 3 angles, 3): row i = (dC/dtheta_i) f
    A = np.swapaxes(At, 1, 2)
    w1, w2 = w[:, 1], w[:, 2]
    F = np.broadcast_to(_f_template(h), (B, STATE_DIM, STATE_DIM)).copy()
    F[:, 0:3, 6:9] = 0.5 * h * h * A
    F[:, 3:6, 6:9] = h * A
    # F[6:9, 6] += dt dE/droll w, F[6:9, 7] += dt dE/dpitch w (E has no yaw)
    F[:, 6, 6] += h * (cr * tp * w1 - sr * tp * w2)
    F[:, 7, 6] += h * (-sr * w1 - cr * w2)
    F[:, 8, 6] += h * (cr / cp * w1 - sr / cp * w2)
    F[:, 6, 7] += h * (sr / c2 * w1 + cr / c2 * w2)
    F[:, 8, 7] += h * (sr * sp / c2 * w1 + cr * sp / c2 * w2)
    G = np.zeros((B, STATE_DIM, 6))
    G[:, 0:3, 0:3] = 0.5 * h * h * C
    G[:, 3:6, 0:3] = h * C
    G[:, 6:9, 3:6] = h * E
    return xp, F, G
