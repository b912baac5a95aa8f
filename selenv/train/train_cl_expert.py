"""Expert iteration on ``CLScheduling-v1``: distil the non-myopic ``rollout`` into the policy.

Rounds of DAgger (the loop of :mod:`selenv.learned.rl.distill`, the labels of
:func:`selenv.learned.families.cooperative.collect_cl_rollout_labels`): round 0 labels the
states the ``rollout`` reference visits, every later round the states the current policy
visits; every labelled decision carries rollout's score of stop and of its ``top_k`` pairs;
the candidate-scoring policy's logits are fitted to all labels so far (ListNet,
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
from typing import Any

from selenv.learned.config import arg
from selenv.learned.families.cooperative import CL_ID, collect_cl_rollout_labels
from selenv.learned.rl import distill
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS
from selenv.learned.rl.distill import (
    ExpertConfig,
    check_expert_outputs,
    evaluate_with_bench,
    expert_outputs,
    expert_run,
    labels_path,
    round_path,
    run_expert_iteration,
    state_files,
)
from selenv.learned.trainer import Script

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
class Config(ExpertConfig):
    """The options of :class:`~selenv.learned.rl.distill.ExpertConfig`, CL defaults."""

    checkpoint: str = str(DEFAULT_CHECKPOINTS[CL_ID])
    out: str = "runs/train_cl_expert/policy.zip"
    env_kwargs: str = arg(
        "{}", "JSON object of gymnasium.make keyword arguments ({}: the benchmark preset)"
    )
    view: str = arg(
        "cl_pairs_fused_top3", "candidate view: the labeller's candidate set (stop + top-3 by gain)"
    )
    top_k: int = arg(3, "the labeller (the bench's rollout reference) scores stop and its top-k")


RUN = Script(SCRIPT, Config, __doc__)


#: the run's :class:`Config` from the command line (and ``--config FILE``)
parse_args = RUN.parse


#: the files the run writes
outputs = expert_outputs


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Collect, fit (per round), save, evaluate; return the checkpoint's metadata."""
    cfg = parse_args(argv)
    with expert_run(cfg, RUN.prog):  # sizes and outputs checked, one run per --out
        return run_expert_iteration(cfg, argv, CL_ID, collect_cl_rollout_labels, SCRIPT, "greedy")


#: the console script: ``main`` with the exit codes of :func:`selenv.learned.trainer.run_cli`
#: (0; 2 usage error or busy ``--out``; 1 I/O failure; 130 / 143 / 75 stopped and saved)
cli = RUN.command(main)


if __name__ == "__main__":
    cli()
