"""Matplotlib rendering of the selenv environments.

:class:`Renderer` owns one figure per env and turns a draw function into a frame: ``"rgb_array"``
draws off-screen on the Agg canvas (no pyplot: headless, safe in subprocess vector envs) into an
``(H, W, 3)`` uint8 array; ``"human"`` updates a pyplot window (a no-op display under Agg).
The ``draw_*`` functions draw one frame of each env from its plain scenario objects. Axis
limits follow the geometry; an ellipse's legend entry gives its semi-axes and says when it
exceeds the view.
"""

from __future__ import annotations

import warnings
from collections import Counter
from collections.abc import Callable, Sequence
from typing import Any

import matplotlib as mpl
import numpy as np
from gymnasium import logger
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.legend_handler import HandlerTuple
from matplotlib.lines import Line2D
from matplotlib.patches import Ellipse
from matplotlib.ticker import MaxNLocator

from selenv.scenarios.fim_selection import SENSOR_NAMES
from selenv.scenarios.kirchner_models import target_state

__all__ = [
    "RENDER_MODES",
    "Renderer",
    "draw_cl_scheduling",
    "draw_fim_selection",
    "draw_landmark_selection",
    "draw_receiver_clustering",
]

#: render modes a :class:`Renderer` accepts (``None``: no rendering)
RENDER_MODES = (None, "rgb_array", "human")
_SENSOR_STYLE = {"camera": ("o", "tab:blue"), "toa": ("s", "tab:green"), "doppler": ("^", "r")}
_FONT = 7
_ARROW = {"arrowstyle": "-|>", "lw": 1.5, "shrinkA": 5, "shrinkB": 5}


class Renderer:
    """One matplotlib figure per env instance, drawn by a callback on every :meth:`render`.

    Args:
        render_mode: ``None``, ``"rgb_array"`` or ``"human"``.
        fps: frames per second of ``"human"`` mode (the pause after each frame is ``1 / fps``).
        figsize: figure size (inches); the frame is ``figsize * dpi`` pixels.
        dpi: dots per inch.

    Raises:
        ValueError: unknown ``render_mode`` or ``fps <= 0``.
    """

    def __init__(
        self,
        render_mode: str | None,
        fps: int,
        figsize: tuple[float, float] = (6.4, 4.8),
        dpi: int = 100,
    ) -> None:
        if render_mode not in RENDER_MODES:
            raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps!r}")
        self.render_mode, self.fps = render_mode, fps
        self.figsize, self.dpi = (float(figsize[0]), float(figsize[1])), int(dpi)
        self._fig: Figure | None = None
        self._warned = False

    def _figure(self) -> Figure:
        """The figure, created lazily (a pyplot window in human mode, off-screen Agg otherwise)."""
        if self.render_mode == "human":
            import matplotlib.pyplot as plt  # lazy: rgb_array never touches pyplot

            if self._fig is None or not plt.fignum_exists(self._fig.number):
                plt.ion()
                self._fig = plt.figure(figsize=self.figsize, dpi=self.dpi)
        elif self._fig is None:
            self._fig = Figure(figsize=self.figsize, dpi=self.dpi)
            FigureCanvasAgg(self._fig)
        return self._fig

    def render(self, draw: Callable[[Figure], None]) -> np.ndarray | None:
        """Clear the figure, call ``draw(fig)`` and output the frame.

        Returns:
            ``"rgb_array"``: the frame ``(H, W, 3)`` uint8; ``"human"`` and ``None``: ``None``.
        """
        if self.render_mode is None:
            if not self._warned:
                logger.warn("render() called with render_mode=None: nothing is rendered")
                self._warned = True
            return None
        fig = self._figure()
        for ax in list(fig.axes):  # Figure.clear() would first clear every axes (slow)
            fig.delaxes(ax)
        fig.clear()
        draw(fig)
        if self.render_mode == "rgb_array":
            canvas = fig.canvas
            canvas.draw()
            return np.asarray(canvas.buffer_rgba())[..., :3].copy()  # type: ignore[attr-defined]
        import matplotlib.pyplot as plt

        plt.figure(fig.number)  # make it the active figure
        fig.canvas.draw_idle()
        with warnings.catch_warnings():  # a non-interactive backend (Agg) cannot show
            warnings.filterwarnings("ignore", message=".*non-interactive.*")
            plt.pause(1.0 / self.fps)
        return None

    def close(self) -> None:
        """Close the window or release the figure (idempotent)."""
        if self._fig is None:
            return
        if self.render_mode == "human":
            import matplotlib.pyplot as plt

            plt.close(self._fig)
        self._fig = None


# -- geometry helpers ---------------------------------------------------------------------------
def _ellipse(cov: np.ndarray, centre: Sequence[float], n_sigma: float = 2.0, **kw: Any) -> Ellipse:
    """The ``n_sigma`` contour of ``N(centre, cov)`` as a patch; ``cov`` is ``(2, 2)`` PSD.

    Eigen-decomposition ``cov = V diag(l) V^T``: semi-axes ``n_sigma sqrt(l)`` along ``V``.
    """
    lam, V = np.linalg.eigh(0.5 * (cov + cov.T))
    lam = np.clip(lam, 0.0, None)
    width, height = 2.0 * n_sigma * np.sqrt(lam[::-1])  # major axis first
    angle = float(np.degrees(np.arctan2(V[1, 1], V[0, 1])))  # direction of the major axis
    return Ellipse((float(centre[0]), float(centre[1])), width, height, angle=angle, **kw)


def _ellipse_label(base: str, patches: Sequence[Ellipse], ax: Axes, unit: str = "m") -> str:
    """Legend text of ellipses: the largest one's semi-axes, and a note if it exceeds the view."""
    e = max(patches, key=lambda p: p.width)
    label = f"{base}: {_fmt(e.width / 2)} × {_fmt(e.height / 2)} {unit}"
    span = min(np.ptp(ax.get_xlim()), np.ptp(ax.get_ylim()))
    return label + ", exceeds view" if e.width > span else label


def _fmt(v: float) -> str:
    return f"{v:.2g}" if abs(v) < 10 else f"{v:.0f}"


def _marginal_cov(information: np.ndarray, idx: Sequence[int]) -> np.ndarray:
    """``[A^-1]_{idx, idx}`` (the marginal covariance) by Cholesky: ``Y = L^-1 E``, ``Y^T Y``."""
    L = np.linalg.cholesky(0.5 * (information + information.T))  # A = L L^T
    E = np.zeros((information.shape[0], len(idx)))
    E[list(idx), np.arange(len(idx))] = 1.0
    Y = np.linalg.solve(L, E)  # triangular, tiny: faster than scipy's solve_triangular here
    return Y.T @ Y


def _logdet(A: np.ndarray) -> float:
    return float(2.0 * np.sum(np.log(np.diag(np.linalg.cholesky(A)))))


def _set_view(ax: Axes, points: np.ndarray, pad: float = 0.08, min_span: float = 1.0) -> None:
    """Limits on the bounding box of ``points (n, 2)`` (padded), widened to an equal aspect.

    The limits fill the axes box (the shorter side of the data is widened), and autoscaling is
    off, so patches added later (large ellipses) never change the view.
    """
    lo, hi = points.min(axis=0), points.max(axis=0)
    half = np.maximum((hi - lo) / 2 * (1 + 2 * pad), min_span / 2)
    box = ax.get_window_extent()  # the axes box in pixels
    ratio = box.height / box.width
    if half[1] < half[0] * ratio:  # equal aspect: half_y / half_x = box height / box width
        half[1] = half[0] * ratio
    else:
        half[0] = half[1] / ratio
    mid = (lo + hi) / 2
    ax.set_xlim(mid[0] - half[0], mid[0] + half[0])
    ax.set_ylim(mid[1] - half[1], mid[1] + half[1])
    ax.set_aspect("equal", adjustable="box")
    ax.set_autoscale_on(False)


def _style(ax: Axes, xlabel: str, ylabel: str) -> None:
    ax.set_xlabel(xlabel, fontsize=_FONT + 1)
    ax.set_ylabel(ylabel, fontsize=_FONT + 1)
    ax.tick_params(labelsize=_FONT)
    for axis in (ax.xaxis, ax.yaxis):  # few tick labels: text dominates the frame time
        loc = axis.get_major_locator()
        if isinstance(loc, MaxNLocator):
            loc.set_params(nbins=5)
    ax.grid(True, lw=0.4, alpha=0.4)


def _title(fig: Figure, title: str, detail: str) -> None:
    fig.suptitle(f"{title}: {detail}" if title else detail, fontsize=_FONT + 3, y=0.985)


def _note(ax: Axes, text: str, xy: Any, dx: float = 5, dy: float = 0, **kw: Any) -> None:
    """Text ``(dx, dy)`` points off the data point ``xy``."""
    ax.annotate(text, xy, xytext=(dx, dy), textcoords="offset points", fontsize=_FONT, **kw)


def _legend(fig: Figure, handles: list[Any], labels: list[str], **kw: Any) -> None:
    """Figure legend; a tuple handle draws its artists side by side."""
    hmap = {tuple: HandlerTuple(ndivide=None)}
    fig.legend(handles, labels, fontsize=_FONT, frameon=False, handler_map=hmap, **kw)


# -- FIMSelection -------------------------------------------------------------------------------
def draw_fim_selection(
    fig: Figure, problem: Any, selected: np.ndarray, information: np.ndarray, title: str = ""
) -> None:
    """Agent paths, candidates by sensor (picked ones bold), target and its CRLB ellipse.

    Args:
        fig: an empty figure.
        problem: a :class:`~selenv.scenarios.fim_selection.FIMProblem` (``positions (N, 3)``,
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
        _note(ax, f"agent {a} (t = 0)", pos[idx[0]], 6, 0, color="0.3", va="center")
    handles: list[Any] = [path]
    labels = ["agent path"]
    for code, name in enumerate(SENSOR_NAMES):
        on = np.asarray(problem.sensor) == code
        if on.any():
            mk, c = _SENSOR_STYLE[name]
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
    _set_view(ax, np.vstack([pos, q, prior[None]]))
    free = list(np.asarray(problem.free))
    if 0 in free and 1 in free:
        ixy = (free.index(0), free.index(1))
        styles: list[tuple[Any, str, dict[str, Any]]] = [
            (information, "CRLB 2σ at truth", {"fc": "tab:purple", "alpha": 0.4, "zorder": 6}),
            (problem.Q0, "prior 2σ at truth", {"fill": False, "ls": ":", "zorder": 3}),
        ]
        for A, text, kw in styles:
            patch = _ellipse(_marginal_cov(np.asarray(A), ixy), full[:2], ec="indigo", **kw)
            ax.add_patch(patch)
            handles.append(patch)
            labels.append(_ellipse_label(text, [patch], ax))
    obj = _logdet(information) - _logdet(np.asarray(problem.Q0))
    _title(fig, title, f"{int(sel.sum())} of {sel.size} picked, f = {obj:.2f} nats")
    _style(ax, "x (m)", "y (m)")
    _legend(fig, handles, labels, loc="upper left", bbox_to_anchor=(0.67, 0.9))


# -- LandmarkSelection --------------------------------------------------------------------------
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
        problem: a :class:`~selenv.scenarios.landmarks.LandmarkProblem` (``states (T+1, 9)``,
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
    ell = _ellipse(np.asarray(P)[:2, :2], est - truth, fc="tab:blue", alpha=0.3, ec="tab:blue")
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
        _note(ax0, str(i), lm[i] * 1e-3, 5, -3)
    _set_view(ax0, np.vstack([lm, track]) * 1e-3)
    ax1.set_xlim(-half, half)
    ax1.set_ylim(-half, half)
    ax1.set_aspect("equal", adjustable="box")
    ax1.add_patch(ell)
    _style(ax0, "east (km)", "north (km)")
    _style(ax1, "east − true east (m)", "north − true north (m)")
    ax0.set_title("overview", fontsize=_FONT + 1, y=1.01)
    ax1.set_title("zoom on the UAV", fontsize=_FONT + 1, y=1.01)
    err, logdet = float(np.linalg.norm(est - truth)), _logdet(np.asarray(P))
    _title(fig, title, f"step {k}, log det P = {logdet:.1f}, horiz. error {err:.1f} m")
    labels = ["landmark", f"picked now {now}", f"last update {last}", "true track"]
    labels += ["true position", "estimate", _ellipse_label("2σ at estimate", [ell], ax1)]
    _legend(fig, [*handles, ell], labels, loc="lower center", ncol=4)


# -- CLScheduling -------------------------------------------------------------------------------
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
        sim: a :class:`~selenv.scenarios.cooperative.CLSimulation` (``truth (A, n)``,
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
    ells = [_ellipse(P[a], est[a], fc=c, alpha=0.25, ec=c) for a, c in enumerate(colors)]
    for a, c in enumerate(colors):
        ax.plot(*states[:, a].T, "-", color=c, lw=0.6, alpha=0.25)
        ax.plot(*states[: sim.k + 1, a].T, "-", color=c, lw=1.2, alpha=0.8)
        ax.plot(*np.stack([truth[a], est[a]], 1), "-", color=c, lw=0.8)
        ax.plot(*truth[a], "o", color=c, ms=7, mec="k")
        ax.plot(*est[a], "x", color=c, ms=8, mew=2)
        _note(ax, str(a), truth[a], 5, 5, color=c, weight="bold")
    ax.plot(*beacons.T, "s", color="k", ms=8, ls="none")
    for p in processed:
        i, j = pairs[p]
        ax.annotate("", xy=truth[j], xytext=truth[i], arrowprops={**_ARROW, "color": colors[i]})
    _set_view(ax, np.vstack([states.reshape(-1, 2), beacons, est]))
    for e in ells:
        ax.add_patch(e)
    _style(ax, "x (m)", "y (m)")
    handles = [
        Line2D([], [], marker="o", color="0.5", mec="k", ls="none", ms=7),
        Line2D([], [], marker="x", color="0.5", mew=2, ls="none", ms=8),
        Ellipse((0, 0), 1, 1, fc="0.5", alpha=0.3),
        Line2D([], [], color="0.5", lw=1.2),
        Line2D([], [], marker="s", color="k", ls="none", ms=7),
        Line2D([], [], color="0.3", marker=">", lw=1.5, ms=5),
    ]
    labels = ["true position (agent no.)", "estimate", _ellipse_label("2σ, largest", ells, ax)]
    labels += ["true track so far", "beacon", f"link i → j processed ({len(processed)})"]
    _legend(fig, handles, labels, loc="upper left", bbox_to_anchor=(0.7, 0.9))
    err = float(np.mean(np.linalg.norm(est - truth, axis=1)))
    links = ", ".join(f"{pairs[p][0]}→{pairs[p][1]}" for p in processed) or "none"
    _title(fig, title, f"step {sim.k}, links {links}, mean error {err:.2f} m")


# -- ReceiverClustering -------------------------------------------------------------------------
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
    _style(ax, "σ₁: std of y₁ = p − θ (m)", "σ₂: std of y₂ = p + θ (m)")
    sizes = Counter(Counter(lab.tolist()).values())
    txt = ", ".join(f"{sizes[s]}×{s}" for s in sorted(sizes, reverse=True))
    head = f"{n_clusters} clusters (count×size: {txt}), max size {max_size}"
    ax.set_title(head, fontsize=_FONT + 1, y=1.01)
    bars = bx.bar(["J_G", "J_C", "J_L"], [J_G, J_C, J_L], color=["C0", "C1", "C2"])
    bx.bar_label(bars, fmt="%.3g", fontsize=_FONT)
    bx.set_ylim(0.0, max(J_G, J_C, J_L, 1e-12) * 1.2)
    bx.set_title(f"J = {J:.4g}", fontsize=_FONT + 2, y=1.01)
    _style(bx, "cost term", "MSE (m²)")
    _title(fig, title, f"step {k}, J = {J:.4g}")
