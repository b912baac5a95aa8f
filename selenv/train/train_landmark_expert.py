"""Expert iteration on ``LandmarkSelection-v0``: distil the landmark ``rollout`` reference.

The same DAgger loop as :mod:`selenv.train.train_cl_expert`, with
:func:`selenv.learned.rl.expert.collect_landmark_rollout_labels`: every pick is labelled by the
landmark ``rollout`` (top-4 K-subsets by one-step gain plus brute force's own, 10 future
filter updates of brute force on the forecast covariances); a landmark's label is the best
score of a candidate subset containing it. The policy starts from the shipped landmark
checkpoint and keeps its view; the result is benchmarked against ``brute_force`` and
``rollout`` on the held-out seeds, and written into the checkpoint's metadata.

    python -m selenv.train.train_landmark_expert --out runs/landmark_expert.zip
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from selenv.learned.config import parse_config
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS
from selenv.learned.rl.expert import LANDMARK_ID, collect_landmark_rollout_labels
from selenv.train.train_cl_expert import run_expert_iteration


@dataclass
class Config:
    """Every field is a ``--kebab-case`` option."""

    checkpoint: str = str(DEFAULT_CHECKPOINTS[LANDMARK_ID])
    out: str = "runs/landmark_expert.zip"
    force: bool = False
    env_kwargs: str = "{}"
    rounds: int = 3
    states_per_round: int = 3000
    top_k: int = 4
    horizon: int = 10
    explore: float = 0.05
    epochs: int = 15
    learning_rate: float = 5e-4
    temperature: float = 0.1
    workers: int = 2
    seed: int = 0
    progress: bool = True
    eval_episodes: int = 30
    eval_seed: int = 1000


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Collect, fit (per round), save, evaluate; return the checkpoint's metadata."""
    cfg = parse_config(Config, argv, (__doc__ or "").split("\n")[0])
    json.loads(cfg.env_kwargs)
    return run_expert_iteration(
        cfg,
        argv,
        LANDMARK_ID,
        collect_landmark_rollout_labels,
        "selenv.train.train_landmark_expert",
        "brute_force",
    )


if __name__ == "__main__":
    main()
