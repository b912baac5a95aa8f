"""Multi-agent policies for the PettingZoo module ``selenv.multiagent.fim_selection_v0``.

* ``greedy``: each acting agent takes its largest masked gain in its own observation (the
  env's ``mode`` decides what information that is); the floor.
* ``random``: uniform over each agent's mask.
* ``centralized_greedy`` (reference): one decision-maker with the pooled FIM picks for every
  agent, greedy over the union of the pools under the per-agent budgets
  (:func:`~selenv.agents.fim_solvers.partition_greedy_whitened`).
* ``centralized_swap`` (reference): the same, then swap local search within each pool
  (:func:`~selenv.agents.fim_solvers.partition_swap_whitened`).

The centralised references read ``env.problem`` (``Q0``, ``G``, ``pool(i)``) and
``env.budgets``, what a fusion centre holding every agent's candidates would know, never the
true state. They plan at the first decision of an episode and play the plan through the env:
each acting agent (``infos[agent]["on_turn"]``) plays its next planned pick, so the env's turn
order (cooperative mode: ``agent_0`` spends its whole budget first) is respected; the final
objective is ``f`` of the plan in either mode.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from selenv.agents.base import AgentSpec, register_agent
from selenv.agents.fim_solvers import (
    Selection,
    partition_greedy_whitened,
    partition_swap_whitened,
)
from selenv.agents.multiagent import FIM_MODULE, MultiAgentPolicy
from selenv.families.fim.agents import CooperativeGreedyPolicy

__all__ = ["CentralizedFIMPolicy", "FIMGreedyPolicy"]


class FIMGreedyPolicy(MultiAgentPolicy):
    """Each acting agent takes its largest masked gain (:class:`CooperativeGreedyPolicy`)."""

    name = "greedy"

    def __init__(self) -> None:
        self.policy = CooperativeGreedyPolicy()

    def act(self, observations: dict[str, Any], infos: dict[str, Any]) -> dict[str, Any]:
        """The largest gain of each agent's own observation (waiting agents pass with 0)."""
        return dict(self.policy.act(observations, self.env.agents))


class CentralizedFIMPolicy(MultiAgentPolicy):
    """A fusion centre that plans every agent's picks on the pooled FIM (module docstring).

    Args:
        swap: also run the swap local search within each pool (``centralized_swap``).
    """

    def __init__(self, swap: bool = False) -> None:
        self.swap = swap
        self.name = "centralized_swap" if swap else "centralized_greedy"  # type: ignore[misc]

    def reset(self, env: Any, seed: int | None = None) -> None:  # noqa: D102
        super().reset(env, seed)
        self.queues: dict[str, list[int]] | None = None
        self.selection: Selection | None = None

    def plan(self) -> dict[str, list[int]]:
        """Each agent's picks, as indices into its own pool, in the order they were chosen."""
        env = self.env
        problem = env.problem
        agents = list(env.possible_agents)
        pools = [problem.pool(i) for i in range(len(agents))]
        budgets = [int(env.budgets[a]) for a in agents]
        solve = partition_swap_whitened if self.swap else partition_greedy_whitened
        self.selection = solve(problem.Q0, problem.G, pools, budgets)
        queues: dict[str, list[int]] = {a: [] for a in agents}
        for k in self.selection.indices:
            i = next(i for i, pool in enumerate(pools) if k in pool)
            queues[agents[i]].append(int(np.searchsorted(pools[i], k)))
        return queues

    def act(self, observations: dict[str, Any], infos: dict[str, Any]) -> dict[str, Any]:
        """Each acting agent's next planned pick; waiting agents pass with 0."""
        if self.queues is None:
            self.queues = self.plan()
        actions: dict[str, Any] = {}
        for a in self.env.agents:
            if not infos[a]["on_turn"]:
                actions[a] = 0
            elif not self.queues[a]:
                raise RuntimeError(f"{self.name}: {a} is on turn but its plan is spent")
            else:
                actions[a] = self.queues[a].pop(0)
        return actions


# -- receiver_clustering_v1 ---------------------------------------------------------------------


def _centralized(swap: bool) -> Any:
    def factory(**kwargs: Any) -> CentralizedFIMPolicy:
        return CentralizedFIMPolicy(swap=swap, **kwargs)

    return factory


_FIM = (FIM_MODULE,)
register_agent(
    AgentSpec("greedy", _FIM, FIMGreedyPolicy, "each acting agent's largest gain (floor)")
)

register_agent(
    AgentSpec(
        "centralized_greedy",
        _FIM,
        _centralized(False),
        "reference: greedy on the pooled FIM under per-agent budgets",
    )
)

register_agent(
    AgentSpec(
        "centralized_swap",
        _FIM,
        _centralized(True),
        "reference: centralized_greedy + swap search within each pool",
    )
)
