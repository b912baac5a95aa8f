"""Multi-agent policies for the PettingZoo modules of :mod:`selenv.multiagent`.

A :class:`MultiAgentPolicy` makes one joint decision per step of a ``ParallelEnv``::

    policy = selenv.agents.make("greedy", "selenv.multiagent.fim_selection_v0")
    observations, infos = env.reset(seed=0)
    policy.reset(env, seed=0)
    while env.agents:
        observations, rewards, terms, truncs, infos = env.step(policy.act(observations, infos))

``act`` returns an action for every live agent (``env.agents``). Policies share the agent
registry (:func:`~selenv.agents.base.register_agent`), the env ids being the module names;
``selenv bench selenv.multiagent.fim_selection_v0`` runs them (:mod:`selenv.bench.multiagent`).

The family policies are in ``selenv.families.fim.multiagent_agents`` and
``selenv.families.clustering.multiagent_agents``; this module holds the protocol and
``random``, which :mod:`selenv.agents` registers (with ``rllib``) for every family's PettingZoo
module.
"""

from __future__ import annotations

from abc import abstractmethod
from typing import Any

import numpy as np

from selenv.agents.base import Agent
from selenv.families import clustering, fim

__all__ = [
    "CLUSTERING_MODULE",
    "FIM_MODULE",
    "MultiAgentPolicy",
    "RandomMaskedPolicy",
    "action_mask_of",
]

#: the current PettingZoo modules of the two multi-agent families (from their records)
FIM_MODULE: str = str(fim.SPEC.multiagent_module)
CLUSTERING_MODULE: str = str(clustering.SPEC.multiagent_module)


class MultiAgentPolicy(Agent):
    """One joint decision per step of a PettingZoo ``ParallelEnv`` (module docstring).

    ``reset(env, seed)`` stores the env (``self.env``) and a generator seeded with ``seed``
    (``self.rng``); ``act(observations, infos)`` maps the env's per-agent dicts to an action
    for every live agent.
    """

    #: the ParallelEnv of the episode (set by :meth:`reset`)
    env: Any

    def reset(self, env: Any, seed: int | None = None) -> None:
        """Start an episode in ``env`` (already reset); ``seed`` seeds ``self.rng``."""
        self.env = env
        self.rng = np.random.default_rng(seed)

    @abstractmethod
    def act(self, observations: dict[str, Any], infos: dict[str, Any]) -> dict[str, Any]:
        """Return ``{agent: action}`` for every live agent."""


def action_mask_of(observations: dict[str, Any], infos: dict[str, Any], agent: str) -> np.ndarray:
    """``agent``'s mask from its info (preferred) or its observation."""
    if "action_mask" in infos.get(agent, {}):
        return np.asarray(infos[agent]["action_mask"], dtype=bool)
    return np.asarray(observations[agent]["action_mask"], dtype=bool)


class RandomMaskedPolicy(MultiAgentPolicy):
    """Each live agent draws uniformly from its own mask, with the policy's seeded generator."""

    name = "random"

    def act(self, observations: dict[str, Any], infos: dict[str, Any]) -> dict[str, Any]:
        """A uniform allowed action per live agent (agents in ``env.agents`` order)."""
        return {
            a: int(self.rng.choice(np.flatnonzero(action_mask_of(observations, infos, a))))
            for a in self.env.agents
        }


# -- fim_selection_v0 ---------------------------------------------------------------------------
