r"""Plot RLlib training records (``<out>.metrics.json`` of ``train_rllib_marl``) side by side.

Three panels against the env steps sampled: the learner's mean PPO policy loss (the last
minibatch of each iteration: with advantages standardised over the steps in the loss it starts
at 0 and an update drives it down, a positive level means the real advantages are off-centre),
the policy's entropy, and the mean training return (summed over agents, as RLlib reports it),
smoothed over ``--window`` iterations. Usage::

    .venv/bin/python scripts/plot_rllib_training.py \
        "batch-wide (RLlib)=docs/bench/rllib_training/batchwide_100k.metrics.json" \
        "masked=docs/bench/rllib_training/masked_100k.metrics.json" \
        "masked, shipped=docs/bench/rllib_training/shipped_200k.metrics.json" \
        --title "RLlib PPO on fim_selection_v0: advantage standardisation" \
        --out docs/figures/rllib_advantage_norm.png

Each run is ``LABEL=PATH``. The figure is written atomically (the format from the suffix of
``--out``). A file that is not a list of iteration records is refused with one line naming it
(exit 2).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from selenv.atomic import save_figure
from selenv.exits import UsageError, guarded_main

PROG = "scripts/plot_rllib_training.py"
#: (record key, panel title)
PANELS = (
    ("policy_loss", "PPO policy loss (last minibatch)"),
    ("entropy", "policy entropy (nats)"),
    ("episode_return_mean_sum_over_agents", "training return, summed over agents"),
)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line: ``LABEL=PATH`` runs, ``--out``, ``--window`` and ``--title``."""
    parser = argparse.ArgumentParser(prog=PROG, description=(__doc__ or "").splitlines()[0])
    parser.add_argument("runs", nargs="+", help="LABEL=PATH of a train_rllib_marl metrics file")
    parser.add_argument("--out", default="rllib_training.png", help="the figure file")
    parser.add_argument("--window", type=int, default=5, help="moving-average width (iterations)")
    parser.add_argument("--title", default="RLlib PPO training", help="the figure's title")
    args = parser.parse_args(argv)
    if args.window < 1:
        raise UsageError(f"--window must be >= 1, got {args.window}")
    return args


def read_run(spec: str) -> tuple[str, list[dict[str, Any]]]:
    """``LABEL=PATH`` -> the label and the records, checked (``UsageError`` naming the file)."""
    label, sep, path = spec.partition("=")
    if not sep or not label or not path:
        raise UsageError(f"a run must be LABEL=PATH, got {spec!r}")
    try:
        records = json.loads(Path(path).read_text())
        ok = (
            isinstance(records, list)
            and records
            and all(
                isinstance(r, dict) and isinstance(r.get("env_steps_lifetime"), int | float)
                for r in records
            )
        )
    except (OSError, ValueError) as exc:
        raise UsageError(f"{path}: cannot read it ({exc})") from None
    if not ok:
        raise UsageError(f"{path}: not a train_rllib_marl metrics file (a list of iterations)")
    return label, records


def smooth(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average over ``window`` points (fewer at the start); NaN-free input."""
    csum = np.cumsum(np.insert(values, 0, 0.0))
    idx = np.arange(1, len(values) + 1)
    lo = np.maximum(idx - window, 0)
    return (csum[idx] - csum[lo]) / (idx - lo)


def plot(runs: list[tuple[str, list[dict[str, Any]]]], window: int, out: str, title: str) -> Path:
    """Draw the panels (module docstring) and write ``out`` atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PANELS), figsize=(14, 3.8))
    for label, records in runs:
        for ax, (key, heading) in zip(axes, PANELS, strict=True):
            pairs = [(r["env_steps_lifetime"], r.get(key)) for r in records]
            pairs = [(s, v) for s, v in pairs if isinstance(v, int | float) and np.isfinite(v)]
            if not pairs:
                continue
            steps, values = (np.array(c, dtype=float) for c in zip(*pairs, strict=True))
            ax.plot(steps / 1000.0, smooth(values, window), label=label)
            ax.set_title(heading, fontsize=10)
            ax.set_xlabel("env steps (thousands)")
    axes[0].axhline(0.0, color="gray", lw=1)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{title} (moving average of {window} iterations)")
    fig.tight_layout()
    path = save_figure(fig, out)
    plt.close(fig)
    return path


def main(argv: Sequence[str] | None = None) -> int:
    """Read the runs, plot; exit 2 on a bad run."""
    args = parse_args(argv)
    runs = [read_run(spec) for spec in args.runs]
    print(f"figure: {plot(runs, args.window, args.out, args.title)}")
    return 0


if __name__ == "__main__":
    sys.exit(guarded_main(main, PROG))
