"""Versioned env ids: the record of one registered id, and the deprecation of old versions.

Gymnasium's rule: any change that can alter an env's results bumps its version, so a result
published against an id can be reproduced from the id alone. Every family
(:mod:`selenv.families`) registers its ids from its record: ``-v0`` (release 0.1), the frozen
versions (:attr:`~selenv.families.spec.FamilySpec.frozen`, still registered and never changed)
and the current one:

========================= ============================================= ======================
family                    ``-v0`` (release 0.1)                          ``-v1``
========================= ============================================= ======================
``CLScheduling``          ``preset="dense"`` (4 agents, budget 2,        ``preset="benchmark"``
                          horizon 200, log det)                          (current)
``FIMSelection``          ``preset="example2" / "example3"`` mean the    the paper's stationary
                          moving-target scenarios (``*_moving``)         Examples 2 and 3
                                                                         (current)
``LandmarkSelection``     unchanged                                      unchanged (current)
``ReceiverClustering``    ``preset="paper"`` (fixed receiver noise),     ``preset="multipath"``,
                          ``obs_mask=False`` (no ``action_mask`` in the  the mask observed;
                          assignment mode's observation)                 frozen: ``-v2`` (one
                                                                         ``Discrete`` placement
                                                                         per step, exact mask)
                                                                         is current
========================= ============================================= ======================

``-v0`` ids emit a ``DeprecationWarning`` pointing to the current id when made; Gymnasium
itself warns that a newer version exists when a frozen id is made. The lookups over the
registered ids (``family_of``, ``version_ids``) are in :mod:`selenv.families`.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

__all__ = ["VERSIONED_ID", "EnvVersion", "warn_deprecated"]

#: ``selenv/<Name>-v<N>``: the family part and the version number
VERSIONED_ID = re.compile(r"(?P<family>.+)-v(?P<version>\d+)")


@dataclass(frozen=True, kw_only=True)
class EnvVersion:
    """One registered id: its entry point and the keyword defaults of that version.

    Args:
        env_id: the Gymnasium id, ``"selenv/<Family>-v<N>"``.
        entry_point: ``"module:function"`` building the env from the make keywords.
        kwargs: defaults of this version, passed to ``gymnasium.register`` (a user's keyword
            overrides them); recorded in ``env.spec.kwargs``.
        superseded_by: the id that replaces this one (``None``: the current version).
        vector_entry_point: ``"module:function"`` building the family's native vector env
            (``gymnasium.make_vec``); ``None``: Gymnasium's Python loop over single envs.
    """

    env_id: str
    entry_point: str
    vector_entry_point: str | None = None
    kwargs: Mapping[str, Any] = field(default_factory=dict)
    superseded_by: str | None = None

    def __post_init__(self) -> None:
        if VERSIONED_ID.fullmatch(self.env_id) is None:
            raise ValueError(f"env_id must look like 'selenv/Name-vN', got {self.env_id!r}")
        object.__setattr__(self, "kwargs", MappingProxyType(dict(self.kwargs)))


def warn_deprecated(env_id: str, newer: str) -> None:
    """``DeprecationWarning``: ``env_id`` reproduces release 0.1, ``newer`` is current."""
    warnings.warn(
        f"{env_id} reproduces selenv 0.1; {newer} is the current version (see its "
        "docstring's Version History)",
        DeprecationWarning,
        stacklevel=4,
    )
