"""Time-varying receiver noise for the clustering scenario: open sky / multipath regimes.

Greiff et al. (2022) draw the noise levels once; their model (1b) allows ``R_k``. This module
holds the two-state Markov chain that makes them time-varying
(:class:`MultipathRegimes`, used by :class:`selenv.families.clustering.scenario.ClusteringConfig`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from selenv.core.linalg import FloatArray
from selenv.scenarios.validation import ArgumentTypeError, check_real, describe

__all__ = ["MAX_DEGRADED_FACTOR", "MultipathRegimes"]


#: largest ``degraded_factor`` (noise std multiplier while degraded)
MAX_DEGRADED_FACTOR = 100.0


def _probability(value: Any, name: str, low_open: bool) -> float:
    ok = isinstance(value, float | int | np.floating | np.integer) and not isinstance(
        value, bool | np.bool_
    )
    where = "(0, 1]" if low_open else "[0, 1]"
    if not ok:
        raise ArgumentTypeError(f"{name} must be a probability in {where}, got {describe(value)}")
    v = float(value)
    if not (np.isfinite(v) and (0.0 < v if low_open else 0.0 <= v) and v <= 1.0):
        raise ValueError(f"{name} must be a probability in {where}, got {value!r}")
    return v


@dataclass(frozen=True, kw_only=True)
class MultipathRegimes:
    """Reception conditions of each receiver: a two-state Markov chain (open sky / degraded).

    A Gilbert-Elliott channel, the two-state "good / bad" land-mobile-satellite model of Lutz et
    al. (1991): from one step to the next a receiver in open sky (state 0) enters multipath /
    urban-canyon conditions (state 1) w.p. ``p_enter`` and a degraded one recovers w.p.
    ``p_leave``, independently of the other receivers. Degraded, both its noise levels are
    ``degraded_factor`` times its base levels. Mean sojourns: ``1 / p_enter`` steps in open
    sky, ``1 / p_leave`` degraded; stationary fraction degraded ``p_enter / (p_enter +
    p_leave)``, the distribution the chain starts from.

    Attributes:
        p_enter: per-step probability of entering the degraded state, in [0, 1].
        p_leave: per-step probability of leaving it, in (0, 1].
        degraded_factor: noise std multiplier while degraded, in ``[1, MAX_DEGRADED_FACTOR]``
            (100).
    """

    p_enter: float = 0.01
    p_leave: float = 0.05
    degraded_factor: float = 5.0

    def __post_init__(self) -> None:
        _probability(self.p_enter, "p_enter", low_open=False)
        _probability(self.p_leave, "p_leave", low_open=True)
        check_real(self.degraded_factor, "degraded_factor", 1.0, MAX_DEGRADED_FACTOR)

    @property
    def degraded_fraction(self) -> float:
        """Stationary probability of the degraded state, ``p_enter / (p_enter + p_leave)``."""
        return float(self.p_enter) / (float(self.p_enter) + float(self.p_leave))

    def draw(self, n: int, steps: int, rng: np.random.Generator) -> FloatArray:
        """A path ``(steps + 1, n)`` of 0/1 states from the stationary distribution at step 0."""
        start = (rng.random(n) < self.degraded_fraction).astype(float)
        return self.sample(start, steps, rng)

    def sample(self, start: FloatArray, steps: int, rng: np.random.Generator) -> FloatArray:
        """A path ``(steps + 1, n)`` of 0/1 states from the states ``start`` (n,) at row 0.

        :func:`~selenv.families.clustering.batched.regime_paths` of one chain.
        """
        from selenv.families.clustering.batched import regime_paths

        u = rng.random((int(steps), start.size))
        path = regime_paths(
            np.asarray(start, dtype=float)[None], u[None], float(self.p_enter), float(self.p_leave)
        )
        return path[0]

    def forecast(self, start: FloatArray, steps: int) -> FloatArray:
        """``P(degraded at t | states start at 0)`` for ``t = 1 .. steps``, ``(steps, n)``.

        ``q_t = pi + (q_0 - pi) lam^t`` with ``lam = 1 - p_enter - p_leave`` (two-state chain).
        """
        pi = self.degraded_fraction
        lam = 1.0 - float(self.p_enter) - float(self.p_leave)
        decay = lam ** np.arange(1, int(steps) + 1)[:, None]
        return pi + (np.asarray(start, dtype=float)[None, :] - pi) * decay

    def noise_scale(self, states: FloatArray) -> FloatArray:
        """Std multiplier of each state: 1 (open sky), ``degraded_factor`` (degraded).

        A fraction ``q`` (a forecast's degraded probability) gives the expected variance,
        ``sqrt(1 + q (f^2 - 1))``.
        """
        f = float(self.degraded_factor)
        q = np.asarray(states, dtype=float)
        return np.where(q >= 1.0, f, np.sqrt(1.0 + q * (f * f - 1.0)))
