"""Motion and measurement models of Kirchner, Hespanha & Garagić (2020), Sections 4-5.

Motion model, eq. (18): on an estimation window starting at ``t_{l-1}``, the target's ground
position and velocity at ``s = tau - t_{l-1}`` are::

    q(s) = theta1 + s theta2 + s^2/2 theta3,      qdot(s) = theta2 + s theta3

with ``theta1, theta2, theta3`` in ``R^2`` (position, velocity, curvature/acceleration). The
motion parameters are the first six entries of ``theta``, ordered ``[x, y, vx, vy, ax, ay]``.
The target lies on the ground plane, so its 3-D position is ``[q; 0]``.

Every function is vectorised over ``T`` candidate times: ``s`` is ``(T,)``, the agent's known
positions ``p`` and velocities ``pdot`` are ``(T, 3)``. Jacobians are returned with respect to
the six motion parameters followed by the sensor's own nuisance parameters (if any); the
caller scatters those nuisance columns into its full parameter vector.

Chain rule used throughout: ``d[q; 0]/dtheta = [I2; 0] (x) b(s)`` with ``b = (1, s, s^2/2)`` and
``d[qdot; 0]/dtheta = [I2; 0] (x) bdot(s)`` with ``bdot = (0, 1, s)``, i.e. the column of
parameter ``2 j + i`` (basis ``j``, coordinate ``i``) is ``grad_q[i] * b[j]``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from selenv.core.linalg import FloatArray, as_float_array, check_finite, check_shape

__all__ = [
    "C_LIGHT",
    "N_MOTION",
    "camera_depth",
    "camera_jacobian",
    "camera_mean",
    "doppler_jacobian",
    "doppler_mean",
    "intrinsics",
    "look_at_rotation",
    "motion_basis",
    "spiral_path",
    "target_state",
    "toa_jacobian",
    "toa_mean",
]

#: speed of light (m/s)
C_LIGHT = 299_792_458.0
#: number of motion parameters (theta1, theta2, theta3 in R^2)
N_MOTION = 6


# -- motion model -------------------------------------------------------------------------------
def _motion(theta: ArrayLike) -> FloatArray:
    """The motion parameters ``theta[..., :6]`` of one ``(d,)`` or per-time ``(T, d)`` vector."""
    th = check_finite(as_float_array(theta, "theta"), "theta")
    if th.ndim not in (1, 2) or th.shape[-1] < N_MOTION:
        raise ValueError(
            f"theta must have shape (d,) or (T, d) with d >= {N_MOTION}, got {th.shape}"
        )
    return th[..., :N_MOTION]


def _times(s: ArrayLike) -> FloatArray:
    return check_shape(check_finite(as_float_array(s, "s"), "s"), (None,), "s")


def _points(p: ArrayLike, T: int, name: str) -> FloatArray:
    return check_shape(check_finite(as_float_array(p, name), name), (T, 3), name)


def motion_basis(s: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Basis of eq. (18) and of its time derivative.

    Args:
        s: ``(T,)`` times since the window start ``t_{l-1}``.

    Returns:
        ``b (T, 3) = (1, s, s^2/2)`` and ``bdot (T, 3) = (0, 1, s)``.
    """
    s_a = _times(s)
    one, zero = np.ones_like(s_a), np.zeros_like(s_a)
    return np.stack([one, s_a, 0.5 * s_a**2], axis=1), np.stack([zero, one, s_a], axis=1)


def target_state(theta: ArrayLike, s: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Target position and velocity, eq. (18).

    Args:
        theta: ``(d,)`` parameters, ``d >= 6``; only ``theta[:6]`` is used. Or ``(T, d)``:
            one parameter vector per time (many drawn targets evaluated in one call).
        s: ``(T,)`` times since the window start.

    Returns:
        ``q (T, 2)`` and ``qdot (T, 2)``.
    """
    th = _motion(theta)
    b, bdot = motion_basis(s)
    if th.ndim == 1:
        th3 = th.reshape(3, 2)  # rows theta1, theta2, theta3
        return b @ th3, bdot @ th3
    per_time = check_shape(th, (b.shape[0], N_MOTION), "theta").reshape(-1, 3, 2)
    return np.einsum("tj,tji->ti", b, per_time), np.einsum("tj,tji->ti", bdot, per_time)


def spiral_path(
    s: ArrayLike,
    q: ArrayLike,
    qdot: ArrayLike,
    *,
    window_s: float,
    start_radius: ArrayLike,
    end_radius: ArrayLike,
    sweep_rad: float,
    end_bearing: ArrayLike,
    altitude: float,
) -> tuple[FloatArray, FloatArray]:
    """Agent path spiralling in on a moving ground point, with its analytic velocity.

    Relative to the point ``q(s)``, the range shrinks linearly from ``start_radius`` to
    ``end_radius`` over ``[0, window_s]`` while the bearing sweeps ``sweep_rad`` and ends at
    ``end_bearing`` (closest at the end of the path, Fig. 2), at a constant ``altitude``::

        p = [q + r(u) (cos phi(u), sin phi(u)); altitude],   u = s / window_s,
        phi(u) = end_bearing - sweep_rad (1 - u).

    Args:
        s: ``(T,)`` times since the window start.
        q: ``(T, 2)`` ground point (e.g. from :func:`target_state`).
        qdot: ``(T, 2)`` its velocity.
        window_s: window length (s).
        start_radius: horizontal range at ``s = 0`` (m).
        end_radius: horizontal range at ``s = window_s`` (m).
        sweep_rad: bearing swept over the window (rad).
        end_bearing: bearing at the end of the window (rad, from world x).
        altitude: constant height above the ground plane (m).

    ``start_radius``, ``end_radius`` and ``end_bearing`` are scalars or ``(T,)`` (one per time:
    the paths of many agents or problems in one call).

    Returns:
        Positions and velocities ``(T, 3)``.
    """
    s_a = _times(s)
    q_a = check_shape(as_float_array(q, "q"), (s_a.shape[0], 2), "q")
    qd_a = check_shape(as_float_array(qdot, "qdot"), (s_a.shape[0], 2), "qdot")
    u = s_a / window_s
    r0 = np.asarray(start_radius, dtype=np.float64)
    r1 = np.asarray(end_radius, dtype=np.float64)
    r = r0 + (r1 - r0) * u
    rdot = np.reshape((r1 - r0) / window_s, (-1, 1))  # (1, 1) or (T, 1)
    phi = np.asarray(end_bearing, dtype=np.float64) - sweep_rad * (1.0 - u)
    phidot = sweep_rad / window_s
    radial = np.column_stack([np.cos(phi), np.sin(phi)])
    tangent = np.column_stack([-np.sin(phi), np.cos(phi)])
    pos = np.column_stack([q_a + r[:, None] * radial, np.full(s_a.shape[0], altitude)])
    vel2 = qd_a + rdot * radial + (r * phidot)[:, None] * tangent
    return pos, np.column_stack([vel2, np.zeros(s_a.shape[0])])


def _relative(
    theta: ArrayLike, s: ArrayLike, p: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """``r = [q; 0] - p`` (T, 3), ``qdot3 = [qdot; 0]`` (T, 3), ``b``, ``bdot`` and ``p``."""
    s_a = _times(s)
    p_a = _points(p, s_a.shape[0], "p")
    q, qdot = target_state(theta, s_a)
    b, bdot = motion_basis(s_a)
    zeros = np.zeros((s_a.shape[0], 1))
    r = np.concatenate([q, zeros], axis=1) - p_a
    return r, np.concatenate([qdot, zeros], axis=1), b, bdot, p_a


def _chain(grad_q: FloatArray, b: FloatArray) -> FloatArray:
    """Chain ``grad_q (T, ..., 2)`` (gradient w.r.t. the ground position) through ``b (T, 3)``.

    Returns ``(T, ..., 6)`` with column ``2 j + i`` equal to ``grad_q[..., i] * b[:, j]``.
    """
    extra = (1,) * (grad_q.ndim - 2)
    out = b.reshape(b.shape[0], *extra, 3, 1) * grad_q[..., None, :]  # (T, ..., 3, 2)
    return out.reshape(*grad_q.shape[:-1], N_MOTION)


# -- time of arrival, eq. (19)-(20) ---------------------------------------------------------------
def toa_mean(
    theta: ArrayLike,
    s: ArrayLike,
    p: ArrayLike,
    k: ArrayLike,
    theta_T: ArrayLike,
    theta_T0: ArrayLike,
) -> FloatArray:
    """Scaled time of arrival ``c T(tau_k) = rho + theta_T k + theta_T0``, eq. (20).

    Args:
        theta: ``(d,)`` parameters (``theta[:6]`` used).
        s: ``(T,)`` times since the window start.
        p: ``(T, 3)`` receiver positions.
        k: ``(T,)`` symbol indices.
        theta_T: ``c T`` (m), scalar or ``(T,)``.
        theta_T0: ``c T0`` (m), scalar or ``(T,)``.

    Returns:
        ``(T,)`` means in metres; ``rho = ||[q; 0] - p||`` is eq. (19).
    """
    r, *_ = _relative(theta, s, p)
    k_a = check_shape(as_float_array(k, "k"), (r.shape[0],), "k")
    return np.linalg.norm(r, axis=1) + np.asarray(theta_T) * k_a + np.asarray(theta_T0)


def toa_jacobian(theta: ArrayLike, s: ArrayLike, p: ArrayLike, k: ArrayLike) -> FloatArray:
    """Jacobian of :func:`toa_mean` (Sec. 5, time-of-arrival gradients).

    ``d rho / d q = e^T`` with ``e = ([q; 0] - p) / rho``, chained through eq. (18);
    ``d / d theta_T = k`` and ``d / d theta_T0 = 1``.

    Returns:
        ``(T, 8)``: columns ``[x, y, vx, vy, ax, ay, theta_T, theta_T0]``.
    """
    r, _, b, _, _ = _relative(theta, s, p)
    k_a = check_shape(as_float_array(k, "k"), (r.shape[0],), "k")
    e = r / np.linalg.norm(r, axis=1, keepdims=True)
    return np.concatenate([_chain(e[:, :2], b), k_a[:, None], np.ones((r.shape[0], 1))], axis=1)


# -- Doppler, eq. (21)-(22) -----------------------------------------------------------------------
def doppler_mean(
    theta: ArrayLike, s: ArrayLike, p: ArrayLike, pdot: ArrayLike, theta_lambda: ArrayLike
) -> FloatArray:
    """Scaled frequency shift ``lambda F = theta_lambda - rhodot``, eq. (22).

    Args:
        theta: ``(d,)`` parameters (``theta[:6]`` used).
        s: ``(T,)`` times since the window start.
        p: ``(T, 3)`` receiver positions.
        pdot: ``(T, 3)`` receiver velocities.
        theta_lambda: ``lambda Delta f`` (m/s), scalar or ``(T,)``.

    Returns:
        ``(T,)`` means in m/s, ``rhodot = e^T ([qdot; 0] - pdot)``, ``e = ([q; 0] - p) / rho``.
    """
    r, qdot3, *_ = _relative(theta, s, p)
    v = qdot3 - _points(pdot, r.shape[0], "pdot")
    rhodot = np.einsum("ti,ti->t", r, v) / np.linalg.norm(r, axis=1)
    return np.asarray(theta_lambda) - rhodot


def doppler_jacobian(theta: ArrayLike, s: ArrayLike, p: ArrayLike, pdot: ArrayLike) -> FloatArray:
    """Exact Jacobian of :func:`doppler_mean` (Sec. 5, Doppler gradients).

    ``d rhodot / d q = v^T (I - e e^T) / rho`` with ``v = [qdot; 0] - pdot`` and
    ``d rhodot / d qdot = e^T``, chained through ``b`` and ``bdot`` of eq. (18). The mean is
    ``theta_lambda - rhodot``, so the motion columns are minus the paper's printed expressions
    (``Q_k`` is invariant to that sign); ``d / d theta_lambda = 1``.

    Returns:
        ``(T, 7)``: columns ``[x, y, vx, vy, ax, ay, theta_lambda]``.
    """
    r, qdot3, b, bdot, _ = _relative(theta, s, p)
    v = qdot3 - _points(pdot, r.shape[0], "pdot")
    rho = np.linalg.norm(r, axis=1, keepdims=True)
    e = r / rho
    d_q = (v - np.einsum("ti,ti->t", v, e)[:, None] * e) / rho  # v^T (I - e e^T) / rho
    d_rhodot = _chain(d_q[:, :2], b) + _chain(e[:, :2], bdot)
    return np.concatenate([-d_rhodot, np.ones((r.shape[0], 1))], axis=1)


# -- camera, eq. (23) ---------------------------------------------------------------------------
def intrinsics(focal_px: float, ox: float = 0.0, oy: float = 0.0) -> FloatArray:
    """Intrinsic matrix ``A = [[f, 0, ox], [0, f, oy], [0, 0, 1]]`` (no skew, square pixels)."""
    return np.array([[focal_px, 0.0, ox], [0.0, focal_px, oy], [0.0, 0.0, 1.0]])


def look_at_rotation(p: ArrayLike, target: ArrayLike) -> FloatArray:
    """World-to-camera rotations ``R_c`` of a gimbal at ``p`` looking at ``target``.

    Convention: camera coordinates are ``x_c = R_c (x - p)``; the rows of ``R_c`` are the camera
    axes expressed in world coordinates. Row 3 (optical axis, depth) is the unit vector from
    ``p`` to ``target``; row 1 (image x) is horizontal, ``z_c x e_up`` normalised (to the right
    when looking along ``z_c``); row 2 (image y) is ``z_c x x_c`` (pointing down in the world),
    so ``R_c`` is a proper rotation (det +1). When ``z_c`` is vertical, world ``y`` replaces
    ``e_up`` in the cross product.

    Args:
        p: ``(T, 3)`` camera centres.
        target: ``(3,)`` or ``(T, 3)`` points to look at.

    Returns:
        ``(T, 3, 3)`` rotation matrices.

    Raises:
        ValueError: if a target coincides with its camera centre.
    """
    p_a = check_finite(as_float_array(p, "p"), "p")
    check_shape(p_a, (None, 3), "p")
    t_a = np.broadcast_to(check_finite(as_float_array(target, "target"), "target"), p_a.shape)
    z = t_a - p_a
    nz = np.linalg.norm(z, axis=1, keepdims=True)
    if np.any(nz <= 1e-12):
        raise ValueError("target must differ from the camera position p at every time")
    z = z / nz
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    vertical = np.linalg.norm(x, axis=1) < 1e-9
    x[vertical] = np.cross(z[vertical], np.array([0.0, 1.0, 0.0]))
    x = x / np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _projection(
    theta: ArrayLike, s: ArrayLike, p: ArrayLike, R_c: ArrayLike, A: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``M (T, 2, 3)``, ``m (T, 3)``, ``r (T, 3)`` and ``b (T, 3)`` of eq. (23)."""
    r, _, b, _, _ = _relative(theta, s, p)
    Rc = check_shape(check_finite(as_float_array(R_c, "R_c"), "R_c"), (r.shape[0], 3, 3), "R_c")
    A_a = check_shape(check_finite(as_float_array(A, "A"), "A"), (3, 3), "A")
    AR = A_a @ Rc  # (T, 3, 3)
    return AR[:, :2, :], AR[:, 2, :], r, b


def camera_depth(
    theta: ArrayLike, s: ArrayLike, p: ArrayLike, R_c: ArrayLike, A: ArrayLike
) -> FloatArray:
    """Projective depth ``d = m ([q; 0] - p)`` of eq. (23), ``(T,)``; positive in front."""
    _, m, r, _ = _projection(theta, s, p, R_c, A)
    return np.einsum("ti,ti->t", m, r)


def camera_mean(
    theta: ArrayLike, s: ArrayLike, p: ArrayLike, R_c: ArrayLike, A: ArrayLike
) -> FloatArray:
    """Image coordinates ``I = M ([q; 0] - p) / (m ([q; 0] - p))``, eq. (23).

    Args:
        theta: ``(d,)`` parameters (``theta[:6]`` used).
        s: ``(T,)`` times since the window start.
        p: ``(T, 3)`` camera centres.
        R_c: ``(T, 3, 3)`` world-to-camera rotations (see :func:`look_at_rotation`).
        A: ``(3, 3)`` intrinsics (see :func:`intrinsics`).

    Returns:
        ``(T, 2)`` image coordinates in pixels, with ``M = [I2 0] A R_c`` and ``m = e3^T A R_c``.
    """
    M, m, r, _ = _projection(theta, s, p, R_c, A)
    U = np.einsum("tij,tj->ti", M, r)  # U = M (q - p)
    d = np.einsum("ti,ti->t", m, r)  # d = m (q - p)
    return U / d[:, None]


def camera_jacobian(
    theta: ArrayLike, s: ArrayLike, p: ArrayLike, R_c: ArrayLike, A: ArrayLike
) -> FloatArray:
    """Jacobian of :func:`camera_mean` (Sec. 5, camera gradients).

    ``d I / d q = (M / d - U m / d^2)[:, :2]`` with ``U = M ([q; 0] - p)``, ``d = m ([q; 0] -
    p)``, chained through eq. (18) (factors ``1, s, s^2/2`` for ``theta1, theta2, theta3``).

    Returns:
        ``(T, 2, 6)``: rows ``(u, v)``, columns ``[x, y, vx, vy, ax, ay]``.
    """
    M, m, r, b = _projection(theta, s, p, R_c, A)
    U = np.einsum("tij,tj->ti", M, r)
    d = np.einsum("ti,ti->t", m, r)[:, None, None]
    dI_dr = M / d - U[:, :, None] * m[:, None, :] / d**2  # (T, 2, 3)
    return _chain(dI_dr[:, :, :2], b)
