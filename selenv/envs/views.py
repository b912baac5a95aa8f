"""Candidate views: every selection env's observation as a set of candidates, one per action.

:class:`~selenv.learned.rl.candidate_policy.CandidateScoringPolicy` reads a ``Dict`` observation
with
one row per action (the ``FIMSelection-v1`` layout)::

    gain        (N,)      a non-negative marginal gain of taking the action now (0: unknown)
    whitened    (N, W)    per-candidate numeric features (symlog-squashed by the policy)
    features    (N, 4)    per-candidate flags / static features in [-1, 1]
    selected    (N,)      1 if the candidate was already used
    budget_left (1,)      fraction of the decision budget left
    action_mask (N,)      allowed actions

``FIMSelection-v1`` and ``LandmarkSelection-v1`` already observe this layout (identity view).
``CLScheduling-v1`` is rewritten by :class:`~selenv.families.cooperative.view.CLView`: the ``P``
directed pairs plus the stop
action are the candidates; ``ReceiverClustering-v1`` by
:class:`~selenv.families.clustering.view.ClusteringEditView`: the local
edits (move, leave, swap, no-op) of the current clustering. A view is a pure function of the
observation, so the same view is applied in training
(:class:`~selenv.learned.rl.views.CandidateViewWrapper`) and when
a checkpoint acts (:mod:`selenv.learned.rl.agent`).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

__all__ = ["IDENTITY_VIEWS", "N_FEATURES", "CandidateView", "IdentityView", "candidate_space"]

N_FEATURES = 4


def candidate_space(n: int, width: int) -> spaces.Dict:
    """The candidate ``Dict`` space for ``n`` candidates with ``width`` numeric features each."""
    return spaces.Dict(
        {
            "action_mask": spaces.MultiBinary(n),
            "budget_left": spaces.Box(0.0, 1.0, (1,), np.float32),
            "features": spaces.Box(-1.0, 1.0, (n, N_FEATURES), np.float32),
            "gain": spaces.Box(0.0, np.inf, (n,), np.float32),
            "selected": spaces.MultiBinary(n),
            "whitened": spaces.Box(-np.inf, np.inf, (n, width), np.float32),
        }
    )


class CandidateView:
    """Base class: ``space(env_space)`` and ``__call__(obs)`` rewrite an env's observations.

    ``env_action(obs, a)`` maps a candidate index back to the env's action (identity unless the
    env's action encoding differs from the candidates, as in receiver clustering's assignment
    mode).
    """

    name = "base"
    #: whether the view reads the live env besides the observation (previewed updates); a
    #: pure view (``False``) is a function of the observation alone and also serves a batched
    #: vector env (:class:`selenv.learned.rl.vec_env.NativeVecEnv`)
    live = False

    def env_action(self, obs: dict[str, np.ndarray], action: int) -> Any:  # noqa: D102
        return action

    def space(self, env_space: spaces.Space) -> spaces.Dict:  # noqa: D102
        raise NotImplementedError

    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:  # noqa: D102
        raise NotImplementedError

    def verify(self, env: gym.Env[Any, Any], obs: dict[str, np.ndarray], actions: Any) -> int:
        """Cost the candidate ``actions`` exactly in ``env`` and return the best one.

        Only views of envs with a cheap exact objective oracle implement it (the policy then
        acts as a learned proposal for a small local search).

        Raises:
            ValueError: the view has no verification.
        """
        raise ValueError(f"the {self.name!r} candidate view has no exact verification")


class IdentityView(CandidateView):
    """The env already observes candidates (``FIMSelection-v1``, ``LandmarkSelection-v1``)."""

    name = "identity"

    def space(self, env_space: spaces.Space) -> spaces.Dict:  # noqa: D102
        if not isinstance(env_space, spaces.Dict):
            raise ValueError(f"expected a Dict observation space, got {env_space}")
        return env_space

    def __call__(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:  # noqa: D102
        return obs


#: the views of an env that already observes candidates (FIMSelection, LandmarkSelection)
IDENTITY_VIEWS: dict[str, Any] = {"identity": lambda env: IdentityView()}
