"""Frames of the env: its ``draw_*`` function (matplotlib; see :mod:`selenv.envs.rendering`)."""

from __future__ import annotations

from collections import Counter
from typing import Any

import matplotlib as mpl
import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from selenv.envs.rendering import FONT, set_title, style_axes

__all__ = ["draw_receiver_clustering"]


def draw_receiver_clustering(
    fig: Figure,
    labels: np.ndarray,
    sigma: np.ndarray,
    J: float,
    J_G: float,
    J_C: float,
    J_L: float,
    k: int,
    max_size: int,
    title: str = "",
) -> None:
    """Receivers at their noise levels ``(sigma_1, sigma_2)`` coloured by cluster; cost terms.

    Args:
        fig: an empty figure.
        labels: ``(n,)`` int cluster label per receiver.
        sigma: ``(n, 2)`` measurement std devs of ``y1 = p - theta`` and ``y2 = p + theta``.
        J: the cost eq. (10), ``a_G J_G + a_C J_C + a_L J_L``.
        J_G: total MSE per state.
        J_C: worst cluster's positional MSE per state.
        J_L: worst receiver's positional MSE per coordinate.
        k: time step.
        max_size: largest allowed cluster.
        title: prefix of the figure title.

    Receivers have no positions in this problem: each sits at its two noise std devs, the
    quantity that drives the clustering. Members of a cluster are joined by a closed outline.
    """
    _, lab = np.unique(np.asarray(labels, dtype=np.int64), return_inverse=True)  # 0..C-1
    sig = np.asarray(sigma, dtype=np.float64)
    n_clusters = int(lab.max()) + 1
    ax, bx = fig.add_axes((0.08, 0.1, 0.52, 0.78)), fig.add_axes((0.74, 0.1, 0.23, 0.72))
    n_col = 10 if n_clusters <= 10 else 20
    cmap = mpl.colormaps[f"tab{n_col}"]
    segs: list[np.ndarray] = []
    seg_colors: list[Any] = []
    for c in range(n_clusters):  # closed outline of each cluster (members ordered by angle)
        pts = sig[lab == c]
        if len(pts) > 1:
            d = pts - pts.mean(axis=0)
            pts = pts[np.argsort(np.arctan2(d[:, 1], d[:, 0]))]
            ring = np.vstack([pts, pts[:1]]) if len(pts) > 2 else pts
            segs.extend(np.stack([ring[:-1], ring[1:]], 1))
            seg_colors.extend([cmap(c % n_col)] * (len(ring) - 1))
    ax.add_collection(LineCollection(segs, colors=seg_colors, lw=0.8, alpha=0.6))
    ax.scatter(
        sig[:, 0], sig[:, 1], c=cmap(lab % n_col), s=36, edgecolors="k", linewidths=0.6, zorder=3
    )
    top = float(sig.max()) * 1.05
    ax.set_xlim(0.0, top)
    ax.set_ylim(0.0, top)
    ax.set_aspect("equal", adjustable="box")
    style_axes(ax, "σ₁: std of y₁ = p − θ (m)", "σ₂: std of y₂ = p + θ (m)")
    sizes = Counter(Counter(lab.tolist()).values())
    txt = ", ".join(f"{sizes[s]}×{s}" for s in sorted(sizes, reverse=True))
    head = f"{n_clusters} clusters (count×size: {txt}), max size {max_size}"
    ax.set_title(head, fontsize=FONT + 1, y=1.01)
    bars = bx.bar(["J_G", "J_C", "J_L"], [J_G, J_C, J_L], color=["C0", "C1", "C2"])
    bx.bar_label(bars, fmt="%.3g", fontsize=FONT)
    bx.set_ylim(0.0, max(J_G, J_C, J_L, 1e-12) * 1.2)
    bx.set_title(f"J = {J:.4g}", fontsize=FONT + 2, y=1.01)
    style_axes(bx, "cost term", "MSE (m²)")
    set_title(fig, title, f"step {k}, J = {J:.4g}")
