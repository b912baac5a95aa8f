"""True flight and landmark layout of the landmark-selection scenario (Soubaras & Chahbazian).

A Fig. 3-like guided flight (straight legs and coordinated level turns, see
:mod:`selenv.families.landmarks.scenario`) whose true IMU drives the same strapdown model the filter
uses, and a seeded uniform landmark layout that keeps every landmark away from the body z axis.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from selenv.core.linalg import FloatArray
from selenv.families.landmarks.models import (
    GRAVITY,
    STATE_DIM,
    body_rates_from_euler_rates,
    euler_to_dcm,
    propagate,
    wrap_angle,
)

if TYPE_CHECKING:
    from selenv.families.landmarks.scenario import LandmarkConfig

__all__ = ["body_vectors_along", "draw_layout", "fly"]

_DEG = np.pi / 180.0
# guidance gains of the true flight (1/s, 1/s^2): roll, pitch, heading alignment, speed, altitude
_K_ROLL, _K_PITCH, _K_HEAD, _K_SPEED, _K_ALT, _K_VZ = 2.0, 1.0, 0.5, 0.2, 0.04, 0.4


def fly(cfg: LandmarkConfig) -> tuple[FloatArray, FloatArray]:
    """True states (T + 1, 9) and true IMU (T, 6) of the guided flight (module docstring)."""
    T, dt, V0 = int(cfg.horizon), float(cfg.dt), float(cfg.speed)
    ends = np.cumsum([leg[0] for leg in cfg.legs])
    rates = np.array([leg[1] * _DEG for leg in cfg.legs])
    psi0 = cfg.heading_deg * _DEG
    x = np.zeros(STATE_DIM)
    x[0:3] = (0.0, 0.0, cfg.altitude)
    x[3:6] = V0 * np.array([np.sin(psi0), np.cos(psi0), 0.0])
    x[8] = psi0
    states, imu = np.empty((T + 1, STATE_DIM)), np.empty((T, 6))
    states[0] = x
    max_roll_rate = cfg.max_roll_rate_deg * _DEG
    for k in range(T):
        leg = int(np.searchsorted(ends, (k * dt) % ends[-1], side="right"))
        roll_cmd = np.arctan(V0 * rates[min(leg, len(rates) - 1)] / GRAVITY)
        roll, pitch, yaw = x[6:9]
        v = x[3:6]
        Vh = float(np.hypot(v[0], v[1]))
        chi = float(np.arctan2(v[0], v[1]))  # course, clockwise from North
        fwd = np.array([np.sin(chi), np.cos(chi), 0.0])
        right = np.array([np.cos(chi), -np.sin(chi), 0.0])
        a = GRAVITY * np.tan(roll) * right + _K_SPEED * (V0 - Vh) * fwd  # coordinated turn
        a[2] = -_K_ALT * (x[2] - cfg.altitude) - _K_VZ * v[2]  # altitude hold
        theta_dot = np.array(
            [
                np.clip(_K_ROLL * (roll_cmd - roll), -max_roll_rate, max_roll_rate),
                -_K_PITCH * pitch,
                GRAVITY * np.tan(roll) / Vh + _K_HEAD * float(wrap_angle(chi - yaw)),
            ]
        )
        f_b = euler_to_dcm(x[6:9]).T @ (a + np.array([0.0, 0.0, GRAVITY]))  # f = C_e^b (a - g)
        imu[k, 0:3] = f_b
        imu[k, 3:6] = body_rates_from_euler_rates(x[6:9], theta_dot)
        x = propagate(x, imu[k], dt)
        states[k + 1] = x
    return states, imu


def body_vectors_along(
    states: FloatArray, landmarks: FloatArray, dcm: FloatArray | None = None
) -> FloatArray:
    """``Delta = C_e^b (p_n - p)`` (eq. 17) of every landmark at every state.

    Args:
        states: (S, 9) states.
        landmarks: (N, 3) or a batch (g, N, 3) of layouts.
        dcm: (S, 3, 3) ``C_b^e`` of ``states`` if known (``None``: computed).

    Returns:
        (S, N, 3), or (g, S, N, 3) for a batch of layouts.
    """
    C = euler_to_dcm(states[:, 6:9]) if dcm is None else dcm
    d = landmarks[..., None, :, :] - states[:, None, 0:3]  # (..., S, N, 3)
    return d @ C  # rows d^T C_b^e = (C_e^b d)^T


def draw_layout(
    cfg: LandmarkConfig,
    states: FloatArray,
    rng: np.random.Generator,
    dcm: FloatArray | None = None,
) -> FloatArray:
    """Uniform landmarks (N, 3) around the track, away from the body z axis (module docstring).

    ``dcm`` (T + 1, 3, 3): ``C_b^e`` along ``states`` if known (``None``: computed).

    A candidate ``l`` is kept when at every state ``rho > sin(a) |Delta|`` (``a`` =
    ``min_off_nadir_deg``, ``Delta = C_e^b (l - p)`` eq. 17, ``rho`` its horizontal part), i.e.
    ``cos^2(a) |l - p|^2 > Delta_z^2`` (``C`` is a rotation, so ``|Delta| = |l - p|`` and
    ``rho^2 = |Delta|^2 - Delta_z^2``), with ``Delta_z = l . c_3 - p . c_3`` and
    ``|l - p|^2 = |l|^2 - 2 l . p + |p|^2`` (``c_3`` the third column of ``C_b^e``): two
    ``(2N, 3) @ (3, T + 1)`` products per round instead of every body vector.
    """
    C = euler_to_dcm(states[:, 6:9]) if dcm is None else dcm
    n, m = int(cfg.n_landmarks), float(cfg.landmark_margin)
    low = [*(states[:, 0:2].min(axis=0) - m), cfg.landmark_height[0]]
    high = [*(states[:, 0:2].max(axis=0) + m), cfg.landmark_height[1]]
    sin_min = np.sin(cfg.min_off_nadir_deg * _DEG)
    cos2 = 1.0 - sin_min * sin_min
    p = states[:, 0:3]
    c3 = C[:, :, 2]  # (S, 3) third column of C_b^e: Delta_z = d . c3
    pT, c3T = np.ascontiguousarray(p.T), np.ascontiguousarray(c3.T)  # (3, S)
    p_c3 = np.einsum("sk,sk->s", p, c3)
    p_sq = np.einsum("sk,sk->s", p, p)
    kept: list[FloatArray] = []
    count = 0
    for _ in range(200):
        cand = rng.uniform(low, high, size=(2 * n, 3))
        dz = cand @ c3T
        dz -= p_c3
        r2 = cand @ pT
        r2 *= -2.0
        r2 += p_sq
        r2 += np.einsum("ik,ik->i", cand, cand)[:, None]
        ok = np.all(cos2 * r2 > dz * dz, axis=1)
        kept.append(cand[ok])
        count += int(ok.sum())
        if count >= n:
            return np.concatenate(kept)[:n]
    raise ValueError(
        f"could not place {n} landmarks outside {cfg.min_off_nadir_deg} deg of nadir; "
        "increase landmark_margin or lower min_off_nadir_deg"
    )
