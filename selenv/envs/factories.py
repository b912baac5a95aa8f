"""Entry points of the registered ids: build the env class from the ``gymnasium.make`` keywords.

``gymnasium.make`` inspects ``entry_point.metadata`` when the entry point is a class, and then
handles ``render_mode`` itself before the env sees it: a non-str ``render_mode`` (``1``,
``True``) fails there with an ``AttributeError`` (``render_mode.endswith``). The ids are
therefore registered with these plain functions, so that every keyword, ``render_mode``
included, is validated by the env (a ``TypeError`` / ``ValueError`` naming it). What
``gymnasium.make`` would have added is kept: ``render_mode="rgb_array_list"`` wraps the
``"rgb_array"`` env in :class:`gymnasium.wrappers.RenderCollection` (every env renders
``"human"`` natively).
"""

from __future__ import annotations

import importlib
from typing import Any

import gymnasium as gym
from gymnasium.wrappers import RenderCollection

__all__ = ["cl_scheduling", "fim_selection", "landmark_selection", "receiver_clustering"]


def _build(entry: str, render_mode: Any = None, **kwargs: Any) -> gym.Env[Any, Any]:
    module, name = entry.split(":")
    cls = getattr(importlib.import_module(module), name)
    modes = cls.metadata["render_modes"]
    if isinstance(render_mode, str) and render_mode.endswith("_list"):
        base = render_mode[: -len("_list")]
        if base in modes and base != "human":
            return RenderCollection(cls(render_mode=base, **kwargs))
    env: gym.Env[Any, Any] = cls(render_mode=render_mode, **kwargs)
    return env


def cl_scheduling(**kwargs: Any) -> gym.Env[Any, Any]:
    """``selenv/CLScheduling-v0``: a ``CLSchedulingEnv``."""
    return _build("selenv.envs.cl_scheduling:CLSchedulingEnv", **kwargs)


def fim_selection(**kwargs: Any) -> gym.Env[Any, Any]:
    """``selenv/FIMSelection-v0``: a ``FIMSelectionEnv``."""
    return _build("selenv.envs.fim_selection:FIMSelectionEnv", **kwargs)


def landmark_selection(**kwargs: Any) -> gym.Env[Any, Any]:
    """``selenv/LandmarkSelection-v0``: a ``LandmarkSelectionEnv``."""
    return _build("selenv.envs.landmark_selection:LandmarkSelectionEnv", **kwargs)


def receiver_clustering(**kwargs: Any) -> gym.Env[Any, Any]:
    """``selenv/ReceiverClustering-v0``: a ``ReceiverClusteringEnv``."""
    return _build("selenv.envs.receiver_clustering:ReceiverClusteringEnv", **kwargs)
