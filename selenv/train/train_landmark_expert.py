"""Expert iteration on ``LandmarkSelection-v1``: distil the landmark ``rollout`` reference.

The same DAgger loop (:mod:`selenv.learned.rl.distill`) as
:mod:`selenv.train.train_cl_expert`, with
:func:`selenv.learned.families.landmarks.collect_landmark_rollout_labels`: every pick is labelled
by the landmark ``rollout`` (top-4 K-subsets by one-step gain plus brute force's own, 10 future
filter updates of brute force on the forecast covariances); a landmark's label is the best
score of a candidate subset containing it. The policy starts from the shipped landmark
checkpoint and keeps its view; the result is benchmarked against ``brute_force`` and
``rollout`` on the held-out seeds, and written into the checkpoint's metadata.

    python -m selenv.train.train_landmark_expert   # -> runs/train_landmark_expert/policy.zip

Stops and resumes as :mod:`selenv.train.train_cl_expert` does (``--checkpoint-every``,
``--max-minutes``, ``--resume``, ``<out stem>.last.zip``).

``--labeller fast_rollout`` labels with the same lookahead on a shortlist of 6 landmarks
(:mod:`selenv.families.landmarks.fast_rollout`), 11-15x cheaper per label.

The shipped ``checkpoints/landmark_selection_ppo.zip`` (``ppo``):
``configs/landmark_selection_ppo.toml`` (3 rounds x 3000 rollout labels, ~6 min).
``checkpoints/landmark_selection_ppo_distilled.zip`` (``ppo_distilled``): two runs with
``--labeller fast_rollout``, 4 x 30,000 then 4 x 50,000 labels (~33 min),
``configs/landmark_selection_ppo_distilled.toml``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any

from selenv.learned.config import arg
from selenv.learned.families.landmarks import (
    LANDMARK_ID,
    LANDMARK_LABELLERS,
    collect_landmark_rollout_labels,
)
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS
from selenv.learned.rl.distill import (
    ExpertConfig,
    expert_outputs,
    expert_run,
    run_expert_iteration,
)
from selenv.learned.trainer import Script

SCRIPT = "selenv.train.train_landmark_expert"


@dataclass
class Config(ExpertConfig):
    """The options of :class:`~selenv.learned.rl.distill.ExpertConfig`, landmark defaults."""

    checkpoint: str = str(DEFAULT_CHECKPOINTS[LANDMARK_ID])
    out: str = "runs/train_landmark_expert/policy.zip"
    states_per_round: int = arg(
        3000,
        "labelled picks collected per round (the shipped ppo: 3 rounds x 3000 rollout labels, "
        "~6 min; ppo_distilled: 4 x 30,000 then 4 x 50,000 fast_rollout labels, ~33 min)",
    )
    labeller: str = arg(
        "rollout",
        "the labelling reference: 'rollout', or 'fast_rollout' (the same forecast on a "
        "shortlist of the 6 landmarks with the largest single gain, 11-15x cheaper per "
        "label)",
        choices=LANDMARK_LABELLERS,
    )
    top_k: int = arg(
        4,
        "the labeller (landmark rollout) scores the top-k subsets by one-step gain "
        "plus brute force's own",
    )
    horizon: int = arg(10, "future filter updates the labeller simulates")
    explore: float = arg(0.05, "random pick probability on the labelling trajectories")
    epochs: int = 15


RUN = Script(SCRIPT, Config, __doc__)


#: the run's :class:`Config` from the command line (and ``--config FILE``)
parse_args = RUN.parse


#: the files the run writes
outputs = expert_outputs


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Collect, fit (per round), save, evaluate; return the checkpoint's metadata."""
    cfg = parse_args(argv)
    with expert_run(cfg, RUN.prog):  # sizes and outputs checked, one run per --out
        return run_expert_iteration(
            cfg,
            argv,
            LANDMARK_ID,
            partial(collect_landmark_rollout_labels, labeller=cfg.labeller),
            SCRIPT,
            "brute_force",
        )


#: the console script: ``main`` with the exit codes of :func:`selenv.learned.trainer.run_cli`
#: (0; 2 usage error or busy ``--out``; 1 I/O failure; 130 / 143 / 75 stopped and saved)
cli = RUN.command(main)


if __name__ == "__main__":
    cli()
