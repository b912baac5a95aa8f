"""Present benchmark results: a text table, the JSON document and plots.

All three show the same statistics (:mod:`selenv.bench.stats`): each agent's per-seed paired
difference of the episode return against the baseline, its mean with a percentile-bootstrap
95 % CI, wins/ties/losses and the normalised score. The JSON document has one shape whatever
the number of envs (:func:`results_to_json`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from selenv.bench.provenance import provenance
from selenv.bench.results import EnvBenchResult
from selenv.bench.stats import TIE_REL_TOL, PairedComparison

__all__ = ["format_table", "plot_filename", "plot_result", "results_to_json", "write_json"]


def _num(x: float | None, fmt: str = ".4g") -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return format(x, fmt)


def _delta_cell(p: PairedComparison | None, is_baseline: bool) -> str:
    if is_baseline:
        return "baseline"
    if p is None:
        return "-"
    lo, hi = p.ci95
    ci = "[n<2]" if math.isnan(lo) else f"[{lo:+#.3g}, {hi:+#.3g}]"
    return f"{p.mean_diff:+#.3g} {ci}" + ("*" if p.significant else "")


def format_table(result: EnvBenchResult) -> str:
    """Render one env's results as an aligned text table with a two-line legend.

    The first line names the env and the settings; then one row per agent: mean return ± std,
    mean final objective, the paired mean difference of the return against the baseline with
    its bootstrap 95 % CI (``*`` when the CI excludes 0; the baseline's row reads
    ``baseline``), wins/ties/losses against the baseline, the normalised score, mean decision
    time in milliseconds and the number of episodes; for envs that count objective evaluations
    (``info["cost_evaluations"]``) also the evaluations per decision. Skipped agents show the
    reason.
    """
    title = f"{result.env_id}  (episodes={result.episodes}, seed={result.seed}"
    if result.env_kwargs:
        title += f", env_kwargs={json.dumps(result.env_kwargs, default=repr)}"
    title += ")"
    base = result.baseline_name
    counted = any(r.cost_evaluations is not None for r in result.agents.values())
    header = (
        "agent",
        "return (mean ± std)",
        "final objective",
        f"Δ vs {base} [95 % CI]",
        "W/T/L",
        "norm. score",
        "decision ms",
        "episodes",
        *(["cost evals/decision"] if counted else []),
    )
    rows: list[tuple[str, ...]] = []
    skipped: list[tuple[str, str]] = []
    for name, res in result.agents.items():
        if res.skipped is not None:
            skipped.append((name, res.skipped))
            continue
        p = result.paired(name)
        wtl = "-" if p is None or name == base else f"{p.wins}/{p.ties}/{p.losses}"
        rows.append(
            (
                name,
                f"{_num(res.mean_return)} ± {_num(res.std_return, '.2g')}",
                _num(res.mean_final_objective),
                _delta_cell(p, name == base),
                wtl,
                _num(result.normalized_score(name), ".3f"),
                _num(1e3 * res.decision_seconds_mean, ".3g"),
                str(len(res.returns)),
                *([_num(res.cost_evaluations_per_decision, ".3g")] if counted else []),
            )
        )
    width_rows = [header, *rows]
    widths = [max(len(r[i]) for r in width_rows) for i in range(len(header))]
    widths[0] = max([widths[0], *(len(n) for n, _ in skipped)])

    def line(cells: Sequence[str]) -> str:
        parts = [cells[0].ljust(widths[0])]
        parts += [c.rjust(w) for c, w in zip(cells[1:], widths[1:], strict=True)]
        return "  ".join(parts).rstrip()

    out = [title, line(header), "  ".join("-" * w for w in widths)]
    out += [line(r) for r in rows]
    out += [f"{name.ljust(widths[0])}  skipped: {why}" for name, why in skipped]
    ref = result.random_reference or "random (not run)"
    out += [
        f"Δ: mean per-seed return difference vs {base}, bootstrap 95 % CI (* = excludes 0)",
        f"W/T/L: seeds above / tied (|Δ| <= {TIE_REL_TOL:g}·max(1, |baseline|)) / below; "
        f"norm. score: (mean - {ref}) / (best mean - {ref})",
    ]
    return "\n".join(out)


def results_to_json(
    results: Sequence[EnvBenchResult],
    *,
    argv: Sequence[str] | None = None,
    executor: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The JSON document: ``{"provenance": {...}, "results": [one object per env]}``.

    The shape does not depend on the number of envs. ``provenance`` is
    :func:`selenv.bench.provenance.provenance` (``argv`` defaults to ``sys.argv``), plus
    ``"executor"`` (:meth:`selenv.parallel.Executor.describe`) when given; each element of
    ``results`` is :meth:`EnvBenchResult.to_json`.
    """
    prov = provenance(argv)
    if executor is not None:
        prov["executor"] = executor
    return {"provenance": prov, "results": [r.to_json() for r in results]}


def write_json(
    results: Sequence[EnvBenchResult],
    path: str | Path,
    *,
    argv: Sequence[str] | None = None,
    executor: dict[str, Any] | None = None,
) -> Path:
    """Write :func:`results_to_json` to ``path`` (parent folders are created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", encoding="utf-8") as fh:
        json.dump(results_to_json(results, argv=argv, executor=executor), fh, indent=2)
        fh.write("\n")
    return path


def plot_filename(env_id: str) -> str:
    """PNG file name of an env's plot: the id without its namespace or package.

    ``selenv/FIMSelection-v1`` -> ``FIMSelection-v1.png``,
    ``selenv.multiagent.fim_selection_v0`` -> ``fim_selection_v0.png``.
    """
    return env_id.rsplit("/", 1)[-1].rsplit(".", 1)[-1] + ".png"


def _symlog_threshold(compared: list[tuple[str, PairedComparison]]) -> float | None:
    """Linear range of a symlog axis when the mean differences span > 2 decades, else ``None``.

    One far-off agent (typically ``random``) would otherwise flatten the CIs of the close ones.
    """
    mags = [
        abs(v) for _, p in compared for v in (p.mean_diff, *p.ci95) if math.isfinite(v) and v != 0.0
    ]
    if not mags or max(mags) <= 100.0 * min(mags):
        return None
    return max(10.0 ** math.floor(math.log10(min(mags))), 1e-4 * max(mags))


def plot_result(result: EnvBenchResult, directory: str | Path) -> Path:
    """Plot each agent's paired return difference against the baseline with its 95 % CI.

    One column per agent other than the baseline: a dot at the mean difference, an error bar
    spanning the bootstrap 95 % CI, the per-seed differences as faint dots, and a line at 0
    (the baseline). When the differences span more than two decades the y axis is symlog
    (labelled so), so that the CIs of close agents stay visible next to a far-off one.
    Uses matplotlib's Agg canvas directly (no pyplot, no global backend switch), so it works
    headless and does not disturb an interactive session. Skipped agents are left out (named
    in the title).

    Returns:
        The path of the written PNG, ``directory / plot_filename(result.env_id)``.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    base = result.baseline_name
    compared = [(n, p) for n in result.agents if n != base and (p := result.paired(n)) is not None]
    fig = Figure(figsize=(max(4.0, 1.1 * len(compared) + 2.5), 4.0), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.axhline(0.0, color="k", lw=1.0, label=f"baseline: {base}")
    jitter = np.random.default_rng(0)
    for i, (_, p) in enumerate(compared):
        ys = np.asarray(p.diffs)
        xs = i + jitter.uniform(-0.18, 0.18, ys.size)
        ax.scatter(xs, ys, s=10, color="C0", alpha=0.35, lw=0, label="per seed" if i == 0 else None)
        lo, hi = p.ci95
        yerr = None if math.isnan(lo) else [[p.mean_diff - lo], [hi - p.mean_diff]]
        ax.errorbar(
            [i],
            [p.mean_diff],
            yerr=yerr,
            fmt="o",
            color="C3",
            capsize=5,
            ms=6,
            zorder=3,
            label="mean, 95 % bootstrap CI" if i == 0 else None,
        )
    ax.set_xticks(np.arange(len(compared)), [n for n, _ in compared], rotation=30, ha="right")
    ax.set_xlim(-0.6, max(len(compared), 1) - 0.4)
    ylabel = f"Δ return vs {base} (same seeds)"
    linthresh = _symlog_threshold(compared)
    if linthresh is not None:
        ax.set_yscale("symlog", linthresh=linthresh)
        ylabel += ", symlog"
        values = [v for _, p in compared for v in (*p.diffs, *p.ci95) if math.isfinite(v)]
        if max(values) <= 0.0:  # nothing above the baseline: no empty decades above 0
            ax.set_ylim(top=linthresh)
        elif min(values) >= 0.0:
            ax.set_ylim(bottom=-linthresh)
    ax.set_ylabel(ylabel)
    skipped = [n for n, r in result.agents.items() if r.skipped is not None]
    title = f"{result.env_id} ({result.episodes} episodes, seed {result.seed})"
    if not compared:
        title += "\nno agent to compare with the baseline"
    if skipped:
        title += f"\nskipped: {', '.join(skipped)}"
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    path = directory / plot_filename(result.env_id)
    fig.savefig(path, dpi=100)
    return path
