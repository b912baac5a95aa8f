"""The PettingZoo module ``fim_selection_v0`` (its manual: ``selenv.families.fim.multiagent``)."""

from __future__ import annotations

from selenv.families.fim.multiagent import (
    MODES,
    FIMSelectionParallelEnv,
    env,
    parallel_env,
    raw_env,
)
from selenv.families.fim.multiagent import __doc__ as _manual

__all__ = ["MODES", "FIMSelectionParallelEnv", "env", "parallel_env", "raw_env"]
__doc__ = _manual
