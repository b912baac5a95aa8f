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

#: factory functions, not the classes: ``gymnasium.make`` would otherwise pre-check
#: ``render_mode`` itself and crash on a non-str value (see :mod:`selenv.envs.factories`)
_ENTRY_POINTS = {
    "selenv/CLScheduling-v0": "selenv.envs.factories:cl_scheduling",
    "selenv/FIMSelection-v0": "selenv.envs.factories:fim_selection",
    "selenv/LandmarkSelection-v0": "selenv.envs.factories:landmark_selection",
    "selenv/ReceiverClustering-v0": "selenv.envs.factories:receiver_clustering",
}

for _id, _entry in _ENTRY_POINTS.items():
    if _id not in gym.registry:
        gym.register(id=_id, entry_point=_entry, disable_env_checker=False)
