"""Expert iteration on ``CLScheduling-v1``: distil the non-myopic ``rollout`` into the policy.

Rounds of DAgger (the loop of :mod:`selenv.learned.rl.distill`, the labels of
:mod:`selenv.learned.rl.expert`): round 0 labels the states the ``rollout``
reference visits, every later round the states the current policy visits; every labelled
decision carries rollout's score of stop and of its ``top_k`` pairs; the candidate-scoring
policy's logits are fitted to all labels so far (ListNet,
:func:`selenv.learned.rl.ranking.fit_ranking`).
The policy starts from ``--checkpoint`` (default: the shipped CL policy, a softened greedy on
the previewed fused gains) and plays in the ``cl_pairs_fused_top3`` view: the candidates
rollout considers (stop and the three pairs of largest previewed gain), ranked by the
network. At play time it costs one greedy preview plus one network evaluation per decision
instead of rollout's ``top_k + 1`` simulated trajectories.

The result is evaluated by ``selenv bench`` against ``greedy`` and ``rollout`` on the
held-out seeds ``--eval-seed .. --eval-seed + --eval-episodes - 1`` (training episodes use
seeds >= 10**6), and the bench's paired statistics and the exact command are written into
the checkpoint's metadata.

    python -m selenv.train.train_cl_expert   # -> runs/train_cl_expert/policy.zip (~25 min, 2 cores)

Outputs (all refused if they exist, unless ``--force``): ``<out>.zip`` + ``.json``, every
round's ``<out>_round<r>.zip`` + ``.json`` with the labels it collected,
``<out>_round<r>.labels.npz``, and, with ``--eval-episodes``, ``<out>.bench.json``. Each
checkpoint and its JSON are written as an atomic pair (the JSON records the zip's
``checkpoint_sha256`` and the labels files' SHA-256).

Stopping and resuming (a stopped run loses at most the step in progress):

* the run's state ``<out stem>.last.zip`` (+ ``.json``, and ``.fit.pt``, the fit's Adam
  state, mid-fit) is written after every collection, every ``--checkpoint-every`` fit epochs
  and every round (``"complete": false``), and removed when the run completes;
* SIGINT / SIGTERM while labelling abandons the round's labels (the worker processes stop at
  once; they also die with this process after ``kill -9``); during a fit the current epoch
  completes. The state is saved with ``"interrupted": "SIGINT"`` / ``"SIGTERM"`` and the
  command exits 130 / 143 with one line naming the file and the ``--resume`` option; a
  second signal abandons at once (the files on disk stay intact);
* ``--max-minutes M`` stops the same way at the first collection, fit epoch or round that
  ends after ``M`` minutes (``"interrupted": "max-minutes"``, exit 75);
* ``--resume <out stem>.last.zip`` (or a round checkpoint ``<out>_round<r>.zip``), with the
  options of the interrupted run, restores the weights, the rounds done, the labels so far
  (each file checked against its recorded SHA-256 and its array headers before it is read),
  the fit's epoch and optimizer and the random generators, and ends with the same weights as
  an uninterrupted run. Other options (seed, env, rounds, ...) or a checkpoint without a
  resume state are refused (exit 2, one line naming the difference).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from selenv.learned.config import arg, parse_config
from selenv.learned.rl import distill
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS
from selenv.learned.rl.distill import (
    check_expert_outputs,
    evaluate_with_bench,
    expert_outputs,
    labels_path,
    round_path,
    run_expert_iteration,
    state_files,
)
from selenv.learned.rl.expert import CL_ID, collect_cl_rollout_labels
from selenv.learned.rl.ranking import check_ranking_sizes
from selenv.learned.trainer import output_lock, run_arg, run_cli

__all__ = [
    "Config",
    "check_expert_outputs",
    "cli",
    "evaluate_with_bench",
    "expert_outputs",
    "labels_path",
    "main",
    "outputs",
    "parse_args",
    "round_path",
    "run_expert_iteration",
    "state_files",
]

SCRIPT = "selenv.train.train_cl_expert"
#: options that may differ between an interrupted run and its --resume
_FREE = distill.FREE_OPTIONS


@dataclass
class Config:
    """Every field is a ``--kebab-case`` option."""

    checkpoint: str = arg(str(DEFAULT_CHECKPOINTS[CL_ID]), "starting weights (a .zip)")
    out: str = arg(
        "runs/train_cl_expert/policy.zip",
        "the trained checkpoint (.zip); also writes its .json, <out>_round<r>.zip/.json per "
        "round and <out>.bench.json",
    )
    force: bool = arg(False, "overwrite existing outputs of --out")
    env_kwargs: str = arg(
        "{}", "JSON object of gymnasium.make keyword arguments ({}: the benchmark preset)"
    )
    view: str = arg(
        "cl_pairs_fused_top3", "candidate view: the labeller's candidate set (stop + top-3 by gain)"
    )
    rounds: int = arg(3, "DAgger rounds (round 0 follows the labeller, later ones the policy)")
    states_per_round: int = arg(1500, "labelled decisions collected per round")
    top_k: int = arg(3, "the labeller (the bench's rollout reference) scores stop and its top-k")
    horizon: int = arg(5, "filter steps the labeller simulates after the current one")
    explore: float = arg(0.05, "random action probability on the labelling trajectories")
    epochs: int = arg(20, "epochs of the ranking fit (ListNet) per round")
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
        return run_expert_iteration(cfg, argv, CL_ID, collect_cl_rollout_labels, SCRIPT, "greedy")


def cli() -> None:
    """Console-script entry point (same options as ``main``).

    Exit code 0 after a run, 2 on a usage error or a busy ``--out``, 1 on an I/O failure,
    130 / 143 after SIGINT / SIGTERM, 75 at ``--max-minutes``.
    """
    raise SystemExit(run_cli(main, f"python -m {SCRIPT}"))


if __name__ == "__main__":
    cli()
