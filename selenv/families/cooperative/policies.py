"""The shipped learned policies of the cooperative-localization family (standings in the JSONs)."""

from __future__ import annotations

from selenv.families.policy import PolicySpec

_ID = "selenv/CLScheduling-v1"

POLICIES = (
    PolicySpec(
        name="cem",
        plays=(_ID,),
        factory="selenv.learned.families.cooperative:make_cl_cem",
        checkpoint="cl_scheduling_cem.json",
        method="cem",
        description="a one-filter-step lookahead of greedy plus a learned correction from 12 "
        "pair features, trained by the cross-entropy method on episode returns "
        "(cem:checkpoint=... for your own)",
        trainer="python -m selenv.train.train_cl_cem --config configs/cl_scheduling_cem.toml",
        budget="one filter step of greedy ahead per candidate pair",
        valid={"n_agents": (6,)},
    ),
    PolicySpec(
        name="ppo",
        plays=(_ID,),
        factory="selenv.learned.rl.agent:make_ppo_agent",
        kwargs={"env_id": _ID},
        checkpoint="cl_scheduling_ppo.zip",
        method="rl",
        description="MaskablePPO pair-scoring policy (ppo:checkpoint=... for your own)",
        trainer="python -m selenv.train.train_cl_ppo --config configs/cl_scheduling_ppo.toml",
        budget="one forward pass per candidate pair",
        retired="the shipped policy plays greedy's schedule (it ties greedy): use `learned`",
    ),
)
