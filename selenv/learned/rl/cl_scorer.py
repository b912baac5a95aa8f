"""Deprecated path of :mod:`selenv.learned.families.cooperative`, removed in the next release.

Importing it warns (``DeprecationWarning``) and re-exports the names it held.
"""

from __future__ import annotations

import warnings

from selenv.learned.families.cooperative import (
    CHECKPOINT_FORMAT,
    DEFAULT_CEM_CHECKPOINT,
    ENV_CONFIG_KEYS,
    CLLearnedScorerAgent,
    env_config,
    make_cl_cem,
    read_scorer,
)

__all__ = [
    "CHECKPOINT_FORMAT",
    "DEFAULT_CEM_CHECKPOINT",
    "ENV_CONFIG_KEYS",
    "CLLearnedScorerAgent",
    "env_config",
    "make_cl_cem",
    "read_scorer",
]

warnings.warn(
    "selenv.learned.rl.cl_scorer is deprecated and removed in the next release; import from "
    "selenv.learned.families.cooperative",
    DeprecationWarning,
    stacklevel=2,
)
