r"""Plot the learning curves recorded by the PPO training scripts (``--curve-every``).

One panel per checkpoint: the policy's normalised held-out score
``(R - R_random) / (R_greedy - R_random)`` against environment steps, with the ``greedy``
baseline at 1 and ``random`` at 0 (both evaluated on the same held-out seeds) and every other
recorded baseline (``brute_force``, ``rollout``, ...) as a line at its own normalised level,
titled with the env id and its keyword arguments; below it, the same curve as the difference to
greedy's mean return (in the env's return units, the first point left out of the scale), where
the small differences between near-greedy policies and the references show. The top axis of
each panel reads the same points in wall minutes of the run (training plus the curve's own
evaluations, as recorded), so a curve can be compared by time as well as by steps. Usage::

    .venv/bin/python scripts/plot_learning_curves.py runs/train_fim_ppo/policy.json \
        [more checkpoints (.json or .zip) ...] --out learning_curves.png

The figure is written atomically (the format from the suffix of ``--out``). A checkpoint
without a ``learning_curve`` (trained without ``--curve-every``), or whose curve lacks the
``greedy`` and ``random`` baselines, is refused with one line naming the file (exit 2).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from selenv.atomic import save_figure
from selenv.exits import UsageError, guarded_main
from selenv.learned.resources import read_metadata
from selenv.learned.rl.curves import CURVE_KEY, check_curve, normalized_score

PROG = "scripts/plot_learning_curves.py"


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line: checkpoints (their ``.json`` or ``.zip``) and ``--out``."""
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    parser.add_argument(
        "checkpoints", nargs="+", type=Path, help="checkpoint metadata (.json, or the .zip)"
    )
    parser.add_argument("--out", type=Path, required=True, help="figure path (e.g. curves.png)")
    return parser.parse_args(argv)


def read_curve(path: Path) -> tuple[str, dict[str, Any]]:
    """The panel title and the checked ``learning_curve`` of checkpoint ``path``.

    Raises:
        UsageError: one line naming the file (missing, unreadable, no curve, no baselines).
    """
    json_path = path.with_suffix(".json")
    try:
        meta = read_metadata(json_path, "checkpoint metadata")
    except (OSError, ValueError) as exc:
        raise UsageError(str(exc)) from None  # names the file
    if not isinstance(meta, dict) or CURVE_KEY not in meta:
        raise UsageError(
            f"{json_path}: no learning_curve in it (train with --curve-every N to record one)"
        )
    try:
        curve = check_curve(meta[CURVE_KEY], str(json_path))
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if normalized_score(0.0, curve["baselines"]) is None:
        raise UsageError(
            f"{json_path}: its learning curve has no distinct greedy and random baselines to "
            "normalise with (train with --baselines greedy,random)"
        )
    if not curve["points"]:
        raise UsageError(f"{json_path}: its learning curve has no points")
    kwargs = meta.get("env_kwargs") or {}
    title = f"{meta.get('env_id', '?')} {json.dumps(kwargs, sort_keys=True)}"
    return title, curve


def _wall_axis(ax: Any, steps: list[float], minutes: list[float]) -> None:
    """A top axis in wall minutes, interpolated between the recorded points.

    Left out when the points do not increase in both steps and time (a curve of one point,
    or a resumed run whose clock restarted).
    """
    import numpy as np

    pairs = list(zip(steps, minutes, strict=True))
    if len(pairs) < 2 or any(b[0] <= a[0] or b[1] <= a[1] for a, b in itertools.pairwise(pairs)):
        return
    x, w = np.asarray(steps, dtype=float), np.asarray(minutes, dtype=float)
    # extended linearly past both ends, so the axis margins get ticks at the same rate
    far = 10.0 * (x[-1] - x[0])
    lo, hi = (w[1] - w[0]) / (x[1] - x[0]), (w[-1] - w[-2]) / (x[-1] - x[-2])
    x = np.concatenate([[x[0] - far], x, [x[-1] + far]])
    w = np.concatenate([[w[0] - lo * far], w, [w[-1] + hi * far]])
    axis = ax.secondary_xaxis(
        "top", functions=(lambda v: np.interp(v, x, w), lambda v: np.interp(v, w, x))
    )
    axis.set_xlabel("wall minutes", fontsize=7)
    axis.tick_params(labelsize=7)


def main(argv: Sequence[str] | None = None) -> int:
    """Read every checkpoint's curve (all checked before drawing), draw, write ``--out``."""
    args = parse_args(argv)
    if not args.out.suffix:
        raise UsageError(f"--out {args.out}: give a file name with a suffix (.png, .pdf, .svg)")
    curves = [read_curve(path) for path in args.checkpoints]

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n = len(curves)
    cols = min(n, 2)
    rows = math.ceil(n / cols)
    fig = Figure(figsize=(6.0 * cols, 6.4 * rows), layout="constrained")
    FigureCanvasAgg(fig)
    for i, (title, curve) in enumerate(curves):
        r, c = divmod(i, cols)
        top = fig.add_subplot(2 * rows, cols, 2 * r * cols + c + 1)
        low = fig.add_subplot(2 * rows, cols, (2 * r + 1) * cols + c + 1, sharex=top)
        steps = [p["timesteps"] for p in curve["points"]]
        base = curve["baselines"]
        scores = [  # none is None: read_curve checked the baselines
            s
            for p in curve["points"]
            if (s := normalized_score(p["mean_return"], base)) is not None
        ]
        top.axhline(1.0, color="tab:green", linestyle="--", label="greedy")
        top.axhline(0.0, color="tab:gray", linestyle=":", label="random")
        low.axhline(0.0, color="tab:green", linestyle="--", label="greedy")
        others = [k for k in base if k not in ("greedy", "random")]
        for j, name in enumerate(others):  # e.g. brute_force, rollout: dash-dotted lines too
            level = normalized_score(base[name], base)
            if level is not None:
                top.axhline(level, color=f"C{3 + j}", linestyle="-.", label=name)
            low.axhline(base[name] - base["greedy"], color=f"C{3 + j}", linestyle="-.", label=name)
        top.plot(steps, scores, marker="o", color="tab:blue", label="policy")
        low.plot(
            steps,
            [p["mean_return"] - base["greedy"] for p in curve["points"]],
            marker="o",
            color="tab:blue",
            label="policy",
        )
        _wall_axis(top, steps, [p["wall_seconds"] / 60.0 for p in curve["points"]])
        top.set_title(title, fontsize=8, wrap=True)
        top.set_ylabel("normalised score")
        low.set_ylabel("return - greedy's")
        low.set_xlabel("environment steps")
        top.legend(fontsize=7, loc="best")
        # near greedy the differences matter: the lower panel zooms on them
        diffs = [p["mean_return"] - base["greedy"] for p in curve["points"][1:]] or [0.0]
        marks = [0.0, *diffs, *(base[k] - base["greedy"] for k in others)]
        span = max(abs(min(marks)), abs(max(marks))) * 1.2 or 1.0
        low.set_ylim(-span, span)
        seeds = curve["seeds"]
        low.text(
            0.99,
            0.02,
            f"{curve['episodes']} held-out episodes, seeds {seeds[0]}..{seeds[1]}",
            transform=low.transAxes,
            ha="right",
            fontsize=7,
        )
    save_figure(fig, args.out, dpi=120)
    print(f"{args.out}: {n} learning curve{'s' if n > 1 else ''}")
    return 0


if __name__ == "__main__":
    sys.exit(guarded_main(main, PROG))
