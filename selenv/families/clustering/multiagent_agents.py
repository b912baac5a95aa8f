"""Multi-agent policies for the PettingZoo module ``selenv.multiagent.receiver_clustering_v1``.

* ``stay``: every receiver keeps its cluster.
* ``random``: uniform over each receiver's mask.
* ``greedy``: the single-agent ``greedy``'s best improving edit, carried out by the receivers
  concerned.

``greedy`` (every ``every`` steps, like :class:`~selenv.families.clustering.agents.GreedyMoveAgent`)
costs the edits of :func:`~selenv.families.clustering.env.edit_mask` with
:func:`~selenv.families.clustering.env.edit_cost_changes` and plays the best if it lowers
``J``: for a move the mover answers the target label (another receiver's label, or the unused
label ``m`` for a new singleton), for a swap both receivers answer each other's label, everyone
else stays. Only edits that the env's resolution rule
(:func:`~selenv.multiagent.receiver_clustering_v1.resolve_moves`) carries out whatever the
visiting order are offered: a move is always accepted (its target has room and nobody else
moves), a swap only when **both** clusters have room. A swap between two full clusters would
be rejected for both receivers (each target is full when visited), and with one full cluster
it would depend on the seeded order (only half of it may happen), so such swaps are left out;
the single-agent greedy can play them, this one cannot.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from selenv.agents.base import AgentSpec, register_agent
from selenv.agents.multiagent import CLUSTERING_MODULE, MultiAgentPolicy
from selenv.families.clustering.env import apply_edit, edit_cost_changes, edit_mask
from selenv.families.clustering.labels import check_int

__all__ = ["ClusteringGreedyPolicy", "StayPolicy"]


def _own_label(obs: dict[str, np.ndarray]) -> int:
    return int(obs["assignment"][int(np.argmax(obs["self"]))])


class StayPolicy(MultiAgentPolicy):
    """Every receiver answers its own label: the initial clustering is kept all episode."""

    name = "stay"

    def act(self, observations: dict[str, Any], infos: dict[str, Any]) -> dict[str, Any]:
        """Each receiver's current label."""
        return {a: _own_label(observations[a]) for a in self.env.agents}


class ClusteringGreedyPolicy(MultiAgentPolicy):
    """The single-agent greedy edit, carried out by the receivers concerned (module docstring).

    Args:
        every: steps between searches (everyone stays in between).
        swaps: include the swaps the resolution rule always carries out.
    """

    name = "greedy"

    def __init__(self, every: int = 5, swaps: bool = True) -> None:
        self.every = check_int(every, "every", 1)
        self.swaps = swaps

    def allowed_edits(self, labels: np.ndarray, max_size: int) -> np.ndarray:
        """Edits (:func:`edit_mask` numbering) that ``resolve_moves`` always carries out."""
        n = labels.size
        mask = edit_mask(labels, max_size)
        iu, ju = np.triu_indices(n, k=1)
        room = np.bincount(labels, minlength=n)[labels] < max_size  # receiver's cluster has room
        mask[1 + n * n :] &= self.swaps & room[iu] & room[ju]
        return np.flatnonzero(mask[1:]) + 1

    def act(self, observations: dict[str, Any], infos: dict[str, Any]) -> dict[str, Any]:
        """Targets that realise the best improving edit (everyone stays if none improves)."""
        env = self.env
        if env.bank.k % self.every != 0:
            return best_improving_targets(env, np.zeros(0, dtype=np.int64))
        return best_improving_targets(env, self.allowed_edits(env.bank.labels, env.max_size))


def best_improving_targets(env: Any, edits: np.ndarray) -> dict[str, int]:
    """Each live agent's target cluster after the best improving edit among ``edits``.

    ``edits`` (shape ``(m,)``, :func:`edit_mask` numbering) are costed together by
    :func:`edit_cost_changes` (the change ``dJ`` of the Algorithm 1 cost, eq. (10) of Greiff
    et al. 2022, now); the lowest is applied when ``dJ < 0``, else everyone stays.
    """
    bank = env.bank
    labels = bank.labels
    targets = labels
    if edits.size:
        d = edit_cost_changes(bank, edits)
        j = int(np.argmin(d))
        if d[j] < 0.0:
            targets = apply_edit(labels, int(edits[j]))
    index = {a: i for i, a in enumerate(env.possible_agents)}
    return {a: int(targets[index[a]]) for a in env.agents}


_CL = (CLUSTERING_MODULE,)
register_agent(AgentSpec("stay", _CL, StayPolicy, "every receiver keeps its cluster"))

register_agent(
    AgentSpec(
        "greedy",
        _CL,
        ClusteringGreedyPolicy,
        "single-agent greedy's best move/swap, by the receivers concerned",
    )
)
