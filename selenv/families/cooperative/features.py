"""Per-pair features of a ``CLScheduling`` decision for learned scorers.

A learned scorer ranks stop and the open pairs by ``score(p) = gain(p) + theta . phi(p)``
(stop scores 0): the one-step objective drop that greedy maximises plus a learned correction
from the features below. They describe what a fusion does beyond the position variance the
objective counts, which is what makes ``rollout`` skip fusions greedy takes (DMV's update
scales agent ``i``'s prior by ``1 / w`` before the measurement shrinks it: velocity and
attitude may end up *more* uncertain, and they feed the next steps' position error). Every
feature is computed from the previews greedy computes anyway (agent ``i``'s prior ``P_i``
and posterior ``P_i+`` of each pair) and the team's covariances now; nothing from the true
state or future noise.

| name | definition (pair ``p = (i, j)``, ``tr_a..b``: trace of the ``a:b`` block) |
|---|---|
| ``d_log_vel`` | ``log tr_3..6(P_i+) - log tr_3..6(P_i)`` (velocity) |
| ``d_log_att`` | ``log tr_6..9(P_i+) - log tr_6..9(P_i)`` (attitude) |
| ``d_logdet`` | ``log det P_i+ - log det P_i`` |
| ``rel_gain`` | ``gain / tr_0..2(P_i)`` |
| ``bias`` | 1 (a threshold on fusing at all) |
| ``time_left`` | ``(horizon - k) / horizon`` |
| ``gain_time_left`` | ``gain * time_left`` |
| ``log_pos_ratio`` | ``log tr_0..2(P_i) / tr_0..2(P_j)`` |
| ``log_vel_ratio`` | ``log tr_3..6(P_i) / tr_3..6(P_j)`` |
| ``log_pos_vs_team`` | ``log tr_0..2(P_i) / mean_a tr_0..2(P_a)`` |
| ``since_agent`` | ``min((k - last fusion into i) / 10, 1)`` |
| ``since_any`` | ``min((k - last fusion of any pair) / 10, 1)`` |

The two ``since_*`` features need the history of the episode's fusions: a
:class:`FusionMemory` kept by the agent (fusions at step 0 when it starts mid-episode).
The blocks are those of the ``ins`` model's 9 states (position, velocity, attitude).
"""

from __future__ import annotations

import numpy as np

from selenv.core.linalg import FloatArray

__all__ = ["FEATURE_NAMES", "FusionMemory", "pair_features"]

FEATURE_NAMES: tuple[str, ...] = (
    "d_log_vel",
    "d_log_att",
    "d_logdet",
    "rel_gain",
    "bias",
    "time_left",
    "gain_time_left",
    "log_pos_ratio",
    "log_vel_ratio",
    "log_pos_vs_team",
    "since_agent",
    "since_any",
)
#: steps after which the ``since_*`` features saturate at 1
SINCE_SCALE = 10.0


class FusionMemory:
    """The step of the last fusion into each agent and of the last fusion of any pair.

    Args:
        n_agents: team size ``A``.
        k: the step the memory starts at (fusions before it count as done then).
    """

    def __init__(self, n_agents: int, k: int = 0) -> None:
        self.last = np.full(n_agents, float(k))
        self.any = float(k)

    def record(self, agent: int, k: int) -> None:
        """A fusion into ``agent`` at step ``k``."""
        self.last[agent] = float(k)
        self.any = float(k)


def _block_trace(P: FloatArray, a: int, b: int) -> FloatArray:
    return np.trace(P[..., a:b, a:b], axis1=-2, axis2=-1)


def pair_features(
    P: FloatArray,
    P_new: FloatArray,
    pairs: np.ndarray,
    gains: FloatArray,
    k: int,
    horizon: int,
    memory: FusionMemory,
) -> FloatArray:
    """``(K, F)`` features of the pairs ``pairs`` (K, 2) (module table, ``F = 12``).

    Args:
        P: (A, 9, 9) the team's covariances now.
        P_new: (K, 9, 9) agent ``i``'s posterior of each pair (the previews).
        pairs: (K, 2) the pairs ``(i, j)``.
        gains: (K,) their one-step objective drops.
        k: filter steps done.
        horizon: the episode's filter steps.
        memory: the episode's fusions so far.
    """
    i, j = pairs[:, 0], pairs[:, 1]
    P_i = P[i]
    pos, vel = _block_trace(P, 0, 2), _block_trace(P, 3, 6)
    time_left = (horizon - k) / horizon
    since_agent = np.minimum((k - memory.last[i]) / SINCE_SCALE, 1.0)
    since_any = min((k - memory.any) / SINCE_SCALE, 1.0)
    ones = np.ones_like(gains)
    columns = (
        np.log(_block_trace(P_new, 3, 6) / _block_trace(P_i, 3, 6)),
        np.log(_block_trace(P_new, 6, 9) / _block_trace(P_i, 6, 9)),
        np.linalg.slogdet(P_new)[1] - np.linalg.slogdet(P_i)[1],
        gains / pos[i],
        ones,
        time_left * ones,
        gains * time_left,
        np.log(pos[i] / pos[j]),
        np.log(vel[i] / vel[j]),
        np.log(pos[i] / pos.mean()),
        since_agent,
        since_any * ones,
    )
    return np.stack(columns, axis=1)
