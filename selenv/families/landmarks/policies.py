"""The shipped learned policies of the landmark family (records; standings in the JSONs)."""

from __future__ import annotations

from selenv.families.policy import PolicySpec

_ID = "selenv/LandmarkSelection-v1"
_VALID = {"n_landmarks": (30,), "k": (2,)}  # trained at horizon 100, verified at 300

POLICIES = (
    PolicySpec(
        name="ppo_search",
        plays=(_ID,),
        factory="selenv.learned.families.landmarks:make_landmark_ppo_search",
        checkpoint="landmark_selection_ppo.zip",
        method="learned_search",
        description="fast_rollout's lookahead on the shortlist the shipped ppo policy ranks "
        "first (ppo_search:checkpoint=... for another policy)",
        trainer="python -m selenv.train.train_landmark_expert --config "
        "configs/landmark_selection_ppo.toml",
        baseline="brute_force",
        budget="a policy forward pass and a batched 10-step lookahead on a 6-landmark "
        "shortlist; at most 2x brute force's decision time",
        max_decision_ratio=2.0,
        valid=_VALID,
    ),
    PolicySpec(
        name="ppo_distilled",
        plays=(_ID,),
        factory="selenv.learned.rl.agent:make_ppo_agent",
        kwargs={"env_id": _ID, "shipped": "landmark_selection_ppo_distilled.zip"},
        checkpoint="landmark_selection_ppo_distilled.zip",
        method="distillation",
        description="MaskablePPO candidate-scoring policy distilled from fast_rollout (320k "
        "labelled picks); no lookahead",
        trainer="python -m selenv.train.train_landmark_expert --config "
        "configs/landmark_selection_ppo_distilled.toml",
        baseline="brute_force",
        budget="one forward pass per landmark per pick; at most 2x brute force's decision time",
        max_decision_ratio=2.0,
        valid=_VALID,
    ),
    PolicySpec(
        name="ppo",
        plays=(_ID,),
        factory="selenv.learned.rl.agent:make_ppo_agent",
        kwargs={"env_id": _ID},
        checkpoint="landmark_selection_ppo.zip",
        method="distillation",
        description="MaskablePPO candidate-scoring policy (expert iteration on rollout labels); "
        "no lookahead",
        trainer="python -m selenv.train.train_landmark_expert --config "
        "configs/landmark_selection_ppo.toml",
        baseline="brute_force",
        budget="one forward pass per landmark per pick; at most 2x brute force's decision time",
        max_decision_ratio=2.0,
        valid=_VALID,
    ),
)
