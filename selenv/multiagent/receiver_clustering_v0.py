"""PettingZoo module ``receiver_clustering_v0``: release 0.1's receiver clustering (deprecated).

The same env as ``receiver_clustering_v1`` with ``preset="paper"`` (fixed receiver noise) by
default, which replays release 0.1's episodes; making it emits a ``DeprecationWarning``. The
manual is ``selenv.families.clustering.multiagent``.
"""

from __future__ import annotations

from selenv.families.clustering.multiagent import (
    ReceiverClusteringParallelEnv,
    label_masks,
    resolve_moves,
)
from selenv.families.clustering.multiagent import env_v0 as env
from selenv.families.clustering.multiagent import parallel_env_v0 as parallel_env
from selenv.families.clustering.multiagent import raw_env_v0 as raw_env

__all__ = [
    "ReceiverClusteringParallelEnv",
    "env",
    "label_masks",
    "parallel_env",
    "raw_env",
    "resolve_moves",
]
