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

``selenv.multiagent.fim_selection_v0``:

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

``selenv.multiagent.receiver_clustering_v0``:

* ``stay``: every receiver keeps its cluster.
* ``random``: uniform over each receiver's mask.
* ``greedy``: the single-agent ``greedy``'s best improving edit, carried out by the receivers
  concerned.

``greedy`` (every ``every`` steps, like :class:`~selenv.agents.clustering.GreedyMoveAgent`)
costs the edits of :func:`~selenv.envs.receiver_clustering.edit_mask` with
:func:`~selenv.envs.receiver_clustering.edit_cost_changes` and plays the best if it lowers
``J``: for a move the mover answers the target label (another receiver's label, or the unused
label ``m`` for a new singleton), for a swap both receivers answer each other's label, everyone
else stays. Only edits that the env's resolution rule
(:func:`~selenv.multiagent.receiver_clustering_v0.resolve_moves`) carries out whatever the
visiting order are offered: a move is always accepted (its target has room and nobody else
moves), a swap only when **both** clusters have room. A swap between two full clusters would
be rejected for both receivers (each target is full when visited), and with one full cluster
it would depend on the seeded order (only half of it may happen), so such swaps are left out;
the single-agent greedy can play them, this one cannot.
"""

from __future__ import annotations

from abc import abstractmethod
from typing import Any

import numpy as np

from selenv.agents.base import Agent, AgentSpec, register_agent
from selenv.agents.fim import CooperativeGreedyPolicy
from selenv.agents.fim_solvers import (
    Selection,
    partition_greedy_whitened,
    partition_swap_whitened,
)
from selenv.envs.receiver_clustering import apply_edit, edit_cost_changes, edit_mask
from selenv.scenarios.clustering_labels import check_int

__all__ = [
    "CLUSTERING_MODULE",
    "FIM_MODULE",
    "CentralizedFIMPolicy",
    "ClusteringGreedyPolicy",
    "FIMGreedyPolicy",
    "MultiAgentPolicy",
    "RandomMaskedPolicy",
    "StayPolicy",
]

FIM_MODULE = "selenv.multiagent.fim_selection_v0"
CLUSTERING_MODULE = "selenv.multiagent.receiver_clustering_v0"


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


def _mask(observations: dict[str, Any], infos: dict[str, Any], agent: str) -> np.ndarray:
    if "action_mask" in infos.get(agent, {}):
        return np.asarray(infos[agent]["action_mask"], dtype=bool)
    return np.asarray(observations[agent]["action_mask"], dtype=bool)


class RandomMaskedPolicy(MultiAgentPolicy):
    """Each live agent draws uniformly from its own mask, with the policy's seeded generator."""

    name = "random"

    def act(self, observations: dict[str, Any], infos: dict[str, Any]) -> dict[str, Any]:
        """A uniform allowed action per live agent (agents in ``env.agents`` order)."""
        return {
            a: int(self.rng.choice(np.flatnonzero(_mask(observations, infos, a))))
            for a in self.env.agents
        }


# -- fim_selection_v0 ---------------------------------------------------------------------------
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


# -- receiver_clustering_v0 ---------------------------------------------------------------------
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
        bank = env.bank
        labels = bank.labels
        targets = labels.copy()
        if bank.k % self.every == 0:
            edits = self.allowed_edits(labels, env.max_size)
            if edits.size:
                d = edit_cost_changes(bank, edits)
                j = int(np.argmin(d))
                if d[j] < 0.0:
                    targets = apply_edit(labels, int(edits[j]))
        index = {a: i for i, a in enumerate(env.possible_agents)}
        return {a: int(targets[index[a]]) for a in env.agents}


def _centralized(swap: bool) -> Any:
    def factory(**kwargs: Any) -> CentralizedFIMPolicy:
        return CentralizedFIMPolicy(swap=swap, **kwargs)

    return factory


_FIM = (FIM_MODULE,)
_CL = (CLUSTERING_MODULE,)
register_agent(
    AgentSpec("greedy", _FIM, FIMGreedyPolicy, "each acting agent's largest gain (floor)")
)
register_agent(
    AgentSpec("random", (*_FIM, *_CL), RandomMaskedPolicy, "uniform over each agent's mask")
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
# the shared learned policy lives above this layer: a lazy "module:attr" factory
register_agent(
    AgentSpec(
        "ppo",
        _FIM,
        "selenv.learned.rl.marl:make_shared_ppo",
        "shared (parameter-sharing) policy, each agent on its own observation "
        "(checkpoints/fim_marl_ppo.zip)",
    )
)
register_agent(AgentSpec("stay", _CL, StayPolicy, "every receiver keeps its cluster"))
register_agent(
    AgentSpec(
        "greedy",
        _CL,
        ClusteringGreedyPolicy,
        "single-agent greedy's best move/swap, by the receivers concerned",
    )
)
# an RLlib-trained shared module (selenv.learned.rl.rllib_agent, lazy: selenv never imports ray)
for _module in (FIM_MODULE, CLUSTERING_MODULE):
    register_agent(
        AgentSpec(
            "rllib",
            (_module,),
            "selenv.learned.rl.rllib_agent:make_rllib_policy",
            "RLlib-trained shared module on each agent's own candidate view "
            "(rllib:path=runs/rllib_<env>/policy.json; selenv/train/train_rllib_marl.py)",
            kwargs={"env_id": _module},
        )
    )
