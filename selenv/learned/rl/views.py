"""Candidate views for the learned policies: the table of every env's views and the wrapper.

The candidate layout and the view classes are in :mod:`selenv.envs.views` and the families' ``view``
modules; :data:`VIEWS` is built from the family records, :class:`CandidateViewWrapper` applies a
view in training and :mod:`selenv.learned.rl.agent` when a checkpoint acts. This module names no
family: a family's view classes are reached through its record (``FamilySpec.views``).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from selenv.envs.views import N_FEATURES, CandidateView, IdentityView, candidate_space
from selenv.families import ADAPTED, FAMILIES
from selenv.families.spec import load_attr
from selenv.learned.rl._moved import moved_attr

__all__ = [
    "N_FEATURES",
    "VIEWS",
    "CandidateView",
    "CandidateViewWrapper",
    "IdentityView",
    "candidate_space",
    "view_for",
]

#: family view classes this module re-exported before (deprecated here, for one release)
_FAMILY_VIEW_CLASSES = ("CLView", "ClusteringEditView")


#: env id (every registered version whose agents are the family's own, not adapted ones) ->
#: {view name -> factory of the view from the env}; the first name is the default. Built from
#: the family records (their ``views``).
VIEWS: dict[str, dict[str, Callable[[Any], CandidateView]]] = {
    version.env_id: load_attr(spec.views)
    for spec in FAMILIES
    for version in spec.versions
    if version.env_id not in ADAPTED
}


def view_for(env_id: str, env: gym.Env[Any, Any], name: str | None = None) -> CandidateView:
    """Candidate view ``name`` (default: the env's first) of ``env`` (``gymnasium.make(env_id)``).

    Raises:
        ValueError: no view for ``env_id``, or no view ``name`` for it (the message lists the
            supported ones).
    """
    if env_id not in VIEWS:
        raise ValueError(f"no candidate view for {env_id!r}; supported: {sorted(VIEWS)}")
    views = VIEWS[env_id]
    if name is None:
        name = next(iter(views))
    if name not in views:
        raise ValueError(f"no candidate view {name!r} for {env_id}; supported: {sorted(views)}")
    return views[name](env)


class CandidateViewWrapper(gym.ObservationWrapper[Any, Any, Any]):
    """Apply a :class:`CandidateView` to a Gymnasium env; forwards ``action_masks()``."""

    def __init__(self, env: gym.Env[Any, Any], view: CandidateView) -> None:
        super().__init__(env)
        self.view = view
        self.observation_space = view.space(env.observation_space)

    def observation(self, observation: Any) -> dict[str, np.ndarray]:  # noqa: D102
        return self.view(observation)

    def action_masks(self) -> np.ndarray:
        """The wrapped env's mask (MaskablePPO reads it through the VecEnv)."""
        return np.asarray(self.env.unwrapped.action_masks(), dtype=bool)  # type: ignore[attr-defined]


def __getattr__(name: str) -> Any:
    """A family view class once re-exported here, from the view module its record names.

    Warns (``DeprecationWarning``) with the module to import it from.
    """
    if name in _FAMILY_VIEW_CLASSES:
        for home in sorted({spec.views.partition(":")[0] for spec in FAMILIES}):
            if hasattr(importlib.import_module(home), name):
                return moved_attr(__name__, name, {name: home})
    return moved_attr(__name__, name, {})
