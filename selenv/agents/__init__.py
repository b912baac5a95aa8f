"""Classic heuristics behind one agent protocol; importing registers them by name.

``selenv.agents.make(name, env_id)`` builds one; ``AGENTS`` lists them; the solvers in
:mod:`selenv.agents.fim_solvers` work on raw arrays without any env. Each family's agents live
in its folder (its record's ``agent_modules``) and are imported here; the learned agents are
registered from the families' policy records (:mod:`selenv.agents.learned`).
"""

from __future__ import annotations

import importlib

from selenv.agents.base import (
    AGENTS,
    Agent,
    AgentSpec,
    PlanAgent,
    agents_for,
    default_agents,
    make,
    parse_spec,
    register_adapted,
    register_agent,
)
from selenv.agents.learned import register_policies
from selenv.agents.multiagent import RandomMaskedPolicy
from selenv.families import FAMILIES

__all__ = [
    "AGENTS",
    "Agent",
    "AgentSpec",
    "PlanAgent",
    "agents_for",
    "default_agents",
    "make",
    "parse_spec",
    "register_agent",
]

# every PettingZoo module of every family: the uniform masked policy
_MODULES = tuple(m for f in FAMILIES for m in f.multiagent_modules)
register_agent(AgentSpec("random", _MODULES, RandomMaskedPolicy, "uniform over each agent's mask"))
for _family in FAMILIES:
    for _module in _family.agent_modules:
        importlib.import_module(_module)  # registers the family's agents
# the shipped learned policies: the families' PolicySpec records, their old names and `learned`
register_policies()
# versions with another action space: every agent of the version before, through its adapter
register_adapted()
