"""Agents for ``selenv/CLScheduling-v1`` (baselines to test against).

| name | what |
|---|---|
| ``greedy`` | the pair whose fused update (previewed) lowers the objective most; else stop |
| ``round_robin`` | cycle through the pairs in a fixed order, taking the next available ones |
| ``random`` | uniformly random available pairs, then stop |
| ``all`` | available pairs in index order until the budget is spent (all when it allows) |
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from selenv.agents.base import Agent, AgentSpec, register_agent
from selenv.families.cooperative.env import CLSchedulingEnv

__all__ = ["CL_ENV_ID", "GreedySchedule", "RoundRobinSchedule"]

CL_ENV_ID = "selenv/CLScheduling-v1"


def _env(env: gym.Env[Any, Any], name: str) -> CLSchedulingEnv:
    base = env.unwrapped
    if not isinstance(base, CLSchedulingEnv):
        raise ValueError(f"agent {name!r} needs {CL_ENV_ID}, got {type(base).__name__}")
    return base


class GreedySchedule(Agent):
    """Preview every available pair with the env's fusion and take the best objective drop."""

    name = "greedy"

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:  # noqa: D102
        super().reset(env, seed)
        self.base = _env(env, self.name)

    def act(self, obs: Any, info: dict[str, Any]) -> int:
        """Best pair by previewed objective decrease, or stop (index ``P``) if none helps."""
        base = self.base
        mask = np.asarray(info["action_mask"], dtype=bool)
        stop = base.n_pairs
        best, best_gain = stop, 0.0
        for p in np.flatnonzero(mask[:-1]):
            gain = base.preview_gain(int(p))
            if gain > best_gain:
                best, best_gain = int(p), gain
        return best


class RoundRobinSchedule(Agent):
    """Take available pairs in a fixed cyclic order, continuing where the last step stopped."""

    name = "round_robin"

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:  # noqa: D102
        super().reset(env, seed)
        self.base = _env(env, self.name)
        self.next = 0

    def act(self, obs: Any, info: dict[str, Any]) -> int:
        """The next available pair in cyclic order, or stop."""
        mask = np.asarray(info["action_mask"], dtype=bool)[:-1]
        P = mask.size
        for shift in range(P):
            p = (self.next + shift) % P
            if mask[p]:
                self.next = p + 1
                return p
        return P


class _MaskedChoice(Agent):
    """``random``: a uniformly random available pair; ``all``: the first available pair."""

    def __init__(self, name: str) -> None:
        self.name = name  # type: ignore[misc]

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:
        super().reset(env, seed)
        _env(env, self.name)

    def act(self, obs: Any, info: dict[str, Any]) -> int:
        mask = np.asarray(info["action_mask"], dtype=bool)[:-1]
        avail = np.flatnonzero(mask)
        if avail.size == 0:
            return mask.size
        return int(self.rng.choice(avail)) if self.name == "random" else int(avail[0])


_ID = (CL_ENV_ID,)
register_agent(AgentSpec("greedy", _ID, GreedySchedule, "best previewed objective drop"))
register_agent(AgentSpec("round_robin", _ID, RoundRobinSchedule, "pairs in cyclic order"))
register_agent(AgentSpec("random", _ID, lambda: _MaskedChoice("random"), "random available pairs"))
register_agent(AgentSpec("all", _ID, lambda: _MaskedChoice("all"), "every available pair"))
