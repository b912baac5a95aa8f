"""Frames of the env: its ``draw_*`` function (matplotlib; see :mod:`selenv.envs.rendering`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Ellipse

from selenv.envs.rendering import (
    ARROW,
    ellipse,
    ellipse_label,
    legend,
    note,
    set_title,
    set_view,
    style_axes,
)

__all__ = ["draw_cl_scheduling"]


def draw_cl_scheduling(
    fig: Figure,
    sim: Any,
    pairs: Sequence[tuple[int, int]],
    processed: Sequence[int],
    title: str = "",
) -> None:
    """Agents' true and estimated positions, 2-sigma ellipses, beacons and processed links.

    Args:
        fig: an empty figure.
        sim: a :class:`~selenv.families.cooperative.scenario.CLSimulation` (``truth (A, n)``,
            ``x (A, n)``, ``P (A, n, n)``, ``k``, ``problem.states (T+1, A, n)``,
            ``problem.beacons (nb, 3)``); the horizontal position is ``[:2]`` of the state for
            both the ``ins`` and the ``unicycle`` model.
        pairs: directed pairs ``(i, j)``: ``i`` measures the range to ``j``.
        processed: indices into ``pairs`` processed in this step (arrows ``i -> j``).
        title: prefix of the figure title.
    """
    ax = fig.add_axes((0.09, 0.1, 0.6, 0.8))  # legend on the right
    truth = np.asarray(sim.truth() if callable(sim.truth) else sim.truth)[:, :2]
    est, P = np.asarray(sim.x)[:, :2], np.asarray(sim.P)[:, :2, :2]
    states = np.asarray(sim.problem.states)[:, :, :2]
    beacons = np.asarray(sim.problem.beacons)[:, :2]
    colors = [f"C{a % 10}" for a in range(truth.shape[0])]
    ells = [ellipse(P[a], est[a], fc=c, alpha=0.25, ec=c) for a, c in enumerate(colors)]
    for a, c in enumerate(colors):
        ax.plot(*states[:, a].T, "-", color=c, lw=0.6, alpha=0.25)
        ax.plot(*states[: sim.k + 1, a].T, "-", color=c, lw=1.2, alpha=0.8)
        ax.plot(*np.stack([truth[a], est[a]], 1), "-", color=c, lw=0.8)
        ax.plot(*truth[a], "o", color=c, ms=7, mec="k")
        ax.plot(*est[a], "x", color=c, ms=8, mew=2)
        note(ax, str(a), truth[a], 5, 5, color=c, weight="bold")
    ax.plot(*beacons.T, "s", color="k", ms=8, ls="none")
    for p in processed:
        i, j = pairs[p]
        ax.annotate("", xy=truth[j], xytext=truth[i], arrowprops={**ARROW, "color": colors[i]})
    set_view(ax, np.vstack([states.reshape(-1, 2), beacons, est]))
    for e in ells:
        ax.add_patch(e)
    style_axes(ax, "x (m)", "y (m)")
    handles = [
        Line2D([], [], marker="o", color="0.5", mec="k", ls="none", ms=7),
        Line2D([], [], marker="x", color="0.5", mew=2, ls="none", ms=8),
        Ellipse((0, 0), 1, 1, fc="0.5", alpha=0.3),
        Line2D([], [], color="0.5", lw=1.2),
        Line2D([], [], marker="s", color="k", ls="none", ms=7),
        Line2D([], [], color="0.3", marker=">", lw=1.5, ms=5),
    ]
    labels = ["true position (agent no.)", "estimate", ellipse_label("2σ, largest", ells, ax)]
    labels += ["true track so far", "beacon", f"link i → j processed ({len(processed)})"]
    legend(fig, handles, labels, loc="upper left", bbox_to_anchor=(0.7, 0.9))
    err = float(np.mean(np.linalg.norm(est - truth, axis=1)))
    links = ", ".join(f"{pairs[p][0]}→{pairs[p][1]}" for p in processed) or "none"
    set_title(fig, title, f"step {sim.k}, links {links}, mean error {err:.2f} m")
