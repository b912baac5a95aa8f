"""Gymnasium environments; importing this module registers every ``selenv/...`` id."""

from __future__ import annotations

import gymnasium as gym

__all__ = ["ENV_IDS"]

#: every Gymnasium id this package registers, in the order ``selenv list`` shows them
ENV_IDS: tuple[str, ...] = (
    "selenv/CLScheduling-v0",
    "selenv/FIMSelection-v0",
    "selenv/LandmarkSelection-v0",
    "selenv/ReceiverClustering-v0",
)

_ENTRY_POINTS = {
    "selenv/CLScheduling-v0": "selenv.envs.cl_scheduling:CLSchedulingEnv",
    "selenv/FIMSelection-v0": "selenv.envs.fim_selection:FIMSelectionEnv",
    "selenv/LandmarkSelection-v0": "selenv.envs.landmark_selection:LandmarkSelectionEnv",
    "selenv/ReceiverClustering-v0": "selenv.envs.receiver_clustering:ReceiverClusteringEnv",
}

for _id, _entry in _ENTRY_POINTS.items():
    if _id not in gym.registry:
        gym.register(id=_id, entry_point=_entry, disable_env_checker=False)
