"""Agent motion and relative measurements for cooperative localization (Chen & Kia 2022).

Two agent models share one interface (:class:`AgentModel`):

* ``"ins"``: the 9-state strapdown model of :mod:`selenv.families.landmarks.models`
  (position, velocity, Euler attitude; input = specific force and body rates from a noisy
  IMU). With ``n = 9`` and a scalar range (``n_z = 1``) the learned surrogates see the paper's
  108 features (``2 x 45 + 2 x 9``).
* ``"unicycle"``: ``x = (p_x, p_y, psi)`` (psi from the x axis), input ``(v, omega)`` from noisy
  odometry: ``p+ = p + v dt (cos psi, sin psi)``, ``psi+ = psi + omega dt``.

Measurements: range to a beacon ``|p - b|``, relative range ``|p_i - p_j|`` and (optionally)
relative bearing ``atan2(dy, dx)`` (ENU / x-y frame), each with Jacobians w.r.t. both agents.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selenv.core.linalg import FloatArray
from selenv.families.landmarks import models as lm

__all__ = [
    "MODELS",
    "AgentModel",
    "beacon_range",
    "relative_bearing",
    "relative_range",
]


@dataclass(frozen=True)
class AgentModel:
    """One agent model: state size, position slice, propagation, Jacobians and process noise.

    Attributes:
        name: ``"ins"`` or ``"unicycle"``.
        n: state dimension.
        dim: positional dimension measured by ranges (3 for ins, 2 for unicycle).
        n_input: input dimension.
    """

    name: str
    n: int
    dim: int
    n_input: int

    def propagate(self, x: FloatArray, u: FloatArray, dt: float) -> FloatArray:
        """``x+ = f(x, u)`` (n,)."""
        if self.name == "ins":
            return lm.propagate(x, u, dt)
        px, py, psi = x
        v, w = u
        return np.array([px + v * dt * np.cos(psi), py + v * dt * np.sin(psi), psi + w * dt])

    def jacobians(
        self, x: FloatArray, u: FloatArray, dt: float, input_sigma: tuple[float, float]
    ) -> tuple[FloatArray, FloatArray]:
        """``(F, Q)``: state Jacobian and process noise ``G diag(sigma^2) G^T`` at ``(x, u)``.

        ``input_sigma``: (accelerometer, gyro) for ins, (speed, turn rate) for unicycle.
        """
        if self.name == "ins":
            F, G = lm.propagation_jacobians(x, u, dt)
            return F, lm.process_noise(G, *input_sigma)
        _, _, psi = x
        v, _ = u
        c, s = np.cos(psi), np.sin(psi)
        F = np.array([[1.0, 0.0, -v * dt * s], [0.0, 1.0, v * dt * c], [0.0, 0.0, 1.0]])
        G = np.array([[dt * c, 0.0], [dt * s, 0.0], [0.0, dt]])
        Gs = G * np.asarray(input_sigma, dtype=float)
        Q = Gs @ Gs.T
        return F, 0.5 * (Q + Q.T)

    def propagate_with_jacobians(
        self, x: FloatArray, u: FloatArray, dt: float, input_sigma: tuple[float, float]
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(x+, F, Q)``: :meth:`propagate` and :meth:`jacobians` at one ``(x, u)``.

        The same values bit for bit; the ins model forms the attitude terms once.
        """
        if self.name == "ins":
            x_new, F, G = lm.propagate_with_jacobians(x, u, dt)
            return x_new, F, lm.process_noise(G, *input_sigma)
        F, Q = self.jacobians(x, u, dt, input_sigma)
        return self.propagate(x, u, dt), F, Q

    def position(self, x: FloatArray) -> FloatArray:
        """The measured position (dim,)."""
        return np.asarray(x[: self.dim], dtype=np.float64)


MODELS: dict[str, AgentModel] = {
    "ins": AgentModel("ins", 9, 3, 6),
    "unicycle": AgentModel("unicycle", 3, 2, 2),
}


def beacon_range(model: AgentModel, x: FloatArray, beacon: FloatArray) -> tuple[float, FloatArray]:
    """Range to a beacon ``|p - b|`` and its Jacobian (1, n)."""
    d = model.position(x) - beacon[: model.dim]
    r = float(np.linalg.norm(d))
    H = np.zeros((1, model.n))
    H[0, : model.dim] = d / r
    return r, H


def relative_range(
    model: AgentModel, x_i: FloatArray, x_j: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``z = |p_i - p_j|`` (1,) with ``H_i`` (1, n) and ``H_j = -H_i`` on the position."""
    d = model.position(x_i) - model.position(x_j)
    r = float(np.linalg.norm(d))
    H_i = np.zeros((1, model.n))
    H_i[0, : model.dim] = d / r
    return np.array([r]), H_i, -H_i


def relative_bearing(
    model: AgentModel, x_i: FloatArray, x_j: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Horizontal bearing of ``j`` from ``i``, ``atan2(dy, dx)`` (1,), with its Jacobians."""
    d = model.position(x_j)[:2] - model.position(x_i)[:2]
    q = float(d @ d)
    H_j = np.zeros((1, model.n))
    H_j[0, :2] = np.array([-d[1], d[0]]) / q  # d atan2(dy, dx) / d p_j
    return np.array([np.arctan2(d[1], d[0])]), -H_j, H_j
