"""PettingZoo module ``receiver_clustering_v1`` (manual: selenv.families.clustering.multiagent)."""

from __future__ import annotations

from selenv.families.clustering.multiagent import (
    ReceiverClusteringParallelEnv,
    env,
    label_masks,
    parallel_env,
    raw_env,
    resolve_moves,
)
from selenv.families.clustering.multiagent import __doc__ as _manual

__all__ = [
    "ReceiverClusteringParallelEnv",
    "env",
    "label_masks",
    "parallel_env",
    "raw_env",
    "resolve_moves",
]
__doc__ = _manual
