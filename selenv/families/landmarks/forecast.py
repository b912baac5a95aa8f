"""Covariance forecast of the landmark EKF for ``rollout`` (see :mod:`selenv.agents.rollout`).

A forecast starts from the current estimate and covariance, holds the last IMU sample, and
applies the EKF's covariance recursion with the known landmark geometry and noise statistics;
it never sees the true state, future inputs or noise realisations.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from selenv.agents.rollout import held_input
from selenv.core.information import whiten
from selenv.core.kalman import kf_predict, kf_update
from selenv.core.linalg import FloatArray
from selenv.families.landmarks.env import landmark_cost
from selenv.families.landmarks.models import (
    STATE_DIM,
    measurement_jacobian,
    process_noise,
    propagate,
    propagation_jacobians,
)

__all__ = ["LandmarkForecast"]


class LandmarkForecast:
    """Covariance forecast of the landmark EKF (:class:`LandmarkEKF` steps).

    Args:
        x: (9,) current estimate; P: (9, 9) covariance; k: predictions done.
        u_hold: (6,) the last measured IMU sample, held over the forecast.
        landmarks: (N, 3) landmark positions (known geometry).
        R_landmark: (2, 2) one landmark's angle noise covariance.
        dt: filter step (s); accel_sigma, gyro_sigma: IMU noise statistics.
        objective: ``"logdet"`` or ``"det"`` (the env's cost eq. 11).
    """

    def __init__(
        self,
        *,
        x: FloatArray,
        P: FloatArray,
        k: int,
        u_hold: FloatArray,
        landmarks: FloatArray,
        R_landmark: FloatArray,
        dt: float,
        accel_sigma: float,
        gyro_sigma: float,
        objective: str,
    ) -> None:
        self.x = np.array(x, dtype=np.float64)
        self.P = np.array(P, dtype=np.float64)
        self.k = int(k)
        self.u_hold = np.array(u_hold, dtype=np.float64)
        self.landmarks = np.asarray(landmarks, dtype=np.float64)
        self.R_landmark = np.asarray(R_landmark, dtype=np.float64)
        self.dt, self.sigmas = float(dt), (float(accel_sigma), float(gyro_sigma))
        self.objective = objective
        self._R: dict[int, FloatArray] = {}

    @classmethod
    def from_env(cls, env: Any) -> LandmarkForecast:
        """Forecast from a ``LandmarkSelectionEnv``'s prediction (copied) and last IMU sample."""
        ekf, problem = env.ekf, env.problem
        cfg = problem.config
        return cls(
            x=ekf.x,
            P=ekf.P,
            k=ekf.k,
            u_hold=held_input(problem.imu_measured, ekf.k),
            landmarks=problem.landmarks,
            R_landmark=problem.R_landmark,
            dt=cfg.dt,
            accel_sigma=cfg.accel_sigma,
            gyro_sigma=cfg.gyro_sigma,
            objective=env.objective,
        )

    def copy(self) -> LandmarkForecast:
        """An independent copy (estimate and covariance copied)."""
        new = copy.copy(self)
        new.x, new.P = self.x.copy(), self.P.copy()
        return new

    def cost(self) -> float:
        """The env's cost eq. (11) of the current covariance: ``log det P`` or ``det P``."""
        return landmark_cost(self.P, self.objective)

    def predict(self) -> None:
        """``LandmarkEKF.predict`` with the held IMU sample; ``k += 1``."""
        F, G = propagation_jacobians(self.x, self.u_hold, self.dt)
        _, self.P = kf_predict(self.x, self.P, F, process_noise(G, *self.sigmas))
        self.x = propagate(self.x, self.u_hold, self.dt)  # x <- f(x, u)
        self.k += 1

    def jacobians(self) -> FloatArray:
        """(N, 2, 9) angle Jacobians of every landmark at the forecast estimate."""
        return measurement_jacobian(self.x, self.landmarks)

    def whitened(self, H: FloatArray) -> FloatArray:
        """``R^-1/2 H`` (N, 2, 9): the pool of the selection solvers."""
        return whiten(H, np.broadcast_to(self.R_landmark, (H.shape[0], 2, 2)))

    def update(self, selection: Any, H: FloatArray) -> None:
        """Covariance of ``LandmarkEKF.update`` with the selected rows of ``H`` (Joseph form)."""
        idx = np.asarray(selection, dtype=np.intp)
        if idx.size == 0:
            return
        H2 = H[idx].reshape(-1, STATE_DIM)  # (2K, 9)
        if idx.size not in self._R:
            self._R[idx.size] = np.kron(np.eye(idx.size), self.R_landmark).astype(np.float64)
        R = self._R[idx.size]
        self.P = kf_update(self.x, self.P, H2 @ self.x, H2, R, validate=False).P
