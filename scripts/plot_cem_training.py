r"""Plot the cross-entropy search of a ``cem`` scorer checkpoint and its held-out result.

Left: the mean training return of each generation's mean vector, of its best vector and of its
elite, as the difference to greedy's mean return on the same training seeds, with the
``fast_rollout`` reference (``rollout``'s decisions) as a line; both references are played on
the checkpoint's training seeds and env keywords (``--no-references`` skips them and draws the
raw returns). Right: the held-out paired differences to greedy recorded in the checkpoint
(``held_out_bench``: mean and 95 % bootstrap CI per agent). Usage::

    .venv/bin/python scripts/plot_cem_training.py checkpoints/cl_scheduling_cem.json \
        --out docs/figures/cl_cem_training.png

The figure is written atomically (the format from the suffix of ``--out``). A file that is not
a scorer checkpoint with a training history is refused with one line naming it (exit 2).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from selenv.atomic import save_figure
from selenv.exits import UsageError, guarded_main

PROG = "scripts/plot_cem_training.py"


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line: the checkpoint, ``--out`` and ``--no-references``."""
    parser = argparse.ArgumentParser(prog=PROG, description=(__doc__ or "").splitlines()[0])
    parser.add_argument("checkpoint", help="a cem scorer checkpoint (.json)")
    parser.add_argument("--out", default="cl_cem_training.png", help="the figure file")
    parser.add_argument(
        "--no-references",
        action="store_true",
        help="do not play greedy and fast_rollout on the training seeds (raw returns)",
    )
    return parser.parse_args(argv)


def reference_returns(data: dict[str, Any]) -> dict[str, float]:
    """Mean returns of greedy and fast_rollout on the checkpoint's training seeds and env."""
    import gymnasium as gym

    import selenv  # noqa: F401
    from selenv.agents import make
    from selenv.threads import set_blas_threads
    from selenv.train.train_cl_cem import episode_return

    set_blas_threads(1)
    env = gym.make(data["env_id"], **data["env_kwargs"])
    first, last = data["training"]["train_seeds"]
    out = {}
    for name in ("greedy", "fast_rollout"):
        agent = make(name, data["env_id"])
        out[name] = float(np.mean([episode_return(agent, env, s) for s in range(first, last + 1)]))
    return out


def plot(data: dict[str, Any], refs: dict[str, float] | None, out: str) -> Path:
    """Draw the two panels (module docstring) and write ``out`` atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    history = data["training"]["history"]
    gen = np.array([h["generation"] + 1 for h in history])
    base = refs["greedy"] if refs else 0.0
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4), width_ratios=(3, 2))
    for key, label, style in (
        ("mean_value", "mean vector (candidate 0)", "-o"),
        ("elite_value", "elite mean", "--"),
        ("best_value", "best vector", ":"),
    ):
        ax.plot(gen, [h[key] - base for h in history], style, label=label)
    if refs:
        ax.axhline(0.0, color="gray", lw=1, label="greedy")
        ax.axhline(refs["fast_rollout"] - base, color="C3", lw=1, label="rollout / fast_rollout")
        ax.set_ylabel("mean training return - greedy's")
    else:
        ax.set_ylabel("mean training return")
    first, last = data["training"]["train_seeds"]
    ax.set_xlabel(f"generation ({data['training']['options']['population']} vectors each)")
    ax.set_title(f"cross-entropy search, training seeds {first}-{last}")
    ax.legend(fontsize=8)
    agents = data.get("held_out_bench", {}).get("agents", {})
    names = [n for n in agents if n != "greedy"]
    if names:
        mean = [agents[n]["paired_vs_greedy"]["mean_diff"] for n in names]
        ci = np.array([agents[n]["paired_vs_greedy"]["ci95"] for n in names])
        err = np.abs(ci.T - np.array(mean))
        labels = [n.split(":")[0] for n in names]
        bx.bar(labels, mean, yerr=err, capsize=4, color=["C3", "C1", "C0"][: len(names)])
        bx.axhline(0.0, color="gray", lw=1)
        bx.set_ylabel("return - greedy's (95 % CI)")
        bx.set_title("held-out seeds (paired)")
    else:
        bx.set_axis_off()
    fig.suptitle(f"{data['env_id']} {data['env_kwargs'] or '(defaults)'}: the cem scorer")
    fig.tight_layout()
    path = save_figure(fig, out)
    plt.close(fig)
    return path


def main(argv: Sequence[str] | None = None) -> int:
    """Read, (play the references,) plot; exit 2 on a file that is not a trained scorer."""
    from selenv.learned.families.cooperative import read_scorer

    args = parse_args(argv)
    try:
        data = read_scorer(args.checkpoint)
        history = data["training"]["history"]
        if not isinstance(history, list) or not history:
            raise ValueError("no training history")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UsageError(f"{args.checkpoint}: not a trained cem checkpoint ({exc})") from None
    refs = None if args.no_references else reference_returns(data)
    print(f"figure: {plot(data, refs, args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(guarded_main(main, PROG))
