"""Agents for ``selenv/FIMSelection-v1``: the classic selection heuristics as env agents.

Each agent plans on the env's oracle view (the current information and the whitened pool) with
the plain solvers of :mod:`selenv.agents.fim_solvers`, then plays the plan one pick per step.
Picks already made in the episode become part of the prior (``Q0 <- FIM(selected)``), so an
agent can also take over in the middle of an episode.

The solvers optimise the env's objective (:func:`env_objective`: ``env.solver_objective`` and
``env.interest``, e.g. ``FIMSelection-v1(objective="trace")`` scores the target position), so
``selenv bench ... --env-kwargs '{"objective": "trace"}'`` runs greedy, swap and brute force
on the trace; ``lazy_greedy`` refuses a non-log-det objective (it needs submodularity).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from selenv.agents.base import AgentSpec, PlanAgent, register_agent
from selenv.agents.fim_exact import DEFAULT_NODE_LIMIT, branch_and_bound_whitened
from selenv.agents.fim_solvers import (
    MAX_BRUTE_FORCE_SUBSETS,
    Selection,
    brute_force_whitened,
    greedy_whitened,
    lazy_greedy_whitened,
    swap_whitened,
)
from selenv.core.objectives import check_objective

__all__ = [
    "FIM_ENV_ID",
    "CooperativeGreedyPolicy",
    "FIMSolverAgent",
    "RandomMaskedAgent",
    "env_objective",
]

FIM_ENV_ID = "selenv/FIMSelection-v1"


def env_objective(env: Any) -> dict[str, Any]:
    """Solver keywords for the objective of ``env`` (unwrapped): ``{}`` for log det.

    ``{"objective": name, "interest": indices}`` from ``env.solver_objective`` and
    ``env.interest`` otherwise; an env without them is log det.
    """
    name = getattr(env, "solver_objective", "logdet")
    if name == "logdet":
        return {}  # the solvers' default: calls are exactly what they were before objectives
    return {"objective": name, "interest": getattr(env, "interest", None)}


class FIMSolverAgent(PlanAgent):
    """Plays the selection a solver computes on the remaining pool and the remaining budget.

    Args:
        solver: ``(Q0, G, budget, **solver_kwargs) -> Selection`` on a whitened pool.
        name: registry name.
        solver_kwargs: extra keyword arguments of the solver.
    """

    def __init__(
        self,
        solver: Callable[..., Selection],
        name: str,
        **solver_kwargs: Any,
    ) -> None:
        try:  # the solver's options are checked now, not at the first decision
            inspect.signature(solver).bind(None, None, 1, **solver_kwargs)
        except TypeError:
            params = list(inspect.signature(solver).parameters)[3:]
            raise ValueError(
                f"agent {name!r} has no option(s) {sorted(set(solver_kwargs) - set(params))}; "
                f"its options: {', '.join(params) or 'none'}"
            ) from None
        if "objective" in solver_kwargs:  # a bad name is refused now, not at the first decision
            check_objective(solver_kwargs["objective"])
        self.solver = solver
        self.name = name  # type: ignore[misc]
        self.solver_kwargs = solver_kwargs

    def plan(self, obs: Any, info: dict[str, Any]) -> list[int]:
        """Solve on the candidates not yet selected, with the current FIM as the prior.

        The solver maximises the env's objective (:func:`env_objective`); with the current
        FIM as the prior, its ``f`` differs from the episode's by a constant.
        """
        env = self.env.unwrapped
        state = env.state  # type: ignore[attr-defined]
        remaining = np.flatnonzero(~state.selected)
        prior = state.information  # Q0 + FIM of the picks so far
        kwargs = {**env_objective(env), **self.solver_kwargs}
        sel = self.solver(prior, state.G[remaining], env.budget_left, **kwargs)  # type: ignore[attr-defined]
        return [int(remaining[k]) for k in sel.indices]


class RandomMaskedAgent(PlanAgent):
    """Uniformly random allowed action, drawn from the agent's seeded generator."""

    name = "random"

    def plan(self, obs: Any, info: dict[str, Any]) -> list[int]:
        """One random allowed action (re-planned every step, so it follows the mask)."""
        mask = np.asarray(info["action_mask"], dtype=bool)
        return [int(self.rng.choice(np.flatnonzero(mask)))]


def _solver_agent(solver: Callable[..., Selection], name: str) -> Callable[..., FIMSolverAgent]:
    def factory(**kwargs: Any) -> FIMSolverAgent:
        return FIMSolverAgent(solver, name, **kwargs)

    return factory


register_agent(AgentSpec("random", (FIM_ENV_ID,), RandomMaskedAgent, "uniform random pick"))
register_agent(
    AgentSpec(
        "greedy",
        (FIM_ENV_ID,),
        _solver_agent(greedy_whitened, "greedy"),
        "Algorithm 1 with rank-one/block updates, >= (1-1/e) OPT",
    )
)
register_agent(
    AgentSpec(
        "lazy_greedy",
        (FIM_ENV_ID,),
        _solver_agent(lazy_greedy_whitened, "lazy_greedy"),
        "greedy with lazy (Minoux) evaluations; same picks",
    )
)
register_agent(
    AgentSpec(
        "swap",
        (FIM_ENV_ID,),
        _solver_agent(swap_whitened, "swap"),
        "greedy + best-improvement swap local search",
    )
)
register_agent(
    AgentSpec(
        "brute_force",
        (FIM_ENV_ID,),
        _solver_agent(brute_force_whitened, "brute_force"),
        f"exhaustive optimum (refuses > {MAX_BRUTE_FORCE_SUBSETS:,} subsets)",
    )
)

register_agent(
    AgentSpec(
        "optimal",
        (FIM_ENV_ID,),
        _solver_agent(branch_and_bound_whitened, "optimal"),
        f"exact optimum by branch and bound (log det), or after {DEFAULT_NODE_LIMIT:,} nodes "
        "the best subset found with a certified gap",
        default=False,
    )
)


class CooperativeGreedyPolicy:
    """Greedy for ``selenv.multiagent.fim_selection_v0``: each agent takes its largest gain.

    The observation's gains are computed against the information the env's ``mode`` gives the
    agent, so this policy is the paper's independent Algorithm 1 in ``mode="independent"`` and
    cooperative greedy (the shared FIM replacing ``Q0``) in ``mode="cooperative"``.
    """

    name = "cooperative_greedy"

    def act(
        self,
        observations: dict[str, dict[str, np.ndarray]],
        agents: Sequence[str] | None = None,
    ) -> dict[str, int]:
        """Map each live agent's observation to its action.

        Args:
            observations: the env's observations (may include agents that just terminated).
            agents: the live agents (``env.agents``); default: every key of ``observations``.
        """
        out = {}
        for agent in observations if agents is None else agents:
            obs = observations[agent]
            gain = np.where(obs["action_mask"].astype(bool), obs["gain"], -np.inf)
            out[agent] = int(np.argmax(gain))
        return out
