"""Expert iteration on ``LandmarkSelection-v1``: distil the landmark ``rollout`` reference.

The same DAgger loop (:mod:`selenv.learned.rl.distill`) as
:mod:`selenv.train.train_cl_expert`, with
:func:`selenv.learned.rl.expert.collect_landmark_rollout_labels`: every pick is labelled by the
landmark ``rollout`` (top-4 K-subsets by one-step gain plus brute force's own, 10 future
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
from pathlib import Path
from typing import Any

from selenv.learned.config import arg, parse_config
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS
from selenv.learned.rl.distill import check_expert_outputs, expert_outputs, run_expert_iteration
from selenv.learned.rl.expert import (
    LANDMARK_ID,
    LANDMARK_LABELLERS,
    collect_landmark_rollout_labels,
)
from selenv.learned.rl.ranking import check_ranking_sizes
from selenv.learned.trainer import output_lock, run_arg, run_cli

SCRIPT = "selenv.train.train_landmark_expert"


@dataclass
class Config:
    """Every field is a ``--kebab-case`` option."""

    checkpoint: str = arg(str(DEFAULT_CHECKPOINTS[LANDMARK_ID]), "starting weights (a .zip)")
    out: str = arg(
        "runs/train_landmark_expert/policy.zip",
        "the trained checkpoint (.zip); also writes its .json, <out>_round<r>.zip/.json per "
        "round and <out>.bench.json",
    )
    force: bool = arg(False, "overwrite existing outputs of --out")
    env_kwargs: str = arg("{}", "JSON object of gymnasium.make keyword arguments")
    rounds: int = arg(3, "DAgger rounds (round 0 follows the labeller, later ones the policy)")
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
    epochs: int = arg(15, "epochs of the ranking fit (ListNet) per round")
    learning_rate: float = arg(5e-4, "Adam learning rate of the ranking fit")
    temperature: float = arg(
        0.1, "temperature T of the ListNet targets softmax(-dJ / (T * spread of dJ))"
    )
    workers: int = arg(2, "labelling worker processes")
    seed: int = arg(0, "seed of the labelling episodes (round r: 100 * seed + r) and the fit")
    progress: bool = arg(True, "show tqdm bars")
    eval_episodes: int = arg(
        30, "held-out episodes of the selenv bench evaluation after training (0: none)"
    )
    eval_seed: int = arg(1000, "seed of the first held-out episode (then +1, +2, ...)")
    checkpoint_every: int = arg(
        5,
        "fit epochs between the periodic state <out stem>.last.zip (+ .json) within a round; it "
        "is also written after every collection and round, and on SIGINT / SIGTERM (0: only "
        "then)",
    )
    allow_large: bool = arg(
        False,
        "lift the ceilings of --rounds (100), --states-per-round / --states (10^6), --epochs "
        "(10,000) and --eval-episodes (100,000)",
    )
    resume: str = arg(
        "",
        "continue an interrupted run (same options) from its <out stem>.last.zip or a round "
        "checkpoint <out>_round<r>.zip: weights, labels so far, round, fit epoch and optimizer",
    )
    max_minutes: float | None = run_arg(
        "max_minutes", None, unit="a collection, a fit epoch or a round"
    )


def parse_args(argv: list[str] | None = None) -> Config:
    """The run's :class:`Config` from the command line (and ``--config FILE``)."""
    return parse_config(Config, argv, (__doc__ or "").split("\n")[0], script=SCRIPT)


def outputs(cfg: Config) -> list[Path]:
    """The files the run writes."""
    return expert_outputs(cfg)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Collect, fit (per round), save, evaluate; return the checkpoint's metadata."""
    cfg = parse_args(argv)
    check_ranking_sizes(cfg)  # every size in range and under its ceiling, before any work
    check_expert_outputs(cfg, f"python -m {SCRIPT}")
    with output_lock(cfg.out, f"python -m {SCRIPT}"):  # one run per --out
        return run_expert_iteration(
            cfg,
            argv,
            LANDMARK_ID,
            partial(collect_landmark_rollout_labels, labeller=cfg.labeller),
            SCRIPT,
            "brute_force",
        )


def cli() -> None:
    """Console-script entry point (same options as ``main``).

    Exit code 0 after a run, 2 on a usage error or a busy ``--out``, 1 on an I/O failure,
    130 / 143 after SIGINT / SIGTERM, 75 at ``--max-minutes``.
    """
    raise SystemExit(run_cli(main, f"python -m {SCRIPT}"))


if __name__ == "__main__":
    cli()
