"""The shipped learned policies of the FIM family (records; their standings live in the JSONs)."""

from __future__ import annotations

from selenv.families.policy import PolicySpec

_ID = "selenv/FIMSelection-v1"
_MODULE = "selenv.multiagent.fim_selection_v0"
_PRESETS = (
    "example1",
    "example1_moving",
    "example2",
    "example2_moving",
    "example3",
    "example3_moving",
)

POLICIES = (
    PolicySpec(
        name="ppo",
        plays=(_ID,),
        factory="selenv.learned.rl.agent:make_ppo_agent",
        kwargs={"env_id": _ID, "shipped": "fim_selection_ppo_general.zip"},
        checkpoint="fim_selection_ppo_general.zip",
        method="rl",
        description="one MaskablePPO candidate-scoring policy for every Kirchner preset and "
        "budget (d-independent invariant view)",
        trainer="python -m selenv.train.train_fim_ppo --config "
        "configs/fim_selection_ppo_general.toml",
        budget="one forward pass of a 64x64 MLP per candidate per pick",
        valid={"preset": _PRESETS, "budget": (5, 10, 15, 20), "n_candidates": (50, 100, 200)},
        aliases={"ppo_general": {}},
    ),
    PolicySpec(
        name="ppo_swap",
        plays=(_ID,),
        factory="selenv.learned.families.fim:make_fim_learned",
        checkpoint="fim_selection_ppo_general.zip",
        method="learned_search",
        description="swap's local search from greedy's picks and from a start the ppo policy "
        "makes (its first 2 picks, greedy completing), the better result played: never below "
        "swap (ppo_swap:starts=policy for the policy start alone)",
        trainer="python -m selenv.train.train_fim_ppo --config "
        "configs/fim_selection_ppo_general.toml",
        budget="two swap searches and 2 policy forward passes per episode (a plan)",
        valid={"preset": _PRESETS, "budget": (5, 10, 15, 20), "n_candidates": (50, 100, 200)},
    ),
    PolicySpec(
        name="ppo",
        plays=(_MODULE,),
        factory="selenv.learned.rl.marl:make_shared_ppo",
        checkpoint="fim_marl_ppo.zip",
        method="rl",
        description="shared (parameter-sharing) policy trained in cooperative mode, each agent "
        "on its own observation",
        trainer="python -m selenv.train.train_fim_marl --config configs/fim_marl_ppo.toml",
        budget="one forward pass per acting agent per step",
        valid={"mode": ("cooperative", "independent")},  # trained cooperative, verified both
    ),
    PolicySpec(
        name="ppo_independent",
        plays=(_MODULE,),
        factory="selenv.learned.rl.marl:make_shared_ppo",
        kwargs={"shipped": "fim_marl_ppo_independent.zip"},
        checkpoint="fim_marl_ppo_independent.zip",
        method="rl",
        description="shared policy trained in independent mode, each agent on its own observation",
        trainer="python -m selenv.train.train_fim_marl --config "
        "configs/fim_marl_ppo_independent.toml",
        budget="one forward pass per acting agent per step",
        valid={"mode": ("independent", "cooperative")},  # trained independent, verified both
    ),
    PolicySpec(
        name="rllib",
        plays=(_MODULE,),
        factory="selenv.learned.rl.rllib_agent:make_rllib_policy",
        kwargs={"env_id": _MODULE},
        checkpoint="rllib_fim_selection_v0.json",
        method="rllib",
        description="RLlib-trained shared module on each agent's own candidate view "
        "(rllib:path=runs/rllib_<env>/policy.json for your own export)",
        trainer="python -m selenv.train.train_rllib_marl --config "
        "configs/rllib_fim_selection_v0.toml",
        budget="one forward pass per acting agent per step",
        valid={"mode": ("cooperative", "independent")},  # trained cooperative, verified both
    ),
)
