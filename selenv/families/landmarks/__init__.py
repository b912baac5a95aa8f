"""The ``LandmarkSelection`` family.

K of N angle-of-arrival landmarks per EKF step (Soubaras & Chahbazian 2023).

:data:`SPEC` is its record; the folder's modules are listed in :mod:`selenv.families.spec`.
"""

from __future__ import annotations

from selenv.families.spec import FamilySpec, env_factories, vector_factories

__all__ = ["SPEC", "make_env", "make_env_v0", "make_vector_env", "make_vector_env_v0"]

SPEC = FamilySpec(
    name="landmarks",
    env_name="LandmarkSelection",
    title="K of N angle-of-arrival landmarks per EKF step (Soubaras & Chahbazian 2023)",
    env_class="selenv.families.landmarks.env:LandmarkSelectionEnv",
    views="selenv.envs.views:IDENTITY_VIEWS",
    checkpoint="landmark_selection_ppo.zip",
    policies="selenv.families.landmarks.policies:POLICIES",
    agent_modules=(
        "selenv.families.landmarks.agents",
        "selenv.families.landmarks.rollout",
        "selenv.families.landmarks.fast_rollout",
    ),
    vector_class="selenv.families.landmarks.vector:LandmarkSelectionVectorEnv",
)
make_env, make_env_v0 = env_factories(SPEC)
make_vector_env, make_vector_env_v0 = vector_factories(SPEC)
