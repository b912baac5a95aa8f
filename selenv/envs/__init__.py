"""Gymnasium environments; importing this module registers every ``selenv/...`` id.

The ids, their entry points and each version's keyword defaults are in
:mod:`selenv.envs.versions` (one table); ``-v0`` reproduces release 0.1, ``-v1`` is current.
"""

from __future__ import annotations

import gymnasium as gym

from selenv.envs.versions import ENV_VERSIONS, latest_ids

__all__ = ["ALL_ENV_IDS", "ENV_IDS"]

#: the current id of every family, in the order ``selenv list`` and ``selenv bench`` use them
ENV_IDS: tuple[str, ...] = latest_ids()

#: every registered Gymnasium id, older versions included
ALL_ENV_IDS: tuple[str, ...] = tuple(v.env_id for v in ENV_VERSIONS)

# factory functions, not the classes: ``gymnasium.make`` would otherwise pre-check
# ``render_mode`` itself and crash on a non-str value (see :mod:`selenv.envs.factories`)
for _v in ENV_VERSIONS:
    if _v.env_id not in gym.registry:
        gym.register(
            id=_v.env_id,
            entry_point=_v.entry_point,
            kwargs=dict(_v.kwargs),
            disable_env_checker=False,
        )
