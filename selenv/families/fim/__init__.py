"""The ``FIMSelection`` family.

Heterogeneous measurement selection by Fisher information (Kirchner et al. 2020).

:data:`SPEC` is its record; the folder's modules are listed in :mod:`selenv.families.spec`.
"""

from __future__ import annotations

from selenv.families.spec import FamilySpec, env_factories, vector_factories

__all__ = ["SPEC", "make_env", "make_env_v0", "make_vector_env", "make_vector_env_v0"]

SPEC = FamilySpec(
    name="fim",
    env_name="FIMSelection",
    title="heterogeneous measurement selection by Fisher information (Kirchner et al. 2020)",
    env_class="selenv.families.fim.env:FIMSelectionEnv",
    v0_presets={"example2": "example2_moving", "example3": "example3_moving"},
    views="selenv.families.fim.view:VIEWS",
    checkpoint="fim_selection_ppo.zip",
    policies="selenv.families.fim.policies:POLICIES",
    agent_modules=(
        "selenv.families.fim.agents",
        "selenv.families.fim.multiagent_agents",
    ),
    multiagent_module="selenv.multiagent.fim_selection_v0",
    vector_class="selenv.families.fim.vector:FIMSelectionVectorEnv",
    return_bound="selenv.families.fim.bounds:return_bound",
)
make_env, make_env_v0 = env_factories(SPEC)
make_vector_env, make_vector_env_v0 = vector_factories(SPEC)
