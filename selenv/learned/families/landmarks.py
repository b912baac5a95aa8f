"""Learning code that serves ``LandmarkSelection``: ``ppo_search``.

``ppo_search``: the learned policy as the prior of a short lookahead. A policy alone recovers
about half of the landmark ``rollout``'s edge over brute force; the lookahead itself,
restricted to a shortlist, recovers nearly all of it at brute force's cost
(``fast_rollout``, :mod:`selenv.families.landmarks.fast_rollout`). This agent joins the two the
way a search with a learned prior does: the policy (a candidate-scoring checkpoint, by default
the shipped ``ppo``) ranks the open landmarks once per filter step -- one forward pass, in
numpy (:meth:`~selenv.learned.rl.agent.SB3PolicyAgent.logits`) -- and
its ``shortlist`` best-scored landmarks are the only ones the lookahead considers (its
candidates and its simulated brute-force base). Everything else is ``fast_rollout``'s: the
``top_k`` K-subsets of the shortlist by one-step gain, each scored by minus the env's cost
eq. (11) of Soubaras & Chahbazian (2023) summed over its update and ``horizon`` simulated
updates, on the forecast (never the true state or future noise).

``fast_rollout`` ranks the shortlist by the single-landmark gain now, which misses landmarks
whose value lies in the future; the policy was trained on ``rollout``'s labels (the best
lookahead score of a subset holding the landmark), so it ranks by an estimate of exactly that.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from selenv.core.linalg import FloatArray
from selenv.families.landmarks.fast_rollout import LandmarkFastRolloutAgent
from selenv.families.landmarks.rollout import LANDMARK_ENV_ID
from selenv.learned.rl.agent import SB3PolicyAgent

__all__ = ["LandmarkPolicySearchAgent", "make_landmark_ppo_search"]


class LandmarkPolicySearchAgent(LandmarkFastRolloutAgent):
    """``fast_rollout`` on the shortlist a learned policy ranks first (module docstring).

    Args:
        checkpoint: candidate-scoring checkpoint trained on ``LandmarkSelection-v1``
            (default: the shipped ``ppo``).
        top_k: candidate K-subsets scored per filter step (>= 1).
        horizon: future filter steps simulated (>= 0).
        shortlist: landmarks ``M`` the policy passes to the lookahead (>= 1; at least the
            budget ``K``).
        allow_large: lift the ceilings on ``top_k``, ``horizon`` and ``shortlist``.

    Raises:
        ValueError: a bad option, or the checkpoint is missing, unreadable or was trained on
            another env.
    """

    name = "ppo_search"

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        top_k: int = 4,
        horizon: int = 10,
        shortlist: int = 6,
        allow_large: bool = False,
    ) -> None:
        super().__init__(top_k, horizon, shortlist, allow_large)
        self.policy = SB3PolicyAgent(checkpoint, env_id=LANDMARK_ENV_ID)

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:
        """Bind the lookahead and the policy to ``env`` (``LandmarkSelection``, log det)."""
        super().reset(env, seed)
        self.policy.reset(env, seed)

    def select_shortlist(
        self, obs: Any, info: dict[str, Any] | None, gains: FloatArray, M: int
    ) -> np.ndarray:
        """The ``M`` open landmarks of largest policy logit (ties: the larger gain, then index).

        Raises:
            ValueError: no observation (``scores()`` called outside an episode step).
        """
        if obs is None:
            raise ValueError(
                "agent 'ppo_search' ranks the shortlist from the observation: pass obs"
            )
        logits = np.asarray(self.policy.logits(obs, info or {}, backend="numpy"), np.float64)
        open_ = np.isfinite(gains)
        # lexsort: last key first -> logit descending, then gain descending, then index
        order = np.lexsort((-np.where(open_, gains, 0.0), -np.where(open_, logits, -np.inf)))
        return order[:M]


def make_landmark_ppo_search(**kwargs: Any) -> LandmarkPolicySearchAgent:
    """Registry factory of ``ppo_search`` (the keyword arguments of the class)."""
    return LandmarkPolicySearchAgent(**kwargs)
