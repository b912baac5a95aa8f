"""Present benchmark results: a text table, the JSON file of the contract, and plots."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from selenv.bench.runner import EnvBenchResult

__all__ = ["format_table", "plot_filename", "plot_result", "results_to_json", "write_json"]

_HEADER = (
    "agent",
    "return (mean ± std)",
    "final objective",
    "gap to best (%)",
    "decision ms",
    "episodes",
)


def _num(x: float | None, fmt: str = ".4g") -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return format(x, fmt)


def format_table(result: EnvBenchResult) -> str:
    """Render one env's results as an aligned text table.

    The first line names the env and the settings; then one row per agent: mean return ± std,
    mean final objective, gap of the mean return to the best agent's (% of ``|best|``), mean
    decision time in milliseconds and the number of episodes; for envs that count objective
    evaluations (``info["cost_evaluations"]``) also the evaluations per decision. Skipped
    agents show the reason.
    """
    title = f"{result.env_id}  (episodes={result.episodes}, seed={result.seed}"
    if result.env_kwargs:
        title += f", env_kwargs={json.dumps(result.env_kwargs)}"
    title += ")"
    counted = any(r.cost_evaluations is not None for r in result.agents.values())
    header = (*_HEADER, "cost evals/decision") if counted else _HEADER
    rows: list[tuple[str, ...]] = []
    skipped: list[tuple[str, str]] = []
    for name, res in result.agents.items():
        if res.skipped is not None:
            skipped.append((name, res.skipped))
            continue
        rows.append(
            (
                name,
                f"{_num(res.mean_return)} ± {_num(res.std_return, '.2g')}",
                _num(res.mean_final_objective),
                _num(result.gap_percent(name), ".2f"),
                _num(1e3 * res.decision_seconds_mean, ".3g"),
                str(len(res.returns)),
                *([_num(res.cost_evaluations_per_decision, ".3g")] if counted else []),
            )
        )
    width_rows = [header, *rows]
    widths = [max(len(r[i]) for r in width_rows) for i in range(len(header))]
    width_name = max([widths[0], *(len(n) for n, _ in skipped)])
    widths[0] = width_name

    def line(cells: Sequence[str]) -> str:
        parts = [cells[0].ljust(widths[0])]
        parts += [c.rjust(w) for c, w in zip(cells[1:], widths[1:], strict=True)]
        return "  ".join(parts).rstrip()

    out = [title, line(header), "  ".join("-" * w for w in widths)]
    out += [line(r) for r in rows]
    out += [f"{name.ljust(widths[0])}  skipped: {why}" for name, why in skipped]
    return "\n".join(out)


def results_to_json(results: Sequence[EnvBenchResult]) -> dict[str, Any] | list[dict[str, Any]]:
    """The JSON document of the contract: one object for one env, a list for several."""
    docs = [r.to_json() for r in results]
    return docs[0] if len(docs) == 1 else docs


def write_json(results: Sequence[EnvBenchResult], path: str | Path) -> Path:
    """Write :func:`results_to_json` to ``path`` (parent folders are created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", encoding="utf-8") as fh:
        json.dump(results_to_json(results), fh, indent=2)
        fh.write("\n")
    return path


def plot_filename(env_id: str) -> str:
    """PNG file name of an env's plot: the id without its namespace (``FIMSelection-v0.png``)."""
    return env_id.rsplit("/", 1)[-1] + ".png"


def plot_result(result: EnvBenchResult, directory: str | Path) -> Path:
    """Plot mean final objective per agent (bars, std error bars, one dot per episode).

    Uses matplotlib's Agg canvas directly (no pyplot, no global backend switch), so it works
    headless and does not disturb an interactive session. Skipped agents are left out.

    Returns:
        The path of the written PNG, ``directory / plot_filename(result.env_id)``.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    ran = [(n, r) for n, r in result.agents.items() if r.skipped is None]
    fig = Figure(figsize=(max(4.0, 1.1 * len(ran) + 2.0), 4.0), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    x = np.arange(len(ran))
    means = [r.mean_final_objective for _, r in ran]
    stds = [r.std_final_objective for _, r in ran]
    ax.bar(x, means, yerr=stds, capsize=4, color="C0", alpha=0.6, label="mean ± std")
    jitter = np.random.default_rng(0)
    for i, (_, r) in enumerate(ran):
        ys = np.asarray(r.final_objectives)
        xs = i + jitter.uniform(-0.15, 0.15, ys.size)
        ax.scatter(xs, ys, s=12, color="k", zorder=3, label="episodes" if i == 0 else None)
    ax.set_xticks(x, [n for n, _ in ran], rotation=30, ha="right")
    ax.set_ylabel("final objective")
    skipped = [n for n, r in result.agents.items() if r.skipped is not None]
    title = f"{result.env_id} ({result.episodes} episodes, seed {result.seed})"
    if skipped:
        title += f"\nskipped: {', '.join(skipped)}"
    ax.set_title(title, fontsize=9)
    if ran:
        ax.legend(fontsize=8)
    path = directory / plot_filename(result.env_id)
    fig.savefig(path, dpi=100)
    return path
