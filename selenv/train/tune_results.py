"""The results of :mod:`selenv.train.tune_sweep`: one row per configuration, and its Markdown table.

A row aggregates the trials of one hyper-parameter configuration (one per training seed and
``--num-samples`` repeat):

* ``mean_return``: the mean over its trials of each trial's mean held-out return;
* ``ci95``: the percentile bootstrap CI of that mean over the trials
  (:func:`selenv.bench.stats.bootstrap_ci`, applied to the trial means: a one-sample CI of
  the mean), ``ci95_t`` the Student t-interval (:func:`selenv.bench.stats.t_interval`); with
  2-5 seeds the percentile bootstrap is too narrow and the t-interval is the one to read;
  both ``None`` with a single trial;
* ``min`` / ``max`` of the trial means;
* ``paired``: policy - baseline on the same eval seeds, every trial's episodes pooled
  (:func:`selenv.bench.stats.compare_paired`: mean difference, bootstrap CI, wins / ties /
  losses). The pooled pairs share eval seeds across trials, so this CI treats training-seed
  variation and episode variation alike.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from selenv.bench.stats import bootstrap_ci, compare_paired, t_interval

__all__ = ["format_table", "summarize"]


def _ci(pair: tuple[float, float]) -> list[float | None]:
    return [None if math.isnan(x) else round(x, 5) for x in pair]


def summarize(sweep: dict[str, Any], trials: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per hyper-parameter configuration (successful trials only), best mean first."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for t in trials:
        if t["error"] is None:
            groups.setdefault(json.dumps(t["params"], sort_keys=True), []).append(t)
    rows = []
    for members in groups.values():
        means = [float(np.mean(t["returns"])) for t in members]
        row: dict[str, Any] = {
            "params": members[0]["params"],
            "n_trials": len(members),
            "seeds": sorted({t["seed"] for t in members}),
            "seed_means": [round(m, 5) for m in means],
            "mean_return": round(float(np.mean(means)), 5),
            "ci95": _ci(bootstrap_ci(means)),
            "ci95_t": _ci(t_interval(means)),
            "min": round(min(means), 5),
            "max": round(max(means), 5),
            "paired": None,
        }
        if sweep["baseline"]:
            pol = [r for t in members for r in t["returns"]]
            base = [r for t in members for r in t["baseline_returns"]]
            row["baseline_mean_return"] = round(float(np.mean(base)), 5)
            row["paired"] = compare_paired(pol, base, sweep["baseline"]).to_json()
            row["paired"].pop("diffs", None)
        rows.append(row)
    return sorted(rows, key=lambda r: -r["mean_return"])


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.4g}"


def _interval(ci: list[float | None]) -> str:
    return "[n<2]" if ci[0] is None else f"[{_fmt(ci[0])}, {_fmt(ci[1])}]"


def format_table(
    sweep: dict[str, Any],
    rows: list[dict[str, Any]],
    n_failed: int,
    *,
    incomplete: str | None = None,
) -> str:
    """Markdown: a header, one row per configuration (best first), the legend and the best.

    ``incomplete``: why some trials have no result (a stopped sweep), shown under the header.
    """
    b = sweep["baseline"]
    head = ["config", "seeds", "mean return", "95% CI boot", "95% CI t", "min", "max"]
    if b:
        head += [f"Δ vs {b} (pooled)", "95% CI", "W/T/L"]
    lines = [
        f"## {sweep['script']} on {sweep['env_id']}: {sweep['fixed']['total_timesteps']} steps, "
        f"seeds {sweep['seeds']}, eval seeds {sweep['eval_seeds'][0]}..{sweep['eval_seeds'][-1]}",
        "",
        *([f"**INCOMPLETE**: {incomplete}", ""] if incomplete else []),
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for r in rows:
        cfg = ", ".join(f"{k}={v}" for k, v in r["params"].items()) or "(script defaults)"
        cells = [cfg, str(r["n_trials"]), _fmt(r["mean_return"]), _interval(r["ci95"])]
        cells += [_interval(r["ci95_t"]), _fmt(r["min"]), _fmt(r["max"])]
        if b:
            p = r["paired"]
            cells += [f"{p['mean_diff']:+.4g}", _interval(p["ci95"])]
            cells += [f"{p['wins']}/{p['ties']}/{p['losses']}"]
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "mean return: mean over a configuration's trials of the mean held-out return; "
        "CI boot: percentile bootstrap over the trials (selenv.bench.stats.bootstrap_ci, too "
        "narrow with few seeds), CI t: Student t-interval; min/max: of the trial means.",
    ]
    if b:
        base = rows[0]["baseline_mean_return"] if rows else None
        lines.append(
            f"Δ: policy - {b} (mean return {_fmt(base)}) on the same eval seeds, all trials' "
            "episodes pooled (selenv.bench.stats.compare_paired); W/T/L: episodes won/tied/lost."
        )
    if rows:
        best = rows[0]
        note = ""
        if len(rows) > 1 and best["ci95_t"][0] is not None:
            inside = best["ci95_t"][0] <= rows[1]["mean_return"]
            note = "; the runner-up's mean is inside its t CI" if inside else ""
        lines.append(
            f"best configuration (highest mean): {best['params'] or '(script defaults)'} "
            f"(mean return {_fmt(best['mean_return'])}{note})"
        )
    if n_failed:
        lines.append(f"FAILED trials: {n_failed} (see results.json)")
    return "\n".join(lines) + "\n"
