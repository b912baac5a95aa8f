"""Covariance forecast of the cooperative-localization filters for ``rollout``.

What a forecast may use (the current estimate and covariance, the models, the noise statistics,
the measurement schedule and the held last input) and never uses (the true state, future inputs,
noise realisations) is stated in :mod:`selenv.agents.rollout`; each step reuses the scenario's
math (:func:`~selenv.families.cooperative.scenario.fuse_relative`, the models' propagation) and
the objective terms mirror the env's ``info["objective"]`` (tested equal).
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from selenv.agents.rollout import held_input
from selenv.core.kalman import kf_update
from selenv.core.linalg import FloatArray
from selenv.families.cooperative.env import agent_objective
from selenv.families.cooperative.models import beacon_range, relative_bearing, relative_range
from selenv.families.cooperative.scenario import CLConfig, fuse_relative

__all__ = ["CLForecast"]


class CLForecast:
    """Covariance forecast of a cooperative-localization team (:class:`CLSimulation` steps).

    Args:
        config: the scenario's :class:`~selenv.families.cooperative.scenario.CLConfig` (models,
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
            u_hold=held_input(sim.problem.inputs, sim.k),
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
