"""``rollout`` for ``CLScheduling``: greedy scheduling simulated ahead (selenv.agents.rollout)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from selenv.agents.base import Agent, AgentSpec, register_agent
from selenv.agents.rollout import best_index, ceiling_option, choice_option
from selenv.families.cooperative.env import CLSchedulingEnv
from selenv.families.cooperative.forecast import CLForecast

__all__ = ["CLRolloutAgent", "rollout_options"]

CL_ENV_ID = "selenv/CLScheduling-v1"
CL_BASES = ("greedy", "all")


def rollout_options(top_k: Any, horizon: Any, base: Any, allow_large: bool) -> tuple[int, int, str]:
    """``(top_k, horizon, base)`` checked, for ``rollout`` and the agents sharing its lookahead.

    A bad value is a ``ValueError`` naming the option; the ceilings apply unless ``allow_large``.
    """
    return (
        ceiling_option(top_k, "top_k", 1, allow_large),
        ceiling_option(horizon, "horizon", 0, allow_large),
        choice_option(base, "base", CL_BASES),
    )


class CLRolloutAgent(Agent):
    """Rollout of the greedy schedule in ``CLScheduling-v1`` (one decision per env step).

    Candidates: stop and the ``top_k`` open pairs by previewed gain. For each, a forecast plays
    the candidate, finishes the current filter step with the base policy (up to the budget;
    greedy stops when no pair lowers the objective), closes it (propagation with the held input,
    ZUPT and beacon covariance updates on their schedule), then plays ``horizon`` more filter
    steps the same way (pairs available on the ``relative_every`` schedule). The score is the
    drop of the env's objective over that trajectory; ties keep stop, then the larger
    one-step gain, so ``horizon = 0`` (immediate reward only) is the greedy agent's choice.
    When stop is the only candidate (no open pair) nothing is simulated and its score is 0.

    Args:
        top_k: pairs evaluated per decision (>= 1), besides stop.
        horizon: filter steps simulated after the current one (>= 0; 0: myopic).
        base: base policy of the simulation: ``"greedy"`` or ``"all"`` (open pairs in index
            order up to the budget).
        allow_large: lift the ceilings on ``top_k`` and ``horizon``
            (:data:`~selenv.agents.rollout.ROLLOUT_CEILINGS`).
    """

    name = "rollout"

    def __init__(
        self, top_k: int = 3, horizon: int = 5, base: str = "greedy", allow_large: bool = False
    ) -> None:
        self.top_k, self.horizon, self.base_policy = rollout_options(
            top_k, horizon, base, allow_large
        )

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:  # noqa: D102
        super().reset(env, seed)
        base = env.unwrapped
        if not isinstance(base, CLSchedulingEnv):
            raise ValueError(f"agent 'rollout' needs {CL_ENV_ID} here, got {type(base).__name__}")
        self.cl = base

    def act(self, obs: Any, info: dict[str, Any]) -> int:
        """The first action of the best simulated trajectory (a pair index, or stop ``P``)."""
        choice, _ = self.scores()
        return choice

    def scores(self) -> tuple[int, dict[int, float]]:
        """The choice and every candidate's score (stop is ``P``), from the env's state now."""
        env = self.cl
        stop = env.n_pairs
        root = CLForecast.from_env(env)
        open_ = [int(p) for p in np.flatnonzero(env.action_masks()[:-1])]
        gains = {p: root.gain(p) for p in open_}
        ranked = sorted(open_, key=lambda p: (-gains[p], p))[: self.top_k]
        candidates = [stop, *ranked]
        if self.horizon == 0 or not ranked:  # immediate reward: the greedy choice
            scores = [0.0, *(gains[p] for p in ranked)]
        else:
            start = root.objective_value()
            scores = [
                start - self._simulate(root, c, open_, gains, env.budget_left) for c in candidates
            ]
        return candidates[best_index(scores)], dict(zip(candidates, scores, strict=True))

    def _simulate(
        self, root: CLForecast, first: int, open_: list[int], gains: dict[int, float], slots: int
    ) -> float:
        """Objective at the end of the simulated trajectory that starts with ``first``."""
        f = root.copy()
        pending, g = list(open_), dict(gains)
        if first != self.cl.n_pairs:
            self._process(f, first, pending, g)
            self._base_step(f, pending, g, slots - 1)
        for _ in range(self.horizon):
            if f.k >= self.cl.horizon:  # the episode ends when this step closes
                return f.objective_value()
            f.advance()
            pending = f.available()
            g = {p: f.gain(p) for p in pending} if self.base_policy == "greedy" else {}
            self._base_step(f, pending, g, self.cl.budget)
        if f.k < self.cl.horizon:
            f.advance()
        return f.objective_value()

    def _process(self, f: CLForecast, p: int, pending: list[int], g: dict[int, float]) -> None:
        """Fuse pair ``p``; refresh the cached gains of the pairs that involve its agent."""
        f.relative_update(p)
        pending.remove(p)
        if self.base_policy == "greedy":
            i = f.pairs[p][0]
            for q in pending:
                if i in f.pairs[q]:
                    g[q] = f.gain(q)

    def _base_step(
        self, f: CLForecast, pending: list[int], g: dict[int, float], slots: int
    ) -> None:
        """The base policy's picks for the rest of a filter step (``slots`` left)."""
        while slots > 0 and pending:
            if self.base_policy == "all":
                p = pending[0]
            else:  # greedy: the largest previewed drop (first index on ties), stop if none > 0
                p = max(pending, key=lambda q: (g[q], -q))
                if not g[p] > 0.0:
                    return
            self._process(f, p, pending, g)
            slots -= 1


register_agent(
    AgentSpec(
        "rollout",
        (CL_ENV_ID,),
        CLRolloutAgent,
        "rollout: top-3 pairs + stop, 5 filter steps of greedy ahead (no future noise)",
    )
)
