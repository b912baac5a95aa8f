"""The ``CLScheduling`` family.

Cooperative localization: which relative measurements to fuse (Chen & Kia 2022).

:data:`SPEC` is its record; the folder's modules are listed in :mod:`selenv.families.spec`.
"""

from __future__ import annotations

from selenv.families.spec import FamilySpec, env_factories, vector_factories

__all__ = ["SPEC", "make_env", "make_env_v0", "make_vector_env", "make_vector_env_v0"]

SPEC = FamilySpec(
    name="cooperative",
    env_name="CLScheduling",
    title="cooperative localization: which relative measurements to fuse (Chen & Kia 2022)",
    env_class="selenv.families.cooperative.env:CLSchedulingEnv",
    v0_kwargs={"preset": "dense"},
    views="selenv.families.cooperative.view:VIEWS",
    checkpoint="cl_scheduling_ppo.zip",
    policies="selenv.families.cooperative.policies:POLICIES",
    agent_modules=(
        "selenv.families.cooperative.agents",
        "selenv.families.cooperative.rollout",
        "selenv.families.cooperative.fast_rollout",
    ),
    vector_class="selenv.families.cooperative.vector:CLSchedulingVectorEnv",
)
make_env, make_env_v0 = env_factories(SPEC)
make_vector_env, make_vector_env_v0 = vector_factories(SPEC)
