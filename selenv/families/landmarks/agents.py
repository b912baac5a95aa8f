"""Agents for ``selenv/LandmarkSelection-v1`` (Soubaras & Chahbazian 2023 and baselines).

The env exposes the same oracle view as ``FIMSelection-v1`` (``state``: the log-det gain state
of the current filter step with prior information ``P_pred^-1``; ``budget_left``: picks left in
the step), so the log-det subset solvers apply unchanged: each agent plans the ``K`` landmarks
of a filter step at its first pick and plays them.

| name | what |
|---|---|
| ``brute_force`` | Algorithm 1: every ``C(N, K)`` subset, vectorised (optimal for one step) |
| ``vns`` | Algorithm 2: VNS warm-started from the previous step's selection |
| ``greedy`` | block greedy on the log-det gains |
| ``swap`` | greedy + swap local search |
| ``random`` | uniform random landmarks |
| ``all`` | every landmark (needs ``k = n_landmarks``): the lower bound |

All of them are myopic (they minimise eq. 11 of the current step, eq. 14), as in the paper.
With ``objective="trace"`` (or ``"max_eig"``) the env exposes that ``solver_objective`` and
``interest = (0, 1, 2)``, and every solver agent (VNS included) then minimises the one-step
position MSE ``tr(P_post[:3, :3])`` (or ``lambda_max(P_post[:3, :3])``) instead
(:func:`~selenv.families.fim.agents.env_objective`).
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np

from selenv.agents.base import AgentSpec, PlanAgent, register_agent
from selenv.agents.fim_solvers import (
    MAX_BRUTE_FORCE_SUBSETS,
    brute_force_whitened,
    greedy_whitened,
    swap_whitened,
)
from selenv.agents.vns import DEFAULT_M, vns_whitened
from selenv.families.fim.agents import FIMSolverAgent, RandomMaskedAgent, env_objective

__all__ = ["LANDMARK_ENV_ID", "AllLandmarksAgent", "VNSAgent"]

LANDMARK_ENV_ID = "selenv/LandmarkSelection-v1"


class VNSAgent(PlanAgent):
    """Algorithm 2 each filter step, warm-started from the previous step's selection.

    The first step starts from brute force when ``C(N, K)`` is within its size guard (the
    paper's suggestion), else from greedy.

    Args:
        l_max: largest neighbourhood (default ``min(K, N - K, len(m_l))``).
        m_l: ``M_1, M_2, ...`` draws without improvement before widening.
        batched: see :func:`~selenv.agents.vns.vns_whitened`.
    """

    name = "vns"

    def __init__(
        self, l_max: int | None = None, m_l: tuple[int, ...] = DEFAULT_M, batched: bool = True
    ) -> None:
        self.l_max, self.m_l, self.batched = l_max, tuple(m_l), batched

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:  # noqa: D102
        super().reset(env, seed)
        self._prev: list[int] | None = None

    def plan(self, obs: Any, info: dict[str, Any]) -> list[int]:
        """VNS on the landmarks not yet picked in this step, for the picks left."""
        env = self.env.unwrapped
        state = env.state  # type: ignore[attr-defined]
        budget = int(env.budget_left)  # type: ignore[attr-defined]
        remaining = np.flatnonzero(~state.selected)
        prior, G = state.information, state.G[remaining]
        obj = env_objective(env)  # {} for log det: the calls are unchanged
        position = {int(r): i for i, r in enumerate(remaining)}
        warm = [position[j] for j in (self._prev or []) if j in position][:budget]
        if len(warm) < budget:
            if self._prev is None and math.comb(remaining.size, budget) <= MAX_BRUTE_FORCE_SUBSETS:
                warm = list(brute_force_whitened(prior, G, budget, **obj).indices)
            else:
                picks = greedy_whitened(prior, G, budget, **obj).indices
                extra = [i for i in picks if i not in warm]
                warm = warm + extra[: budget - len(warm)]
        sel = vns_whitened(
            prior,
            G,
            budget,
            initial=warm,
            l_max=self.l_max,
            m_l=self.m_l,
            batched=self.batched,
            rng=self.rng,
            **obj,
        )
        plan = [int(remaining[i]) for i in sel.indices]
        self._prev = [*(int(j) for j in np.flatnonzero(state.selected)), *plan]
        return plan


class AllLandmarksAgent(PlanAgent):
    """Every landmark each step: the lower bound of the cost (needs ``k = n_landmarks``)."""

    name = "all"

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:
        """Refuse (``ValueError``) unless the env lets every landmark be picked."""
        super().reset(env, seed)
        base = env.unwrapped
        if getattr(base, "k", None) != getattr(base, "n", None):
            raise ValueError(
                f"agent 'all' uses every landmark: it needs k = n_landmarks = "
                f"{getattr(base, 'n', '?')}, the env has k = {getattr(base, 'k', '?')}"
            )

    def plan(self, obs: Any, info: dict[str, Any]) -> list[int]:
        """The landmarks not yet picked."""
        return [int(i) for i in np.flatnonzero(np.asarray(info["action_mask"], dtype=bool))]


def _solver(solver: Any, name: str) -> Any:
    def factory(**kwargs: Any) -> FIMSolverAgent:
        return FIMSolverAgent(solver, name, **kwargs)

    return factory


_ID = (LANDMARK_ENV_ID,)
register_agent(
    AgentSpec(
        "brute_force",
        _ID,
        _solver(brute_force_whitened, "brute_force"),
        "Algorithm 1: all C(N, K) subsets (optimal per step)",
    )
)
register_agent(AgentSpec("vns", _ID, VNSAgent, "Algorithm 2: VNS warm-started each step"))
register_agent(AgentSpec("greedy", _ID, _solver(greedy_whitened, "greedy"), "block greedy"))
register_agent(AgentSpec("swap", _ID, _solver(swap_whitened, "swap"), "greedy + swap search"))
register_agent(AgentSpec("random", _ID, RandomMaskedAgent, "uniform random landmarks"))
register_agent(AgentSpec("all", _ID, AllLandmarksAgent, "every landmark (needs k = N)"))
