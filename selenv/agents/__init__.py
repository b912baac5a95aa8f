"""Classic heuristics behind one agent protocol; importing registers them by name.

``selenv.agents.make(name, env_id)`` builds one; ``AGENTS`` lists them; the solvers in
:mod:`selenv.agents.fim_solvers` work on raw arrays without any env. Each family's agents live
in its folder (its record's ``agent_modules``) and are imported here; the ``ppo`` agent of every
family with a shipped checkpoint is registered from the record.
"""

from __future__ import annotations

import importlib

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
from selenv.agents.multiagent import RandomMaskedPolicy
from selenv.families import FAMILIES

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

# every PettingZoo module of every family: the uniform masked policy
_MODULES = tuple(m for f in FAMILIES for m in f.multiagent_modules)
register_agent(AgentSpec("random", _MODULES, RandomMaskedPolicy, "uniform over each agent's mask"))
for _family in FAMILIES:
    for _module in _family.agent_modules:
        importlib.import_module(_module)  # registers the family's agents
    if _family.checkpoint is not None:  # the learned policy lives above this layer: lazy
        register_agent(
            AgentSpec(
                "ppo",
                (_family.current_id,),
                "selenv.learned.rl.agent:make_ppo_agent",
                f"{_family.ppo_description} (checkpoints/{_family.checkpoint})",
                kwargs={"env_id": _family.current_id},
                all_versions=False,  # the shipped checkpoint was trained on this version
                learned=True,
            )
        )
    for _name, _file, _text in _family.more_policies:
        register_agent(
            AgentSpec(
                _name,
                (_family.current_id,),
                "selenv.learned.rl.agent:make_ppo_agent",
                f"{_text} (checkpoints/{_file})",
                kwargs={"env_id": _family.current_id, "shipped": _file},
                all_versions=False,
                learned=True,
            )
        )
# an RLlib-trained shared module (selenv.learned.rl.rllib_agent, lazy: selenv never imports ray)
for _family in FAMILIES:
    if _family.multiagent_module is not None:
        register_agent(
            AgentSpec(
                "rllib",
                (_family.multiagent_module,),
                "selenv.learned.rl.rllib_agent:make_rllib_policy",
                "RLlib-trained shared module on each agent's own candidate view "
                "(rllib:path=runs/rllib_<env>/policy.json; selenv/train/train_rllib_marl.py)",
                kwargs={"env_id": _family.multiagent_module},
                all_versions=False,  # a shipped module was trained on the current version
                learned=True,
            )
        )
