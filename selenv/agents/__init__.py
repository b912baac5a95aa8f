"""Classic heuristics behind one agent protocol; importing registers them by name.

``selenv.agents.make(name, env_id)`` builds one; ``AGENTS`` lists them; the solvers in
:mod:`selenv.agents.fim_solvers` work on raw arrays without any env.
"""

from __future__ import annotations

from selenv.agents import cl as _cl  # noqa: F401  (registers the CL scheduling agents)
from selenv.agents import clustering as _clustering  # noqa: F401  (registers clustering agents)
from selenv.agents import clustering_rollout as _clustering_rollout  # noqa: F401
from selenv.agents import fim as _fim  # noqa: F401  (registers the FIM agents)
from selenv.agents import landmarks as _landmarks  # noqa: F401  (registers landmark agents)
from selenv.agents import multiagent as _multiagent  # noqa: F401  (registers the PettingZoo agents)
from selenv.agents import rollout as _rollout  # noqa: F401  (registers the rollout agents)
from selenv.agents.base import (
    AGENTS,
    Agent,
    AgentSpec,
    PlanAgent,
    agents_for,
    make,
    parse_spec,
    register_agent,
)

__all__ = [
    "AGENTS",
    "Agent",
    "AgentSpec",
    "PlanAgent",
    "agents_for",
    "make",
    "parse_spec",
    "register_agent",
]
