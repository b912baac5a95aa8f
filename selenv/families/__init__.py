"""The env families, one folder each; importing this registers their Gymnasium ids.

:data:`FAMILIES` lists the records (:class:`~selenv.families.spec.FamilySpec`), one line per
family; everything that names a family elsewhere (the ids and their versions, ``selenv list``,
the agent registry, the candidate views, the ``ppo`` agent's checkpoints) is built from them.
Adding a family: a new folder with its record (see ``docs/guide/adding_a_family.md``) and one line
here.
"""

from __future__ import annotations

import gymnasium as gym

from selenv.envs.versions import VERSIONED_ID, EnvVersion
from selenv.families import clustering, cooperative, fim, landmarks
from selenv.families.spec import FamilySpec

__all__ = [
    "ADAPTED",
    "ALL_ENV_IDS",
    "ENV_IDS",
    "ENV_VERSIONS",
    "FAMILIES",
    "FamilySpec",
    "family_of",
    "family_spec",
    "version_ids",
]

#: every family, in the order ``selenv list`` and ``selenv bench`` show them
FAMILIES: tuple[FamilySpec, ...] = (cooperative.SPEC, fim.SPEC, landmarks.SPEC, clustering.SPEC)

#: every registered id, oldest version of each family first
ENV_VERSIONS: tuple[EnvVersion, ...] = tuple(v for f in FAMILIES for v in f.versions)
#: the current id of every family
ENV_IDS: tuple[str, ...] = tuple(f.current_id for f in FAMILIES)
#: every registered Gymnasium id, older versions included
ALL_ENV_IDS: tuple[str, ...] = tuple(v.env_id for v in ENV_VERSIONS)

#: current id -> ``(older id, "module:adapter")``: the older version's agents play the current
#: one through the adapter (:attr:`FamilySpec.agent_adapter`)
ADAPTED: dict[str, tuple[str, str]] = {
    f.current_id: (f.adapted_from, f.agent_adapter)
    for f in FAMILIES
    if f.adapted_from is not None and f.agent_adapter is not None
}

_BY_ID = {v.env_id: f for f in FAMILIES for v in f.versions}
_BY_MODULE = {m: f for f in FAMILIES for m in f.multiagent_modules}


def family_of(env_id: str) -> str:
    """``"selenv/CLScheduling"`` for any registered version; other names (PettingZoo) as given."""
    match = VERSIONED_ID.fullmatch(env_id) if env_id in _BY_ID else None
    return env_id if match is None else match["family"]


def family_spec(env_id: str) -> FamilySpec | None:
    """The record of the family ``env_id`` (any version) belongs to; ``None`` if none."""
    return _BY_ID.get(env_id)


def version_ids(env_id: str) -> tuple[str, ...]:
    """Every version of ``env_id``: the family's Gymnasium ids, or its PettingZoo module names.

    ``(env_id,)`` if ``env_id`` is neither.
    """
    if env_id in _BY_MODULE:
        return _BY_MODULE[env_id].multiagent_modules
    spec = _BY_ID.get(env_id)
    return (env_id,) if spec is None else tuple(v.env_id for v in spec.versions)


# factory functions, not the classes, as entry points (see selenv.families.spec.build_env)
for _v in ENV_VERSIONS:
    if _v.env_id not in gym.registry:
        gym.register(
            id=_v.env_id,
            entry_point=_v.entry_point,
            kwargs=dict(_v.kwargs),
            vector_entry_point=_v.vector_entry_point,
            disable_env_checker=False,
        )
