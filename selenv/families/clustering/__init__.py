"""The ``ReceiverClustering`` family.

Clustering GNSS receivers with a shared bias (Greiff et al. 2022).

:data:`SPEC` is its record; the folder's modules are listed in :mod:`selenv.families.spec`.
"""

from __future__ import annotations

from selenv.families.spec import (
    FamilySpec,
    FrozenVersion,
    env_factories,
    frozen_factories,
    vector_factories,
)

__all__ = [
    "SPEC",
    "make_env",
    "make_env_v0",
    "make_env_v1",
    "make_vector_env",
    "make_vector_env_v0",
    "make_vector_env_v1",
]

SPEC = FamilySpec(
    name="clustering",
    env_name="ReceiverClustering",
    title="clustering GNSS receivers with a shared bias (Greiff et al. 2022)",
    env_class="selenv.families.clustering.sequential:ReceiverClusteringSequentialEnv",
    vector_class="selenv.families.clustering.sequential_vector:ReceiverClusteringSequentialVectorEnv",
    frozen=(
        FrozenVersion(
            env_class="selenv.families.clustering.env:ReceiverClusteringEnv",
            vector_class="selenv.families.clustering.vector:ReceiverClusteringVectorEnv",
            change="one Discrete action per receiver placement with an exact mask (was: the "
            "whole clustering as a MultiDiscrete label vector, or an edit index)",
        ),
    ),
    agent_adapter="selenv.families.clustering.sequential:SequentialAgent",
    v0_kwargs={"preset": "paper", "obs_mask": False},
    views="selenv.families.clustering.view:VIEWS",
    checkpoint="receiver_clustering_ppo.zip",
    policies="selenv.families.clustering.policies:POLICIES",
    agent_modules=(
        "selenv.families.clustering.agents",
        "selenv.families.clustering.rollout",
        "selenv.families.clustering.multiagent_agents",
    ),
    multiagent_module="selenv.multiagent.receiver_clustering_v1",
    multiagent_v0="selenv.multiagent.receiver_clustering_v0",
    return_bound="selenv.families.clustering.bounds:return_bound",
)
make_env, make_env_v0 = env_factories(SPEC)
make_vector_env, make_vector_env_v0 = vector_factories(SPEC)
make_env_v1, make_vector_env_v1 = frozen_factories(SPEC, 1)
