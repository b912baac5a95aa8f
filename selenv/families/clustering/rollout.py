"""``rollout``: a non-myopic reference for ``selenv/ReceiverClustering-v1`` (Bertsekas rollout).

At each decision (every ``every`` steps, like ``greedy``) the agent costs every allowed local
edit of the current clustering by Algorithm 1 (:func:`~selenv.families.clustering.env.
edit_cost_changes`), keeps the ``top_k`` edits with the lowest one-step cost change and the
no-op, and for each simulates ``horizon`` filter steps ahead: the edit is applied at ``k``, then
the base heuristic (``greedy``: the best improving move or swap, on its schedule ``k % every ==
0``) plays the simulated steps. A candidate's score is the sum of the simulated costs
``J_{k+1} + ... + J_{k+L}`` (the negated env rewards); the best first edit is committed. Since
the greedy's own first edit (or the no-op) is always a candidate, rollout improves on greedy
in the simulated model (the cost-improvement property). ``horizon = 0`` scores a candidate by
its Algorithm 1 cost at ``k``: the myopic ``greedy`` choice.

**What the simulation knows.** The simulation runs on a fork of the env's filter bank
(:meth:`~selenv.families.clustering.filters.ClusterFilterBank.fork`; the env is never
changed) whose noise is a *forecast*: the past and current noise levels (steps ``<= k``) as they
were, and for steps ``> k`` the known Markov statistics of
:class:`~selenv.families.clustering.scenario.MultipathRegimes` started from each receiver's
*current*
regime, never the env's pre-drawn future path:

* ``forecast="mean"`` (default): one deterministic simulation with each receiver's expected
  variance ``sigma^2 (1 + q_t (f^2 - 1))``, ``q_t = P(degraded at k + t | regime at k)``;
* ``forecast="sample"``: ``samples`` regime paths drawn from the agent's own seeded ``rng``,
  the same paths for every candidate (common random numbers), scores averaged.

With fixed noise (``preset="paper"``) the simulation is exact. The horizon is cut at the end
of the episode.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium as gym
import numpy as np

from selenv.agents.base import Agent, AgentSpec, register_agent
from selenv.agents.rollout import ceiling_option
from selenv.families.clustering.agents import CLUSTERING_ENV_ID, best_edit, clustering_env
from selenv.families.clustering.env import apply_edit, edit_cost_changes, edit_mask
from selenv.families.clustering.filters import ClusterFilterBank
from selenv.families.clustering.scenario import ClusteringProblem

__all__ = ["FORECASTS", "ClusteringRolloutAgent"]

FORECASTS = ("mean", "sample")


class ClusteringRolloutAgent(Agent):
    """Rollout with the greedy base heuristic on forecast noise (see the module docstring).

    Args:
        top_k: edits simulated per decision besides the no-op, ``>= 1``.
        horizon: simulated steps ``L``, ``>= 0`` (``0``: the myopic greedy choice).
        every: steps between decisions (and of the simulated greedy), ``>= 1``.
        forecast: ``"mean"`` (expected variance) or ``"sample"`` (sampled regime paths).
        samples: regime paths per decision with ``forecast="sample"``, ``>= 1``.
        allow_large: lift the ceilings on ``top_k``, ``horizon``, ``every`` and ``samples``
            (:data:`~selenv.agents.rollout.ROLLOUT_CEILINGS`).

    Attributes:
        last_scores: ``{edit: score}`` of the last decision (for inspection and tests).
    """

    name = "rollout"

    def __init__(
        self,
        top_k: int = 4,
        horizon: int = 10,
        every: int = 5,
        forecast: str = "mean",
        samples: int = 4,
        allow_large: bool = False,
    ) -> None:
        self.top_k = ceiling_option(top_k, "top_k", 1, allow_large)
        self.horizon = ceiling_option(horizon, "horizon", 0, allow_large)
        self.every = ceiling_option(every, "every", 1, allow_large)
        if not isinstance(forecast, str) or forecast not in FORECASTS:
            raise ValueError(f"forecast must be one of {FORECASTS}, got {forecast!r}")
        self.forecast = forecast
        self.samples = ceiling_option(samples, "samples", 1, allow_large)
        self.last_scores: dict[int, float] = {}

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:  # noqa: D102
        super().reset(env, seed)
        self.base = clustering_env(env, self.name, ("assignment", "edit"))
        self.last_scores = {}

    def act(self, obs: Any, info: dict[str, Any]) -> Any:
        """The best first edit by simulated cost (labels or edit index, per the env's mode)."""
        bank = self.base.bank
        action = self.decide(bank) if bank.k % self.every == 0 else 0
        if self.base.action_mode == "edit":
            return action
        return apply_edit(bank.labels, action)

    # -- the decision -------------------------------------------------------------------------
    def decide(self, bank: ClusterFilterBank) -> int:
        """Edit to play now (0: keep); scores in :attr:`last_scores`."""
        labels = bank.labels
        actions = np.flatnonzero(edit_mask(labels, self.base.max_size)[1:]) + 1
        d = edit_cost_changes(bank, actions)  # one-step Algorithm 1 cost changes
        order = np.argsort(d, kind="stable")[: self.top_k]
        candidates = [0, *(int(a) for a in actions[order])]
        steps = min(self.horizon, self.base.horizon - bank.k)
        if steps <= 0:
            scores = [0.0, *(float(x) for x in d[order])]  # J_k(edit) - J_k: myopic
        else:
            scores = [0.0] * len(candidates)
            for problem in self._forecasts(bank.problem, bank.k, steps):
                for c, action in enumerate(candidates):
                    scores[c] += self._simulate(bank, problem, action, steps)
        self.last_scores = dict(zip(candidates, scores, strict=True))
        return candidates[int(np.argmin(scores))]  # ties: the no-op, then the greedy order

    def _forecasts(
        self, problem: ClusteringProblem, k: int, steps: int
    ) -> list[ClusteringProblem | None]:
        """Problems holding the known noise up to ``k`` and a forecast for ``k+1 .. k+steps``.

        ``None`` (use the env's problem) when the noise is fixed: nothing to forecast.
        """
        model = problem.config.regimes
        if model is None or problem.regimes is None:
            return [None]
        past = problem.regimes[: k + 1]  # steps 0 .. k: known (the current regime included)
        now = past[-1]
        if self.forecast == "mean":
            futures = [model.forecast(now, steps)]
        else:
            futures = [model.sample(now, steps, self.rng)[1:] for _ in range(self.samples)]
        return [
            dataclasses.replace(problem, regimes=np.concatenate([past, future]))
            for future in futures
        ]

    def _simulate(
        self, bank: ClusterFilterBank, problem: ClusteringProblem | None, action: int, steps: int
    ) -> float:
        """``J_{k+1} + ... + J_{k+steps}`` after ``action`` at ``k`` and greedy from then on."""
        sim = bank.fork(problem)
        sim.recluster(apply_edit(sim.labels, action))
        total = 0.0
        for t in range(steps):
            if t > 0 and sim.k % self.every == 0:  # the base heuristic's own decisions
                edit, _ = best_edit(sim, self.base.max_size)
                sim.recluster(apply_edit(sim.labels, edit))
            sim.step()
            total += sim.cost().J
        bank.n_cost_evaluations += sim.n_cost_evaluations  # the decision's whole effort
        return total


register_agent(
    AgentSpec(
        "rollout",
        (CLUSTERING_ENV_ID,),
        ClusteringRolloutAgent,
        "top-k edits, each simulated L steps with greedy on forecast noise (no future noise)",
    )
)
