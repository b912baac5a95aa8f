"""What a decision-maker can forecast of the filters: the models behind the ``rollout`` agents.

A rollout (:mod:`selenv.agents.rollout`) scores a decision by simulating the filters ahead. A
forecast is built from what is known at decision time and nothing else:

* the current estimate ``x_hat`` and covariance ``P`` (copies: the env is never touched);
* the models: the dynamics and their Jacobians, the measurement Jacobians evaluated at the
  *predicted* estimate, the noise covariances (statistics, never realisations), the landmark
  and beacon geometry, and the measurement schedule (``relative_every``, ``beacon_every``,
  ``zupt_every``: design parameters of the scenario);
* the **last measured input** (IMU or odometry sample), **held** over the lookahead. The next
  inputs are not known at decision time; holding the last one continues the current manoeuvre,
  a good forecast over a lookahead of a second or so (the truth's guidance varies slowly).

Never used: the true state, future inputs, noise realisations, measurement values. The
covariance recursions of the KF / EKF / CI / DMV / PECMV updates do not depend on measurement
values, so a forecast runs on ``(x_hat propagated by the models with no correction, P)``: every
update is applied with a zero innovation (``z = h(x_hat)``), which leaves ``x_hat`` unchanged.

Each step of a forecast reuses the scenario's math (:func:`~selenv.core.kalman.kf_predict` /
:func:`~selenv.core.kalman.kf_update`, :func:`~selenv.scenarios.cooperative.fuse_relative`, the
models' propagation and Jacobians); the tests check each step against the simulator's own.
The objective terms mirror the envs' ``info["objective"]`` (tested equal).
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from selenv.core.information import whiten
from selenv.core.kalman import kf_predict, kf_update
from selenv.core.linalg import FloatArray
from selenv.envs.cl_scheduling import agent_objective
from selenv.envs.landmark_selection import landmark_cost
from selenv.scenarios.cooperative import CLConfig, fuse_relative
from selenv.scenarios.cooperative_models import beacon_range, relative_bearing, relative_range
from selenv.scenarios.landmark_models import (
    STATE_DIM,
    measurement_jacobian,
    process_noise,
    propagate,
    propagation_jacobians,
)

__all__ = ["CLForecast", "LandmarkForecast"]


def _held_input(inputs: FloatArray, k: int) -> FloatArray:
    """The last input used by the filter (sample ``k - 1``), copied: the held forecast input."""
    if k < 1:
        raise ValueError("a forecast needs one propagation done (the held input), got k = 0")
    return np.array(inputs[k - 1], dtype=np.float64)


class CLForecast:
    """Covariance forecast of a cooperative-localization team (:class:`CLSimulation` steps).

    Args:
        config: the scenario's :class:`~selenv.scenarios.cooperative.CLConfig` (models,
            schedule, noise statistics, beacon geometry).
        fusion: the env's fusion method for relative measurements.
        objective: ``"logdet"`` (sum of ``log det P_i``) or ``"trace"`` (sum of the horizontal
            position variances), as in ``CLSchedulingEnv``.
        x: (A, n) current estimates; P: (A, n, n) covariances; k: steps done.
        u_hold: (A, n_input) the last measured inputs, held over the forecast.
        R_rel: (m, m) relative-measurement noise covariance.
    """

    def __init__(
        self,
        *,
        config: CLConfig,
        fusion: str,
        objective: str,
        x: FloatArray,
        P: FloatArray,
        k: int,
        u_hold: FloatArray,
        R_rel: FloatArray,
    ) -> None:
        self.config, self.fusion, self.objective = config, fusion, objective
        self.model = config.agent_model
        self.x = np.array(x, dtype=np.float64)
        self.P = np.array(P, dtype=np.float64)
        self.k = int(k)
        self.u_hold = np.array(u_hold, dtype=np.float64)
        self.R_rel = np.array(R_rel, dtype=np.float64)
        self.pairs = config.relative_pairs
        self.beacons = np.asarray(config.beacons, dtype=np.float64).reshape(-1, 3)
        self._zero = np.zeros(self.R_rel.shape[0])

    @classmethod
    def from_env(cls, env: Any) -> CLForecast:
        """Forecast from a ``CLSchedulingEnv``'s current estimate (copied) and last input."""
        sim = env.sim
        return cls(
            config=sim.problem.config,
            fusion=sim.fusion,
            objective=env.objective,
            x=sim.x,
            P=sim.P,
            k=sim.k,
            u_hold=_held_input(sim.problem.inputs, sim.k),
            R_rel=sim.R_rel,
        )

    def copy(self) -> CLForecast:
        """An independent copy (estimates and covariances copied)."""
        new = copy.copy(self)
        new.x, new.P = self.x.copy(), self.P.copy()
        return new

    # -- objective ---------------------------------------------------------------------------
    def cost(self, P_i: FloatArray) -> float:
        """One agent's term of the env's objective (``log det P_i`` or ``tr P_i[:2, :2]``)."""
        return float(agent_objective(P_i, self.objective))

    def objective_value(self) -> float:
        """The env's objective (sum over agents) on the forecast covariances."""
        return sum(self.cost(P_i) for P_i in self.P)

    # -- transition between filter steps (CLSimulation.predict, zupt_updates, beacon_updates) --
    def predict(self) -> None:
        """EKF prediction of every agent with its held input; ``k += 1``."""
        cfg = self.config
        for i in range(cfg.n_agents):
            u = self.u_hold[i]
            F, Q = self.model.jacobians(self.x[i], u, cfg.dt, cfg.input_sigma_of(i))
            self.x[i] = self.model.propagate(self.x[i], u, cfg.dt)  # x <- f(x, u)
            P = F @ self.P[i] @ F.T + Q  # P <- F P F^T + Q
            self.P[i] = 0.5 * (P + P.T)
        self.k += 1

    def _update(self, i: int, H: FloatArray, R: FloatArray) -> None:
        """Covariance of a Kalman update of agent ``i`` (zero innovation: ``x`` unchanged)."""
        self.P[i] = kf_update(self.x[i], self.P[i], H @ self.x[i], H, R, validate=False).P

    def zupt_updates(self) -> None:
        """Velocity pseudo-measurements of every ins agent, on the ``zupt_every`` schedule."""
        cfg = self.config
        if cfg.model != "ins" or cfg.zupt_every is None or self.k % cfg.zupt_every:
            return
        H = np.zeros((3, self.model.n))
        H[:, 3:6] = np.eye(3)
        R = cfg.zupt_sigma**2 * np.eye(3)
        for i in range(cfg.n_agents):
            self._update(i, H, R)

    def beacon_updates(self) -> None:
        """Range updates of the beacon agents (``H`` at the forecast), every ``beacon_every``."""
        cfg = self.config
        if self.fusion == "dead_reckoning" or self.k % cfg.beacon_every:
            return
        R = np.array([[cfg.range_sigma**2]])
        for i in cfg.beacon_agents:
            for beacon in self.beacons:
                self._update(i, beacon_range(self.model, self.x[i], beacon)[1], R)

    def advance(self) -> None:
        """The env's transition to the next filter step: predict, ZUPT and beacon updates."""
        self.predict()
        self.zupt_updates()
        self.beacon_updates()

    # -- relative measurements ---------------------------------------------------------------
    def available(self) -> list[int]:
        """Pairs measured at this step (the ``relative_every`` schedule)."""
        return [] if self.k % self.config.relative_every else list(range(len(self.pairs)))

    def relative_jacobians(self, p: int) -> tuple[FloatArray, FloatArray]:
        """``(H_i, H_j)`` of relative measurement ``p`` at the forecast estimates."""
        i, j = self.pairs[p]
        _, H_i, H_j = relative_range(self.model, self.x[i], self.x[j])
        if self.config.bearing_sigma_deg is not None:
            _, Hb_i, Hb_j = relative_bearing(self.model, self.x[i], self.x[j])
            H_i, H_j = np.vstack([H_i, Hb_i]), np.vstack([H_j, Hb_j])
        return H_i, H_j

    def preview(self, p: int) -> FloatArray:
        """Agent ``i``'s covariance if pair ``p`` were fused now (no change to the forecast)."""
        i, j = self.pairs[p]
        H_i, H_j = self.relative_jacobians(p)
        return fuse_relative(
            self.fusion, self.x[i], self.P[i], self.P[j], H_i, H_j, self.R_rel, self._zero
        )[1]

    def gain(self, p: int) -> float:
        """Drop of the objective if pair ``p`` were fused now (``CLSchedulingEnv.preview_gain``)."""
        i = self.pairs[p][0]
        return self.cost(self.P[i]) - self.cost(self.preview(p))

    def relative_update(self, p: int) -> None:
        """Fuse pair ``p`` into agent ``i``'s covariance."""
        self.P[self.pairs[p][0]] = self.preview(p)


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
            u_hold=_held_input(problem.imu_measured, ekf.k),
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
