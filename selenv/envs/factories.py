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

from selenv.envs.versions import warn_deprecated

__all__ = [
    "FIM_V0_PRESETS",
    "cl_scheduling",
    "cl_scheduling_v0",
    "fim_selection",
    "fim_selection_v0",
    "landmark_selection",
    "landmark_selection_v0",
    "receiver_clustering",
    "receiver_clustering_v0",
]

#: ``FIMSelection-v0`` preset names as release 0.1 meant them (the moving-target scenarios);
#: every other preset name means the same in both versions
FIM_V0_PRESETS = {"example2": "example2_moving", "example3": "example3_moving"}


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
    """``selenv/CLScheduling-v1``: a ``CLSchedulingEnv``."""
    return _build("selenv.envs.cl_scheduling:CLSchedulingEnv", **kwargs)


def fim_selection(**kwargs: Any) -> gym.Env[Any, Any]:
    """``selenv/FIMSelection-v1``: a ``FIMSelectionEnv``."""
    return _build("selenv.envs.fim_selection:FIMSelectionEnv", **kwargs)


def landmark_selection(**kwargs: Any) -> gym.Env[Any, Any]:
    """``selenv/LandmarkSelection-v1``: a ``LandmarkSelectionEnv``."""
    return _build("selenv.envs.landmark_selection:LandmarkSelectionEnv", **kwargs)


def receiver_clustering(**kwargs: Any) -> gym.Env[Any, Any]:
    """``selenv/ReceiverClustering-v1``: a ``ReceiverClusteringEnv``."""
    return _build("selenv.envs.receiver_clustering:ReceiverClusteringEnv", **kwargs)


def cl_scheduling_v0(**kwargs: Any) -> gym.Env[Any, Any]:
    """``selenv/CLScheduling-v0`` (release 0.1): the ``dense`` preset by default (registered)."""
    warn_deprecated("selenv/CLScheduling-v0")
    return cl_scheduling(**kwargs)


def fim_selection_v0(**kwargs: Any) -> gym.Env[Any, Any]:
    """``selenv/FIMSelection-v0`` (release 0.1): example 2 / 3 are the moving-target scenarios.

    ``preset="example2"`` (the default) and ``"example3"`` map through :data:`FIM_V0_PRESETS`.
    """
    warn_deprecated("selenv/FIMSelection-v0")
    preset = kwargs.pop("preset", "example2")
    if isinstance(preset, str):
        preset = FIM_V0_PRESETS.get(preset, preset)
    return fim_selection(preset=preset, **kwargs)


def landmark_selection_v0(**kwargs: Any) -> gym.Env[Any, Any]:
    """``selenv/LandmarkSelection-v0`` (release 0.1): the same env as ``-v1``."""
    warn_deprecated("selenv/LandmarkSelection-v0")
    return landmark_selection(**kwargs)


def receiver_clustering_v0(**kwargs: Any) -> gym.Env[Any, Any]:
    """``selenv/ReceiverClustering-v0`` (release 0.1): the ``paper`` preset by default."""
    warn_deprecated("selenv/ReceiverClustering-v0")
    return receiver_clustering(**kwargs)
