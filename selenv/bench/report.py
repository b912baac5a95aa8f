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
from typing import TYPE_CHECKING, Any

import numpy as np

from selenv import atomic
from selenv.bench.provenance import provenance
from selenv.bench.results import EnvBenchResult
from selenv.bench.stats import TIE_REL_TOL, PairedComparison

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "OBJECTIVE_HEADERS",
    "column_decimals",
    "decimals_for",
    "format_fixed",
    "format_ms",
    "format_table",
    "plot_figure",
    "plot_filename",
    "plot_result",
    "results_to_json",
    "write_json",
]


#: the header of the final-objective column per :attr:`EnvBenchResult.objective_direction`
OBJECTIVE_HEADERS = {
    "higher": "final objective (higher is better)",
    "lower": "final objective (lower is better)",
    None: "final objective",
}

_MAX_DECIMALS = 6


def _finite(values: Sequence[float | None]) -> list[float]:
    return [float(v) for v in values if v is not None and math.isfinite(v)]


def decimals_for(magnitude: float | None, significant: int) -> int:
    """Decimals that show ``significant`` digits of a number of size ``magnitude``.

    Between 0 and 6; 2 when ``magnitude`` is ``None``, 0 or not finite.
    ``decimals_for(14350.0, 4) == 0``, ``decimals_for(1.089, 4) == 3``,
    ``decimals_for(0.0534, 3) == 4``.
    """
    if magnitude is None or not math.isfinite(magnitude) or magnitude == 0.0:
        return 2
    exponent = math.floor(math.log10(abs(magnitude)))
    return min(_MAX_DECIMALS, max(0, significant - 1 - exponent))


def format_fixed(x: float | None, decimals: int, *, sign: bool = False) -> str:
    """``x`` with ``decimals`` fixed decimals and thousands separators; ``-`` if missing.

    Never an exponent, never ``-0``: ``format_fixed(14350.4, 0) == "14,350"``,
    ``format_fixed(-0.0001, 2) == "0.00"``; ``sign=True`` writes ``+`` before a positive one.
    """
    if x is None or not math.isfinite(x):
        return "-"
    value = round(float(x), decimals)
    if value == 0.0:
        value = 0.0  # drops the sign of -0.0
    return format(value, f"{'+' if sign and value != 0.0 else ''},.{decimals}f")


def format_ms(seconds: float | None) -> str:
    """A duration in seconds as milliseconds with 3 significant digits, no exponent.

    ``format_ms(0.0578) == "57.8"``, ``format_ms(2.81e-5) == "0.0281"``,
    ``format_ms(1.2345) == "1,234"`` (at least the whole milliseconds).
    """
    if seconds is None or not math.isfinite(seconds):
        return "-"
    ms = 1e3 * seconds
    return format_fixed(ms, 0 if ms == 0.0 else decimals_for(ms, 3))


def column_decimals(values: Sequence[float | None], significant: int = 4) -> int:
    """Fixed decimals of a column: ``significant`` digits of its largest magnitude."""
    mags = [abs(v) for v in _finite(values)]
    return decimals_for(max(mags) if mags else None, significant)


def _delta_decimals(compared: Sequence[PairedComparison]) -> int:
    """Decimals of the Δ column: 3 significant digits of its smallest non-zero entry.

    An entry's size is the larger of ``|mean|`` and the CI's half width, so a near-tie with a
    narrow CI does not ask for more decimals than its CI resolves.
    """
    sizes = []
    for p in compared:
        lo, hi = p.ci95
        half = 0.5 * (hi - lo) if math.isfinite(lo) and math.isfinite(hi) else 0.0
        size = max(abs(p.mean_diff) if math.isfinite(p.mean_diff) else 0.0, half)
        if size > 0.0:
            sizes.append(size)
    return decimals_for(min(sizes) if sizes else None, 3)


def _delta_cell(p: PairedComparison | None, is_baseline: bool, decimals: int) -> str:
    if is_baseline:
        return "baseline"
    if p is None:
        return "-"
    lo, hi = p.ci95
    if math.isnan(lo):
        ci = "[n<2]"
    else:
        ci = f"[{format_fixed(lo, decimals, sign=True)}, {format_fixed(hi, decimals, sign=True)}]"
    mean = format_fixed(p.mean_diff, decimals, sign=True)
    return f"{mean} {ci}" + ("*" if p.significant else "")


def _gap_cell(gap: tuple[float, float, float] | None) -> str:
    """A gap to the bound as a percentage with 3 decimals (``-`` when there is none)."""
    return "-" if gap is None else f"{format_fixed(100.0 * gap[0], 3)} %"


def format_table(result: EnvBenchResult) -> str:
    """Render one env's results as an aligned text table with a short legend.

    The first line names the env and the settings; then one row per agent: mean return ± std,
    mean final objective (the header says whether higher or lower is better,
    :attr:`EnvBenchResult.objective_direction`), the paired mean difference of the return
    against the baseline with its bootstrap 95 % CI as ``[lo, hi]`` (``*`` when the CI
    excludes 0; the baseline's row reads ``baseline``), wins/ties/losses against the baseline,
    the normalised score, the gap to the env's certified bound on the return (where the family
    has one, :mod:`selenv.bench.bounds`), mean decision time in milliseconds (3 significant
    digits) and the
    number of episodes; for envs that count objective evaluations
    (``info["cost_evaluations"]``) also the evaluations per decision. Skipped agents show the
    reason.

    Numbers never use an exponent: each column has fixed decimals chosen by its magnitude
    (4 significant digits of its largest value for returns and objectives, 3 of the smallest
    difference for Δ) and thousands separators.

    An incomplete result (a stopped run) is shown on its paired seeds
    (:meth:`EnvBenchResult.statistics_view`), under a line giving the episodes each agent
    finished.
    """
    title = f"{result.env_id}  (episodes={result.episodes}, seed={result.seed}"
    if result.env_kwargs:
        title += f", env_kwargs={json.dumps(result.env_kwargs, default=repr)}"
    title += ")"
    if not result.complete:
        done = ", ".join(f"{n} {k}" for n, k in result.episodes_done().items())
        title += (
            f"\nINCOMPLETE (stopped early): episodes finished: {done}; statistics on the "
            f"{len(result.paired_seeds())} seeds every agent finished"
        )
        result = result.statistics_view()
    base = result.baseline_name
    ran = {n: r for n, r in result.agents.items() if r.skipped is None}
    counted = any(r.cost_evaluations is not None for r in ran.values())
    bounded = bool(result.bounds)
    header = (
        "agent",
        "return (mean ± std)",
        OBJECTIVE_HEADERS[result.objective_direction],
        f"Δ vs {base} [95 % CI]",
        "W/T/L",
        "norm. score",
        *(["gap to bound"] if bounded else []),
        "decision ms",
        "episodes",
        *(["cost evals/decision"] if counted else []),
    )
    paired = {n: result.paired(n) for n in ran}
    ret_dec = column_decimals([r.mean_return for r in ran.values()])
    obj_dec = column_decimals([r.mean_final_objective for r in ran.values()])
    delta_dec = _delta_decimals([p for n, p in paired.items() if p is not None and n != base])
    evals_dec = column_decimals([r.cost_evaluations_per_decision for r in ran.values()], 3)
    rows: list[tuple[str, ...]] = []
    for name, res in ran.items():
        p = paired[name]
        wtl = "-" if p is None or name == base else f"{p.wins}/{p.ties}/{p.losses}"
        evals = res.cost_evaluations_per_decision
        rows.append(
            (
                name,
                f"{format_fixed(res.mean_return, ret_dec)} ± "
                f"{format_fixed(res.std_return, ret_dec)}",
                format_fixed(res.mean_final_objective, obj_dec),
                _delta_cell(p, name == base, delta_dec),
                wtl,
                format_fixed(result.normalized_score(name), 3),
                *([_gap_cell(result.gap_to_bound(name))] if bounded else []),
                format_ms(res.decision_seconds_mean),
                str(len(res.returns)),
                *([format_fixed(evals, evals_dec)] if counted else []),
            )
        )
    skipped = [(n, r.skipped) for n, r in result.agents.items() if r.skipped is not None]
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
        'final objective: mean info["objective"] after the last step; return: always higher is '
        "better",
        f"Δ: mean per-seed return difference vs {base}, bootstrap 95 % CI (* = excludes 0)",
        f"W/T/L: seeds above / tied (|Δ| <= {TIE_REL_TOL:g}·max(1, |baseline|)) / below; "
        f"norm. score: (mean - {ref}) / (best mean - {ref})",
    ]
    if bounded:
        what = "the optimum" if result.bound_kind == "optimum" else "a certified upper bound"
        out.append(
            f"gap to bound: mean (bound - return) / |bound| over the seeds, in %; bound: {what} "
            f"on each episode's return ({result.bound_method})"
        )
    return "\n".join(out)


def results_to_json(
    results: Sequence[EnvBenchResult],
    *,
    argv: Sequence[str] | None = None,
    executor: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The JSON document: ``{"provenance": {...}, "complete": bool, "results": [one per env]}``.

    The shape does not depend on the number of envs. ``complete`` is ``False`` when a run was
    stopped early (then so is the ``complete`` of the env that was running, see
    :meth:`EnvBenchResult.to_json`; envs that never started are absent). ``provenance`` is
    :func:`selenv.bench.provenance.provenance` (``argv`` defaults to ``sys.argv``), plus
    ``"executor"`` (:meth:`selenv.parallel.Executor.describe`) when given; each element of
    ``results`` is :meth:`EnvBenchResult.to_json`.
    """
    prov = provenance(argv)
    if executor is not None:
        prov["executor"] = executor
    return {
        "provenance": prov,
        "complete": all(r.complete for r in results),
        "results": [r.to_json() for r in results],
    }


def write_json(
    results: Sequence[EnvBenchResult],
    path: str | Path,
    *,
    argv: Sequence[str] | None = None,
    executor: dict[str, Any] | None = None,
) -> Path:
    """Write :func:`results_to_json` to ``path`` atomically (parent folders are created).

    The document is serialised first, then written to a temporary file next to ``path``,
    flushed and renamed over it (:func:`selenv.atomic.write_json`): on any failure (a full
    disk, a file-size limit, an interruption) ``path`` keeps its previous bytes and no
    partial file is left. Raises the ``OSError`` of the failed write.
    """
    return atomic.write_json(path, results_to_json(results, argv=argv, executor=executor))


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


def plot_figure(result: EnvBenchResult) -> Figure:
    """The figure of :func:`plot_result`: every seed's paired difference, mean and 95 % CI.

    One column per agent other than the baseline: the per-seed differences of the episode
    return against the baseline as a jittered strip of points (one per seed; the collection's
    ``gid`` is ``"seeds:<agent>"``), over them the mean difference with its bootstrap 95 % CI
    bar (the mean marker's ``gid`` is ``"mean:<agent>"``), and a line at 0 (the baseline,
    named in the legend).
    The y label names the baseline and the direction (``> 0: better than <baseline>``; a
    return is always to be maximised). When the differences span more than two decades the
    y axis is symlog (labelled so), so that the CIs of close agents stay visible next to a
    far-off one. Skipped agents are left out (named in the title).

    Built on matplotlib's Agg canvas directly (no pyplot, no global backend switch), so it
    works headless and does not disturb an interactive session.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    base = result.baseline_name
    compared = [(n, p) for n in result.agents if n != base and (p := result.paired(n)) is not None]
    fig = Figure(figsize=(max(4.5, 1.1 * len(compared) + 2.5), 4.2), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.axhline(0.0, color="k", lw=1.0, label=f"baseline: {base} (Δ = 0)")
    jitter = np.random.default_rng(0)
    for i, (name, p) in enumerate(compared):
        ys = np.asarray(p.diffs, dtype=float)
        xs = i + jitter.uniform(-0.2, 0.2, ys.size)
        ax.scatter(
            xs,
            ys,
            s=16,
            color="C0",
            alpha=0.6,
            lw=0,
            zorder=2,
            gid=f"seeds:{name}",
            label=f"one seed ({ys.size} per agent)" if i == 0 else None,
        )
        lo, hi = p.ci95
        yerr = None if math.isnan(lo) else [[p.mean_diff - lo], [hi - p.mean_diff]]
        bars = ax.errorbar(
            [i],
            [p.mean_diff],
            yerr=yerr,
            fmt="D",
            color="C3",
            capsize=6,
            ms=6,
            elinewidth=1.5,
            zorder=3,
            label="mean, 95 % bootstrap CI" if i == 0 else None,
        )
        mean_line = bars.lines[0]
        if mean_line is not None:
            mean_line.set_gid(f"mean:{name}")
    ax.set_xticks(np.arange(len(compared)), [n for n, _ in compared], rotation=30, ha="right")
    ax.set_xlim(-0.6, max(len(compared), 1) - 0.4)
    ylabel = f"Δ return vs {base}, per seed\n(> 0: better than {base})"
    linthresh = _symlog_threshold(compared)
    if linthresh is not None:
        ax.set_yscale("symlog", linthresh=linthresh)
        ylabel += ", symlog axis"
        values = [v for _, p in compared for v in (*p.diffs, *p.ci95) if math.isfinite(v)]
        if max(values) <= 0.0:  # nothing above the baseline: no empty decades above 0
            ax.set_ylim(top=linthresh)
        elif min(values) >= 0.0:
            ax.set_ylim(bottom=-linthresh)
    ax.set_ylabel(ylabel)
    skipped = [n for n, r in result.agents.items() if r.skipped is not None]
    title = f"{result.env_id} ({result.episodes} episodes from seed {result.seed})"
    if not compared:
        title += "\nno agent to compare with the baseline"
    if skipped:
        title += f"\nskipped: {', '.join(skipped)}"
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    return fig


def plot_result(result: EnvBenchResult, directory: str | Path) -> Path:
    """Write :func:`plot_figure` of ``result`` as a PNG into ``directory`` (created if needed).

    Written atomically (a temporary PNG next to the target, renamed over it): a failed write
    leaves the previous PNG as it was. An incomplete result is plotted on its paired seeds
    (:meth:`EnvBenchResult.statistics_view`).

    Returns:
        The path of the written PNG, ``directory / plot_filename(result.env_id)``.

    Raises:
        OSError: the folder or the PNG could not be written.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / plot_filename(result.env_id)
    fig = plot_figure(result.statistics_view())
    with atomic.atomic_path(path) as temp:
        fig.savefig(temp, dpi=100, format="png")
    return path
