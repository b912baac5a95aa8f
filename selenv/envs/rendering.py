"""Matplotlib rendering of the selenv environments.

:class:`Renderer` owns one figure per env and turns a draw function into a frame: ``"rgb_array"``
draws off-screen on the Agg canvas (no pyplot: headless, safe in subprocess vector envs) into an
``(H, W, 3)`` uint8 array; ``"human"`` updates a pyplot window (a no-op display under Agg).
The helpers here are shared by each family's ``rendering`` module (its ``draw_*`` function draws
one frame of the env from its plain scenario objects). Axis limits follow the geometry; an
ellipse's legend entry gives its semi-axes and says when it exceeds the view.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium import logger

if TYPE_CHECKING:  # matplotlib is imported on the first frame, not with the envs
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.patches import Ellipse

__all__ = [
    "ARROW",
    "FONT",
    "RENDER_MODES",
    "Renderer",
    "chol_logdet",
    "ellipse",
    "ellipse_label",
    "fmt",
    "legend",
    "marginal_cov",
    "note",
    "set_title",
    "set_view",
    "style_axes",
]

#: render modes a :class:`Renderer` accepts (``None``: no rendering)
RENDER_MODES = (None, "rgb_array", "human")
FONT = 7
ARROW = {"arrowstyle": "-|>", "lw": 1.5, "shrinkA": 5, "shrinkB": 5}


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
            from matplotlib.backends.backend_agg import FigureCanvasAgg
            from matplotlib.figure import Figure

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
def ellipse(cov: np.ndarray, centre: Sequence[float], n_sigma: float = 2.0, **kw: Any) -> Ellipse:
    """The ``n_sigma`` contour of ``N(centre, cov)`` as a patch; ``cov`` is ``(2, 2)`` PSD.

    Eigen-decomposition ``cov = V diag(l) V^T``: semi-axes ``n_sigma sqrt(l)`` along ``V``.
    """
    lam, V = np.linalg.eigh(0.5 * (cov + cov.T))
    lam = np.clip(lam, 0.0, None)
    width, height = 2.0 * n_sigma * np.sqrt(lam[::-1])  # major axis first
    angle = float(np.degrees(np.arctan2(V[1, 1], V[0, 1])))  # direction of the major axis
    from matplotlib.patches import Ellipse

    return Ellipse((float(centre[0]), float(centre[1])), width, height, angle=angle, **kw)


def ellipse_label(base: str, patches: Sequence[Ellipse], ax: Axes, unit: str = "m") -> str:
    """Legend text of ellipses: the largest one's semi-axes, and a note if it exceeds the view."""
    e = max(patches, key=lambda p: p.width)
    label = f"{base}: {fmt(e.width / 2)} × {fmt(e.height / 2)} {unit}"
    span = min(np.ptp(ax.get_xlim()), np.ptp(ax.get_ylim()))
    return label + ", exceeds view" if e.width > span else label


def fmt(v: float) -> str:
    """A short label of ``v``: 2 significant digits below 10, else an integer."""
    return f"{v:.2g}" if abs(v) < 10 else f"{v:.0f}"


def marginal_cov(information: np.ndarray, idx: Sequence[int]) -> np.ndarray:
    """``[A^-1]_{idx, idx}`` (the marginal covariance) by Cholesky: ``Y = L^-1 E``, ``Y^T Y``."""
    L = np.linalg.cholesky(0.5 * (information + information.T))  # A = L L^T
    E = np.zeros((information.shape[0], len(idx)))
    E[list(idx), np.arange(len(idx))] = 1.0
    Y = np.linalg.solve(L, E)  # triangular, tiny: faster than scipy's solve_triangular here
    return Y.T @ Y


def chol_logdet(A: np.ndarray) -> float:
    """``log det A`` of SPD ``A`` by Cholesky."""
    return float(2.0 * np.sum(np.log(np.diag(np.linalg.cholesky(A)))))


def set_view(ax: Axes, points: np.ndarray, pad: float = 0.08, min_span: float = 1.0) -> None:
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


def style_axes(ax: Axes, xlabel: str, ylabel: str) -> None:
    """Axis labels, small ticks (at most 5 per axis) and a light grid."""
    from matplotlib.ticker import MaxNLocator

    ax.set_xlabel(xlabel, fontsize=FONT + 1)
    ax.set_ylabel(ylabel, fontsize=FONT + 1)
    ax.tick_params(labelsize=FONT)
    for axis in (ax.xaxis, ax.yaxis):  # few tick labels: text dominates the frame time
        loc = axis.get_major_locator()
        if isinstance(loc, MaxNLocator):
            loc.set_params(nbins=5)
    ax.grid(True, lw=0.4, alpha=0.4)


def set_title(fig: Figure, title: str, detail: str) -> None:
    """The figure title ``"title: detail"`` (``detail`` alone without a title)."""
    fig.suptitle(f"{title}: {detail}" if title else detail, fontsize=FONT + 3, y=0.985)


def note(ax: Axes, text: str, xy: Any, dx: float = 5, dy: float = 0, **kw: Any) -> None:
    """Text ``(dx, dy)`` points off the data point ``xy``."""
    ax.annotate(text, xy, xytext=(dx, dy), textcoords="offset points", fontsize=FONT, **kw)


def legend(fig: Figure, handles: list[Any], labels: list[str], **kw: Any) -> None:
    """Figure legend; a tuple handle draws its artists side by side."""
    from matplotlib.legend_handler import HandlerTuple

    hmap = {tuple: HandlerTuple(ndivide=None)}
    fig.legend(handles, labels, fontsize=FONT, frameon=False, handler_map=hmap, **kw)
