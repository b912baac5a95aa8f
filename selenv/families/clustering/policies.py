"""The shipped learned policies of the clustering family (records; standings in the JSONs)."""

from __future__ import annotations

from selenv.families.policy import PolicySpec

_ID = "selenv/ReceiverClustering-v1"
_MODULE = "selenv.multiagent.receiver_clustering_v1"

POLICIES = (
    PolicySpec(
        name="ppo",
        plays=(_ID,),
        factory="selenv.learned.rl.agent:make_ppo_agent",
        kwargs={"env_id": _ID, "verify_top_k": 8},
        checkpoint="receiver_clustering_ppo.zip",
        method="distillation",
        description="edit-ranking policy (ranking-trained, one DAgger round): its 8 best edits "
        "costed, the best improving one played (ppo:verify_top_k=K for K edits, 0 for its top "
        "edit unverified)",
        trainer="python -m selenv.train.train_clustering_dagger --config "
        "configs/receiver_clustering_ppo.toml",
        budget="8 cost evaluations per decision",
        valid={"preset": ("paper", "multipath"), "n_agents": (30,)},  # trained, verified
        aliases={"ppo_top8": {}, "ppo_top4": {"verify_top_k": 4}},
    ),
    PolicySpec(
        name="ppo",
        plays=(_MODULE,),
        factory="selenv.learned.families.clustering:make_clustering_marl_learned",
        checkpoint="receiver_clustering_ppo.zip",
        method="distillation",
        description="the ReceiverClustering-v1 edit ranking on the joint state: its 8 best edits "
        "costed, the best improving one played by the receivers concerned (ppo:top_k=K; "
        "ppo:greedy_every=G runs greedy's full search every G steps)",
        trainer="python -m selenv.train.train_clustering_dagger --config "
        "configs/receiver_clustering_ppo.toml",
        budget="8 cost evaluations per decision",
        valid={"preset": ("paper", "multipath"), "n_agents": (30,)},
    ),
    PolicySpec(
        name="rllib",
        plays=(_MODULE,),
        factory="selenv.learned.rl.rllib_agent:make_rllib_policy",
        kwargs={"env_id": _MODULE},
        checkpoint="rllib_receiver_clustering_v1.json",
        method="rllib",
        description="RLlib-trained shared module (rllib:path=runs/rllib_<env>/policy.json for "
        "your own export)",
        trainer="python -m selenv.train.train_rllib_marl --config "
        "configs/rllib_receiver_clustering_v1.toml",
        budget="one forward pass per receiver per step",
        retired="the shipped module plays exactly `stay` (every receiver keeps its cluster) and "
        "never beats greedy: use `learned`",
    ),
)
