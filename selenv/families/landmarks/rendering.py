"""Frames of the env: its ``draw_*`` function (matplotlib; see :mod:`selenv.envs.rendering`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from selenv.envs.rendering import (
    FONT,
    chol_logdet,
    ellipse,
    ellipse_label,
    legend,
    note,
    set_title,
    set_view,
    style_axes,
)

__all__ = ["draw_landmark_selection"]


def draw_landmark_selection(
    fig: Figure,
    problem: Any,
    x_hat: np.ndarray,
    P: np.ndarray,
    k: int,
    picks: Sequence[int],
    last_selection: Sequence[int] | None,
    title: str = "",
) -> None:
    """UAV track, landmarks and picks (overview, km), and the estimate with its ellipse (zoom).

    Args:
        fig: an empty figure.
        problem: a :class:`~selenv.families.landmarks.scenario.LandmarkProblem` (``states (T+1,
        9)``,
            ``landmarks (N, 3)``, ENU, m).
        x_hat: ``(9,)`` current estimate (position first).
        P: ``(9, 9)`` its covariance.
        k: time index of ``x_hat`` (the truth is ``problem.states[k]``).
        picks: landmarks picked so far for the open update.
        last_selection: landmarks used by the last update (``None``: none yet).
        title: prefix of the figure title.

    The position ellipse (tens of metres) is invisible among landmarks kilometres apart, so the
    right panel zooms on the UAV, in metres relative to its true position.
    """
    ax0, ax1 = fig.add_axes((0.08, 0.25, 0.4, 0.6)), fig.add_axes((0.58, 0.25, 0.4, 0.6))
    lm = np.asarray(problem.landmarks)[:, :2]
    track = np.asarray(problem.states)[: k + 1, :2]
    truth, est = track[-1], np.asarray(x_hat)[:2]
    now, last = list(picks), list(last_selection or [])
    ell = ellipse(np.asarray(P)[:2, :2], est - truth, fc="tab:blue", alpha=0.3, ec="tab:blue")
    half = max(0.75 * ell.width, 1.5 * float(np.linalg.norm(est - truth)), 20.0)
    for ax, s, off in ((ax0, 1e-3, np.zeros(2)), (ax1, 1.0, truth)):  # overview km, zoom m
        for idx, c, ls in ((last, "tab:orange", ":"), (now, "tab:red", "-")):  # lines of sight
            segs = np.stack([np.broadcast_to(truth, (len(idx), 2)), lm[idx]], 1)
            ax.add_collection(
                LineCollection(list((segs - off) * s), colors=c, lw=0.8, linestyles=ls)
            )
        handles = [
            ax.plot(*((lm - off) * s).T, "^", color="0.55", ms=5, ls="none")[0],
            ax.plot(*((lm[now] - off) * s).T, "^", color="tab:red", mec="k", ms=8, ls="none")[0],
            ax.plot(*((lm[last] - off) * s).T, "o", mfc="none", mec="tab:orange", ms=11, mew=2,
                    ls="none")[0],
            ax.plot(*((track - off) * s).T, "-", color="k", lw=1.2)[0],
            ax.plot(*((truth - off) * s), "o", color="k", ms=5)[0],
            ax.plot(*((est - off) * s), "x", color="tab:blue", ms=8, mew=2)[0],
        ]  # fmt: skip
    for i in {*now, *last}:
        note(ax0, str(i), lm[i] * 1e-3, 5, -3)
    set_view(ax0, np.vstack([lm, track]) * 1e-3)
    ax1.set_xlim(-half, half)
    ax1.set_ylim(-half, half)
    ax1.set_aspect("equal", adjustable="box")
    ax1.add_patch(ell)
    style_axes(ax0, "east (km)", "north (km)")
    style_axes(ax1, "east − true east (m)", "north − true north (m)")
    ax0.set_title("overview", fontsize=FONT + 1, y=1.01)
    ax1.set_title("zoom on the UAV", fontsize=FONT + 1, y=1.01)
    err, logdet = float(np.linalg.norm(est - truth)), chol_logdet(np.asarray(P))
    set_title(fig, title, f"step {k}, log det P = {logdet:.1f}, horiz. error {err:.1f} m")
    labels = ["landmark", f"picked now {now}", f"last update {last}", "true track"]
    labels += ["true position", "estimate", ellipse_label("2σ at estimate", [ell], ax1)]
    legend(fig, [*handles, ell], labels, loc="lower center", ncol=4)
