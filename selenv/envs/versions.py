"""Versioned env ids: which ``-vN`` of a family reproduces which release's behaviour.

Gymnasium's rule: any change that can alter an env's results bumps its version, so a result
published against an id can be reproduced from the id alone. The table here is the one source
of the ids, their entry points and the keyword defaults of each version; registration
(:mod:`selenv.envs`), ``selenv list`` and the agent registry (an agent registered for one
version of a family applies to all of them) read it.

========================= ============================================= ======================
family                    ``-v0`` (release 0.1)                          ``-v1`` (current)
========================= ============================================= ======================
``CLScheduling``          ``preset="dense"`` (4 agents, budget 2,        ``preset="benchmark"``
                          horizon 200, log det)
``FIMSelection``          ``preset="example2" / "example3"`` mean the    the paper's stationary
                          moving-target scenarios (``*_moving``)         Examples 2 and 3
``LandmarkSelection``     unchanged                                      unchanged
``ReceiverClustering``    ``preset="paper"`` (fixed receiver noise)      ``preset="multipath"``
========================= ============================================= ======================

``-v0`` ids emit a ``DeprecationWarning`` pointing to ``-v1`` when made.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

__all__ = [
    "ENV_VERSIONS",
    "EnvVersion",
    "family_of",
    "latest_ids",
    "version_ids",
    "warn_deprecated",
]


@dataclass(frozen=True, kw_only=True)
class EnvVersion:
    """One registered id: its entry point and the keyword defaults of that version.

    Args:
        env_id: the Gymnasium id, ``"selenv/<Family>-v<N>"``.
        entry_point: ``"module:function"`` building the env from the make keywords.
        kwargs: defaults of this version, passed to ``gymnasium.register`` (a user's keyword
            overrides them); recorded in ``env.spec.kwargs``.
        superseded_by: the id that replaces this one (``None``: the current version).
    """

    env_id: str
    entry_point: str
    kwargs: Mapping[str, Any] = field(default_factory=dict)
    superseded_by: str | None = None

    def __post_init__(self) -> None:
        if _VERSIONED.fullmatch(self.env_id) is None:
            raise ValueError(f"env_id must look like 'selenv/Name-vN', got {self.env_id!r}")
        object.__setattr__(self, "kwargs", MappingProxyType(dict(self.kwargs)))


_VERSIONED = re.compile(r"(?P<family>.+)-v(?P<version>\d+)")
_F = "selenv.envs.factories"


def _family(name: str, factory: str, v0_kwargs: Mapping[str, Any]) -> tuple[EnvVersion, ...]:
    """``-v0`` (release 0.1, ``<factory>_v0`` with ``v0_kwargs``) and ``-v1`` of a family."""
    v0, v1 = f"selenv/{name}-v0", f"selenv/{name}-v1"
    return (
        EnvVersion(env_id=v0, entry_point=f"{_F}:{factory}_v0", kwargs=v0_kwargs, superseded_by=v1),
        EnvVersion(env_id=v1, entry_point=f"{_F}:{factory}"),
    )


#: every registered id, oldest version of each family first
ENV_VERSIONS: tuple[EnvVersion, ...] = (
    *_family("CLScheduling", "cl_scheduling", {"preset": "dense"}),
    *_family("FIMSelection", "fim_selection", {}),  # the factory maps v0's preset names
    *_family("LandmarkSelection", "landmark_selection", {}),
    *_family("ReceiverClustering", "receiver_clustering", {"preset": "paper"}),
)

_BY_ID = {v.env_id: v for v in ENV_VERSIONS}


def family_of(env_id: str) -> str:
    """``"selenv/CLScheduling"`` for any registered version; other names (PettingZoo) as given."""
    match = _VERSIONED.fullmatch(env_id) if env_id in _BY_ID else None
    return env_id if match is None else match["family"]


def version_ids(env_id: str) -> tuple[str, ...]:
    """Every registered id of ``env_id``'s family (``(env_id,)`` if it is not in the table)."""
    family = family_of(env_id)
    ids = tuple(v.env_id for v in ENV_VERSIONS if family_of(v.env_id) == family)
    return ids or (env_id,)


def latest_ids() -> tuple[str, ...]:
    """The current id of every family, in the table's order."""
    return tuple(v.env_id for v in ENV_VERSIONS if v.superseded_by is None)


def warn_deprecated(env_id: str) -> None:
    """``DeprecationWarning`` naming the id that supersedes ``env_id`` (if any)."""
    newer = _BY_ID[env_id].superseded_by
    if newer is not None:
        warnings.warn(
            f"{env_id} reproduces selenv 0.1; {newer} is the current version (see its "
            "docstring's Version History)",
            DeprecationWarning,
            stacklevel=4,
        )
