"""``rollout``: non-myopic lookahead references for the landmark and CL scheduling envs.

Rollout (Bertsekas): at each decision, for each of the ``top_k`` candidate actions with the
largest one-step gain, simulate ``horizon`` filter steps ahead with a base heuristic, score the
simulated trajectory by the env's reward summed over it, and commit the best first action. When
the base heuristic's own action is among the candidates, rollout improves on the base policy in
the simulated model (the cost-improvement property; exactly so when the lookahead reaches the
end of the episode).

The simulation runs on a forecast (each family's ``forecast`` module) of what the
decision-maker knows: the current ``x_hat`` and ``P``, the models, the noise statistics and the
measurement schedule, with the last measured input held. It never sees the true state, the
future inputs or any noise realisation, and never changes the env (tested).

* ``selenv/CLScheduling-v1``
  (:class:`~selenv.families.cooperative.rollout.CLRolloutAgent`): a decision is one pair or stop;
  candidates are stop and the ``top_k`` pairs by ``preview_gain``; base ``greedy``; score: the
  drop of the objective (``log det`` or trace) over the trajectory, propagations included.
* ``selenv/LandmarkSelection-v1``
  (:class:`~selenv.families.landmarks.rollout.LandmarkRolloutAgent`): a decision is the K-subset
  of a filter step; candidates are the ``top_k`` K-subsets by one-step gain (and the base's);
  base ``brute_force``; score: minus the cost eq. (11) summed over the filter updates.

``horizon = 0`` scores only the immediate reward: it is the myopic choice (CL: ``greedy``;
landmarks: ``brute_force``'s optimal subset).

A forecast is built from what is known at decision time and nothing else: the current estimate
``x_hat`` and covariance ``P`` (copies: the env is never touched); the models (dynamics and
Jacobians, measurement Jacobians at the *predicted* estimate, noise covariances as statistics,
the landmark and beacon geometry, the measurement schedule); and the **last measured input**,
held over the lookahead (:func:`held_input`). The covariance recursions do not depend on
measurement values, so every update is applied with a zero innovation. The families'
``forecast`` modules reuse their scenario's math, checked step by step against the simulators.

This module holds what the families' rollout agents share: option checks and the held input.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from selenv.core.linalg import FloatArray

__all__ = [
    "ROLLOUT_CEILINGS",
    "best_index",
    "ceiling_option",
    "choice_option",
    "held_input",
    "int_option",
]


#: ceilings of the rollout agents' work-multiplying options (``allow_large=True`` lifts them):
#: a decision simulates ``top_k`` candidates for ``horizon`` steps (``samples`` times)
ROLLOUT_CEILINGS = {
    "top_k": 256,
    "horizon": 10_000,
    "samples": 1_000,
    "every": 1_000_000,
    "max_subsets": 10_000_000,
    "shortlist": 200,
}


def int_option(
    value: Any, name: str, low: int, high: int | None = None, *, allow_large: bool = False
) -> int:
    """``value`` if it is an int in ``[low, high]`` (bools refused), else ``ValueError``.

    ``high`` is a ceiling on work, not a validity bound: the message says how to lift it
    (the agent option ``allow_large=True``), which ``allow_large`` does.
    """
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
        raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    if high is not None and value > high and not allow_large:
        raise ValueError(
            f"{name}={value} is above its ceiling {high:,} (each decision's work grows with "
            f"it); pass allow_large=True (e.g. rollout:{name}={value}:allow_large=true) to run it"
        )
    return int(value)


def ceiling_option(value: Any, name: str, low: int, allow_large: bool) -> int:
    """:func:`int_option` with the ceiling :data:`ROLLOUT_CEILINGS` gives ``name``."""
    return int_option(value, name, low, ROLLOUT_CEILINGS[name], allow_large=allow_large)


def choice_option(value: Any, name: str, allowed: Any) -> str:
    """``value`` if it is one of the strings ``allowed``, else ``ValueError`` naming it."""
    if not isinstance(value, str) or value not in allowed:
        raise ValueError(f"{name} must be one of {tuple(allowed)}, got {value!r}")
    return value


def best_index(scores: list[float]) -> int:
    """Index of the first maximal score (ties keep the earlier candidate)."""
    best = 0
    for c, s in enumerate(scores):
        if s > scores[best]:
            best = c
    return best


def held_input(inputs: FloatArray, k: int) -> FloatArray:
    """The last input used by the filter (sample ``k - 1``), copied: the held forecast input."""
    if k < 1:
        raise ValueError("a forecast needs one propagation done (the held input), got k = 0")
    return np.array(inputs[k - 1], dtype=np.float64)
