"""Frames of the env: its ``draw_*`` function (matplotlib; see :mod:`selenv.envs.rendering`)."""

from __future__ import annotations

from typing import Any

import numpy as np
from matplotlib.figure import Figure

from selenv.envs.rendering import (
    chol_logdet,
    ellipse,
    ellipse_label,
    legend,
    marginal_cov,
    note,
    set_title,
    set_view,
    style_axes,
)
from selenv.families.fim.models import target_state
from selenv.families.fim.scenario import SENSOR_NAMES

__all__ = ["draw_fim_selection"]

SENSOR_STYLE = {"camera": ("o", "tab:blue"), "toa": ("s", "tab:green"), "doppler": ("^", "r")}


def draw_fim_selection(
    fig: Figure, problem: Any, selected: np.ndarray, information: np.ndarray, title: str = ""
) -> None:
    """Agent paths, candidates by sensor (picked ones bold), target and its CRLB ellipse.

    Args:
        fig: an empty figure.
        problem: a :class:`~selenv.families.fim.scenario.FIMProblem` (``positions (N, 3)``,
            ``agent``, ``sensor``, ``times (N,)``, ``theta_true``, ``theta_prior_mean``, ``Q0``,
            ``free``, ``full_theta``).
        selected: ``(N,)`` bool, the picked candidates.
        information: ``(d, d)`` current Fisher information ``Q0 + sum_{k picked} Q_k``.
        title: prefix of the figure title.

    The target position ``x(0)`` is ``theta[:2]`` of the full vector (at the window start; its
    track over the window is eq. 18). The ellipse is the 2-sigma contour of
    ``[information^-1]_{xy}`` (the CRLB of ``x(0)``), centred on the truth; drawn only if both
    ``x`` and ``y`` are estimated (in ``problem.free``), with the prior's for comparison.
    """
    sel = np.asarray(selected, dtype=bool)
    ax = fig.add_axes((0.09, 0.1, 0.56, 0.8))  # legend on the right
    pos, t = np.asarray(problem.positions)[:, :2], np.asarray(problem.times)
    for a in np.unique(problem.agent):
        idx = np.flatnonzero(problem.agent == a)
        idx = idx[np.argsort(t[idx], kind="stable")]  # the path in time order
        (path,) = ax.plot(*pos[idx].T, color="0.55", lw=1.0, zorder=1)
        note(ax, f"agent {a} (t = 0)", pos[idx[0]], 6, 0, color="0.3", va="center")
    handles: list[Any] = [path]
    labels = ["agent path"]
    for code, name in enumerate(SENSOR_NAMES):
        on = np.asarray(problem.sensor) == code
        if on.any():
            mk, c = SENSOR_STYLE[name]
            (pool,) = ax.plot(*pos[on].T, mk, color=c, ms=3, alpha=0.3, ls="none", zorder=2)
            (bold,) = ax.plot(*pos[on & sel].T, mk, color=c, ms=8, mec="k", ls="none", zorder=4)
            handles.append((pool, bold))
            labels.append(f"{name}: pool / picked ({int((on & sel).sum())})")
    full = problem.full_theta(problem.theta_true)
    q, _ = target_state(full, np.linspace(0.0, float(t.max()), 60))
    prior = problem.full_theta(problem.theta_prior_mean)[:2]
    handles += [
        ax.plot(*q.T, "--", color="k", lw=1.0, zorder=3)[0],
        ax.plot(*full[:2], "*", color="gold", mec="k", ms=11, zorder=5)[0],
        ax.plot(*prior, "P", color="0.3", ms=7, zorder=5)[0],
    ]
    labels += ["target true track", "target true x(0)", "prior mean x(0)"]
    set_view(ax, np.vstack([pos, q, prior[None]]))
    free = list(np.asarray(problem.free))
    if 0 in free and 1 in free:
        ixy = (free.index(0), free.index(1))
        styles: list[tuple[Any, str, dict[str, Any]]] = [
            (information, "CRLB 2σ at truth", {"fc": "tab:purple", "alpha": 0.4, "zorder": 6}),
            (problem.Q0, "prior 2σ at truth", {"fill": False, "ls": ":", "zorder": 3}),
        ]
        for A, text, kw in styles:
            patch = ellipse(marginal_cov(np.asarray(A), ixy), full[:2], ec="indigo", **kw)
            ax.add_patch(patch)
            handles.append(patch)
            labels.append(ellipse_label(text, [patch], ax))
    obj = chol_logdet(information) - chol_logdet(np.asarray(problem.Q0))
    set_title(fig, title, f"{int(sel.sum())} of {sel.size} picked, f = {obj:.2f} nats")
    style_axes(ax, "x (m)", "y (m)")
    legend(fig, handles, labels, loc="upper left", bbox_to_anchor=(0.67, 0.9))
