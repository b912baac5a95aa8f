"""Reproduce the results section (Sec. 6, Figs. 2-7) of Kirchner, Hespanha & Garagić (2020).

Monte-Carlo comparison of FIM-based greedy measurement selection (Algorithm 1) against uniformly
random selection on the scenario presets ``example1`` (one camera), ``example2`` (camera +
Doppler) and ``example3`` (two agents with camera + Doppler, independent vs cooperative
selection). The geometry is fixed (``randomize=False``); per trial the true parameter vector is
a fresh draw from the prior (``make_problem`` on a per-trial generator). Selection uses only the
Jacobians at the prior mean (``problem.G``); measurements of the selected candidates are sampled
at the truth and ``theta`` is estimated by MAP (Gauss-Newton, prior ``N(mu0, P0)``). The metric is
the position error ``||theta_hat[:2] - theta_true[:2]||`` (m) at the window start. Example 1 is
the paper's stationary target (position only); the same camera pool with a moving target
(``MOVING_VARIANT``, theta_1..theta_3 estimated) is the second panel of Fig. 3. Results and
the comparison with the paper: ``docs/REPRODUCTION.md``.

Usage::

    python scripts/reproduce_kirchner.py [--trials N] [--out docs/figures] [--seed S] [--quick]

Writes ``kirchner_fig3.png``, ``kirchner_fig5.png``, ``kirchner_fig7.png`` and
``kirchner_geometry.png`` into ``--out`` and prints the result tables (Markdown).
``main(argv)`` returns every number as a dict.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter
from tqdm import tqdm

from selenv.agents.fim_solvers import cooperative_greedy, greedy_whitened
from selenv.core.estimation import gauss_newton_map
from selenv.core.information import information_matrix, logdet_objective
from selenv.scenarios import kirchner_models as km
from selenv.scenarios.fim_selection import (
    CAMERA,
    DOPPLER,
    FIMProblem,
    config_from,
    make_problem,
)

#: budgets K of the full run (per agent in example 3)
FULL_KS: tuple[int, ...] = (2, 3, 4, 5, 6, 8, 10, 15, 20, 30, 50)
#: budgets K of ``--quick``
QUICK_KS: tuple[int, ...] = (4, 10, 30)
#: budget shown in the geometry figure (Figs. 2, 4, 6 show 10 selections)
GEOMETRY_K = 10
DEFAULT_TRIALS, QUICK_TRIALS = 100, 20
DEFAULT_SEED = 2020
EX3_METHODS = ("agent1", "agent2", "independent", "cooperative")
#: variant of example 1: the same camera pool with a moving target, so velocity and curvature
#: (theta_2, theta_3 of eq. 18) are estimated too (d = 6 instead of the stationary d = 2)
MOVING_VARIANT: dict[str, bool] = {"stationary": False}
FIGURE_NAMES = ("kirchner_fig3", "kirchner_fig5", "kirchner_fig7", "kirchner_geometry")


# -- estimation and bounds -----------------------------------------------------------------------
def map_position_error(
    problem: FIMProblem, Y: np.ndarray, idx: Sequence[int]
) -> tuple[float, bool]:
    """MAP estimate from the measurements ``Y[idx]``; position error (m) and convergence flag."""
    ix = np.asarray(idx, dtype=np.intp)
    res = gauss_newton_map(
        lambda th: problem.measurement_mean(th, ix),
        lambda th: problem.measurement_jacobian(th, ix),
        Y[ix],
        problem.R[ix],
        problem.theta_prior_mean,
        problem.P0,
    )
    err = float(np.linalg.norm(res.theta[:2] - problem.theta_true[:2]))
    return err, bool(res.converged)


def crlb_position_rms(problem: FIMProblem, idx: Sequence[int]) -> float:
    """``sqrt(trace((FIM(S)^-1)[:2, :2]))`` (m), FIM at the prior mean (what the selector sees)."""
    F = information_matrix(problem.Q0, problem.G, np.asarray(idx, dtype=np.intp))
    C = np.linalg.inv(F)
    return float(np.sqrt(np.trace(C[:2, :2])))


def _new_record(n_trials: int, n_k: int) -> dict[str, np.ndarray]:
    return {
        "error": np.full((n_trials, n_k), np.nan),
        "crlb": np.full((n_trials, n_k), np.nan),
        "converged": np.ones((n_trials, n_k), dtype=bool),
        "logdet": np.full((n_trials, n_k), np.nan),
    }


def _evaluate(
    rec: dict[str, np.ndarray], t: int, j: int, problem: FIMProblem, Y: np.ndarray, idx: Any
) -> None:
    err, ok = map_position_error(problem, Y, idx)
    rec["error"][t, j], rec["converged"][t, j] = err, ok
    rec["crlb"][t, j] = crlb_position_rms(problem, idx)
    rec["logdet"][t, j] = logdet_objective(problem.Q0, problem.G, np.asarray(idx, dtype=np.intp))


def summarize(rec: dict[str, np.ndarray]) -> dict[str, Any]:
    """Per-K error mean, standard error, median; mean CRLB and f(S); non-converged counts."""
    e = rec["error"]
    n = e.shape[0]
    se = e.std(axis=0, ddof=1) / np.sqrt(n) if n > 1 else np.full(e.shape[1], np.nan)
    return {
        "mean": e.mean(axis=0),
        "se": se,
        "median": np.median(e, axis=0),
        "crlb": rec["crlb"].mean(axis=0),
        "logdet": rec["logdet"].mean(axis=0),
        "nonconverged": (~rec["converged"]).sum(axis=0),
        "errors": e,
    }


def _trial_rngs(ss: np.random.SeedSequence) -> tuple[np.random.Generator, ...]:
    """Independent streams of one trial: problem (truth), measurement noise, random selection."""
    return tuple(np.random.default_rng(s) for s in ss.spawn(3))


# -- examples 1 and 2 ---------------------------------------------------------------------------
def run_single_agent(
    preset: str,
    ks: Sequence[int],
    trials: int,
    ss: np.random.SeedSequence,
    *,
    desc: str | None = None,
    **overrides: Any,
) -> dict[str, Any]:
    """FIM greedy vs uniformly random selection on a single-agent preset (plus overrides)."""
    cfg = config_from(preset, randomize=False, **overrides)
    recs = {"fim": _new_record(trials, len(ks)), "random": _new_record(trials, len(ks))}
    n_camera = np.zeros((trials, len(ks)), dtype=int)
    n_doppler = np.zeros((trials, len(ks)), dtype=int)
    for t, tss in enumerate(tqdm(ss.spawn(trials), desc=desc or preset, unit="trial")):
        rng_problem, rng_noise, rng_select = _trial_rngs(tss)
        problem = make_problem(cfg, rng_problem)
        Y = problem.sample_measurements(rng_noise)  # all candidates: common noise for both
        for j, K in enumerate(ks):
            fim = np.asarray(greedy_whitened(problem.Q0, problem.G, K).indices, dtype=np.intp)
            rnd = rng_select.choice(problem.N, size=K, replace=False)
            _evaluate(recs["fim"], t, j, problem, Y, fim)
            _evaluate(recs["random"], t, j, problem, Y, rnd)
            n_camera[t, j] = int(np.sum(problem.sensor[fim] == CAMERA))
            n_doppler[t, j] = int(np.sum(problem.sensor[fim] == DOPPLER))
    out: dict[str, Any] = {
        "overrides": dict(overrides),
        "ks": list(ks),
        "methods": {name: summarize(rec) for name, rec in recs.items()},
        "fim_n_camera": n_camera.mean(axis=0),
        "fim_n_doppler": n_doppler.mean(axis=0),
    }
    return out


def sensor_mix(preset: str, k_max: int, seed: int) -> dict[str, Any]:
    """Camera / Doppler counts of the greedy selection for every K in 1..k_max.

    ``problem.G`` is evaluated at the prior mean on the fixed geometry, so it (and hence the
    greedy selection) is the same for every trial; one problem suffices.
    """
    problem = make_problem(config_from(preset, randomize=False), np.random.default_rng(seed))
    ks = np.arange(1, k_max + 1)
    cam, dop = [], []
    for K in ks:
        sel = np.asarray(greedy_whitened(problem.Q0, problem.G, int(K)).indices, dtype=np.intp)
        cam.append(int(np.sum(problem.sensor[sel] == CAMERA)))
        dop.append(int(np.sum(problem.sensor[sel] == DOPPLER)))
    cam_a, dop_a = np.array(cam), np.array(dop)
    return {
        "ks": ks,
        "n_camera": cam_a,
        "n_doppler": dop_a,
        "camera_fraction": cam_a / ks,
        "doppler_fraction": dop_a / ks,
    }


# -- example 3 ----------------------------------------------------------------------------------
def ex3_selections(problem: FIMProblem, K: int) -> dict[str, np.ndarray]:
    """Global candidate indices of each example-3 method for ``K`` picks per agent."""
    pools = [problem.pool(i) for i in range(problem.config.n_agents)]
    pairs = [(problem.H[p], problem.R[p]) for p in pools]
    out: dict[str, np.ndarray] = {}
    for mode in ("independent", "cooperative"):
        coop = cooperative_greedy(problem.Q0, pairs, [K] * len(pools), mode=mode)
        per_agent = [p[list(s.indices)] for p, s in zip(pools, coop.selections, strict=True)]
        out[mode] = np.concatenate(per_agent).astype(np.intp)
        if mode == "independent":  # each agent alone = its own Algorithm-1 selection on Q0
            out["agent1"], out["agent2"] = per_agent[0], per_agent[1]
    return out


def run_example3(ks: Sequence[int], trials: int, ss: np.random.SeedSequence) -> dict[str, Any]:
    """Agent 1 alone, agent 2 alone, both independent, cooperative (``K`` picks per agent)."""
    cfg = config_from("example3", randomize=False)
    recs = {name: _new_record(trials, len(ks)) for name in EX3_METHODS}
    for t, tss in enumerate(tqdm(ss.spawn(trials), desc="example3", unit="trial")):
        rng_problem, rng_noise, _ = _trial_rngs(tss)
        problem = make_problem(cfg, rng_problem)
        Y = problem.sample_measurements(rng_noise)
        for j, K in enumerate(ks):
            sels = ex3_selections(problem, K)
            for name in EX3_METHODS:
                _evaluate(recs[name], t, j, problem, Y, sels[name])
    return {"ks": list(ks), "methods": {name: summarize(rec) for name, rec in recs.items()}}


# -- figures ------------------------------------------------------------------------------------
def _error_curve(ax: Axes, ks: Sequence[int], s: dict[str, Any], color: str, label: str) -> None:
    k = np.asarray(ks)
    mean, se = np.asarray(s["mean"]), np.asarray(s["se"])
    ax.plot(k, mean, "o-", color=color, lw=2, ms=4, label=f"{label}: mean ± s.e.")
    if np.all(np.isfinite(se)):
        lo = np.maximum(mean - se, 1e-3)
        ax.fill_between(k, lo, mean + se, color=color, alpha=0.2, lw=0)
    ax.plot(k, s["median"], "--", color=color, lw=1.2, label=f"{label}: median")
    ax.plot(k, s["crlb"], ":", color=color, lw=1.2, label=f"{label}: CRLB (prior mean)")


def _minor_label(v: float, _pos: int) -> str:
    lead = round(v / 10.0 ** np.floor(np.log10(v)))
    return f"{v:g}" if lead in (2, 3, 5) else ""


def _style_error_axes(ax: Axes, xlabel: str, title: str) -> None:
    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
    ax.yaxis.set_minor_formatter(FuncFormatter(_minor_label))
    ax.set_xlabel(xlabel)
    ax.set_ylabel("position error at window start (m)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)


def plot_fig3(res: dict[str, Any], diag: dict[str, Any], trials: int, path: Path) -> None:
    fig = Figure(figsize=(13, 5), layout="constrained")
    ax_a, ax_b = fig.subplots(1, 2, sharey=True)
    titles = (
        f"Fig. 3 (Example 1 preset, one camera): MAP error, {trials} trials",
        "Variant: same camera pool, moving target (theta_1..theta_3 estimated)",
    )
    for ax, r, title in zip((ax_a, ax_b), (res, diag), titles, strict=True):
        _error_curve(ax, r["ks"], r["methods"]["fim"], "red", "FIM greedy")
        _error_curve(ax, r["ks"], r["methods"]["random"], "blue", "random")
        _style_error_axes(ax, "number of measurements selected K (of 1000)", title)
    ax_b.yaxis.set_tick_params(labelleft=True)
    fig.savefig(path, dpi=120)


def plot_fig5(res: dict[str, Any], mix: dict[str, Any], trials: int, path: Path) -> None:
    fig = Figure(figsize=(12, 4.8), layout="constrained")
    ax_a, ax_b = fig.subplots(1, 2)
    ks, m = res["ks"], res["methods"]
    _error_curve(ax_a, ks, m["fim"], "red", "FIM greedy")
    _error_curve(ax_a, ks, m["random"], "blue", "random")
    _style_error_axes(
        ax_a,
        "number of measurements selected K (of 1000 camera + 1000 RF)",
        f"Fig. 5a (Example 2, camera + Doppler): MAP error, {trials} trials",
    )
    k = mix["ks"]
    ax_b.plot(k, mix["camera_fraction"], "o-", color="red", ms=3, label="camera (image)")
    ax_b.plot(k, mix["doppler_fraction"], "s-", color="blue", ms=3, label="RF (Doppler)")
    ax_b.axhline(2 / 3, color="red", ls=":", lw=1, label="paper: ~2/3 camera")
    ax_b.axhline(1 / 3, color="blue", ls=":", lw=1, label="paper: ~1/3 RF")
    if GEOMETRY_K <= len(k):
        c, d = mix["n_camera"][GEOMETRY_K - 1], mix["n_doppler"][GEOMETRY_K - 1]
        ax_b.annotate(
            f"K={GEOMETRY_K}: {c} camera + {d} RF\n(paper: 7 + 3)",
            (GEOMETRY_K, c / GEOMETRY_K),
            xytext=(GEOMETRY_K + 5, 0.9),
            arrowprops={"arrowstyle": "->"},
            fontsize=8,
        )
    ax_b.set_ylim(0, 1.05)
    ax_b.set_xlabel("number of measurements selected K")
    ax_b.set_ylabel("fraction of FIM-selected measurements")
    ax_b.set_title("Fig. 5b: sensor mix of the greedy selection")
    ax_b.grid(True, alpha=0.3)
    ax_b.legend(fontsize=8)
    fig.savefig(path, dpi=120)


def plot_fig7(res: dict[str, Any], trials: int, path: Path) -> None:
    fig = Figure(figsize=(7, 4.8), layout="constrained")
    ax = fig.add_subplot()
    ks, m = np.asarray(res["ks"]), res["methods"]
    styles = {
        "agent1": ("blue", "agent 1 only"),
        "agent2": ("green", "agent 2 only"),
        "independent": ("cyan", "both, independent selection"),
        "cooperative": ("red", "both, cooperative selection"),
    }
    for i, (name, (color, label)) in enumerate(styles.items()):
        s = m[name]
        x = ks * (1.0 + 0.015 * (i - 1.5))  # small offsets keep the error bars apart
        ax.errorbar(x, s["mean"], yerr=s["se"], fmt="o-", color=color, lw=2, ms=4, capsize=3,
                    label=f"{label} (mean ± s.e.)")  # fmt: skip
        ax.plot(ks, s["crlb"], ":", color=color, lw=1.2)
    ax.plot([], [], ":", color="gray", label="CRLB at prior mean (same colours)")
    _style_error_axes(
        ax,
        "measurements selected per agent K",
        f"Fig. 7 (Example 3, two agents): MAP error, {trials} trials",
    )
    fig.savefig(path, dpi=120)


def _plot_geometry_panel(
    ax: Axes, problem: FIMProblem, sels: dict[str, np.ndarray], title: str
) -> None:
    for i in range(problem.config.n_agents):
        pool = problem.pool(i)
        cams = pool[problem.sensor[pool] == CAMERA]
        ax.plot(*problem.positions[cams, :2].T, "k-", lw=1, label="agent path" if i == 0 else None)
        start = problem.positions[cams[0], :2]
        ax.annotate(
            f"agent {i + 1} start", start, fontsize=7, xytext=(3, 3), textcoords="offset points"
        )
    markers = {"selected": ("o", "filled"), "cooperative": ("D", "none")}
    for key, (marker, fill) in markers.items():
        if key not in sels:
            continue
        idx = sels[key]
        for code, color, name in ((CAMERA, "red", "camera"), (DOPPLER, "blue", "RF")):
            pts = problem.positions[idx[problem.sensor[idx] == code], :2]
            if not len(pts):
                continue
            extra = "" if key == "selected" else " (cooperative, agent 2)"
            label = f"selected {name}{extra} ({len(pts)})"
            face = color if fill == "filled" else "none"
            size = 30 if fill == "filled" else 70
            ax.scatter(*pts.T, s=size, marker=marker, facecolors=face, edgecolors=color,
                       zorder=3, label=label)  # fmt: skip
    s = np.linspace(0.0, problem.config.window_s, 200)
    q_true, _ = km.target_state(problem.full_theta(problem.theta_true), s)
    ax.plot(*q_true.T, "g-", lw=2, label="target truth (window)")
    ax.plot(*problem.theta_true[:2], "g*", ms=14, mec="k", label="target truth at t=0")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2)


def plot_geometry(seed: int, path: Path) -> dict[str, Any]:
    """Figs. 2/4/6: paths, greedy selections at K = 10 by sensor, one truth draw per example."""
    fig = Figure(figsize=(18, 7.5), layout="constrained")
    axes = fig.subplots(1, 3)
    info: dict[str, Any] = {}
    for ax, preset in zip(axes, ("example1", "example2", "example3"), strict=True):
        problem = make_problem(config_from(preset, randomize=False), np.random.default_rng(seed))
        if preset == "example3":
            ex3 = ex3_selections(problem, GEOMETRY_K)
            coop2 = np.setdiff1d(ex3["cooperative"], ex3["independent"])
            sels = {"selected": ex3["independent"], "cooperative": coop2}
            title = (
                f"Example 3 (Fig. 6): {GEOMETRY_K} per agent, independent greedy (filled);\n"
                "hollow diamonds: agent-2 picks that change under cooperative selection"
            )
        else:
            sel = greedy_whitened(problem.Q0, problem.G, GEOMETRY_K).indices
            sels = {"selected": np.asarray(sel, dtype=np.intp)}
            fig_no, pool = ("2", "1000") if preset == "example1" else ("4", "1000 camera + 1000 RF")
            title = f"Example {preset[-1]} (Fig. {fig_no}): {GEOMETRY_K} greedy picks of {pool}"
            title += "\n(several picks near the end of the path overlap)"
        info[preset] = {k: v.tolist() for k, v in sels.items()}
        _plot_geometry_panel(ax, problem, sels, title)
    fig.suptitle("Geometry: agent paths (positions of the candidate pool), selections, target")
    fig.savefig(path, dpi=110)
    return info


# -- report -------------------------------------------------------------------------------------
def _fmt(x: float) -> str:
    return f"{x:.2f}" if np.isfinite(x) else "nan"


def paired_difference(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-K mean and standard error of ``a - b`` over trials (same truth and noise per trial)."""
    d = a - b
    return d.mean(axis=0), d.std(axis=0, ddof=1) / np.sqrt(d.shape[0])


def format_tables(results: dict[str, Any]) -> str:
    """Markdown tables of every figure's numbers."""
    lines: list[str] = []
    for ex, fig in (
        ("example1", "Fig. 3"),
        ("example2", "Fig. 5a"),
        ("example1_moving", "Fig. 3 variant, moving target"),
    ):
        r = results[ex]
        f, rn = r["methods"]["fim"], r["methods"]["random"]
        dm, ds = paired_difference(rn["errors"], f["errors"])
        lines += [
            f"### {fig} ({ex})",
            "",
            "| K | FIM mean ± s.e. (m) | random mean ± s.e. (m) | random/FIM | "
            "random − FIM, paired (m) | FIM median | random median | FIM CRLB | random CRLB | "
            "non-conv. FIM/random |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for j, K in enumerate(r["ks"]):
            lines.append(
                f"| {K} | {_fmt(f['mean'][j])} ± {_fmt(f['se'][j])} | "
                f"{_fmt(rn['mean'][j])} ± {_fmt(rn['se'][j])} | "
                f"{rn['mean'][j] / f['mean'][j]:.2f} | {_fmt(dm[j])} ± {_fmt(ds[j])} | "
                f"{_fmt(f['median'][j])} | {_fmt(rn['median'][j])} | {_fmt(f['crlb'][j])} | "
                f"{_fmt(rn['crlb'][j])} | "
                f"{int(f['nonconverged'][j])}/{int(rn['nonconverged'][j])} |"
            )
        lines.append("")
    mix = results["example2_sensor_mix"]
    lines += [
        "### Fig. 5b (example2): sensor mix of the FIM greedy selection",
        "",
        "| K | camera | RF (Doppler) | camera fraction |",
        "|---:|---:|---:|---:|",
    ]
    for K in results["example2"]["ks"]:
        if K <= len(mix["ks"]):
            c, d = int(mix["n_camera"][K - 1]), int(mix["n_doppler"][K - 1])
            lines.append(f"| {K} | {c} | {d} | {c / K:.2f} |")
    lines.append("")
    r = results["example3"]
    m = r["methods"]
    dm, ds = paired_difference(m["independent"]["errors"], m["cooperative"]["errors"])
    lines += [
        "### Fig. 7 (example3): mean ± s.e. (median) position error (m), K per agent",
        "",
        "| K | agent 1 only | agent 2 only | independent | cooperative | indep./coop. | "
        "indep. − coop., paired (m) |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for j, K in enumerate(r["ks"]):
        cells = [
            f"{_fmt(m[n]['mean'][j])} ± {_fmt(m[n]['se'][j])} ({_fmt(m[n]['median'][j])})"
            for n in EX3_METHODS
        ]
        ratio = m["independent"]["mean"][j] / m["cooperative"]["mean"][j]
        lines.append(f"| {K} | {' | '.join(cells)} | {ratio:.2f} | {_fmt(dm[j])} ± {_fmt(ds[j])} |")
    lines += [
        "",
        "### Fig. 7 (example3): bounds at the prior mean, K per agent",
        "",
        "| K | position CRLB a1 / a2 / indep. / coop. (m) | f(S) indep. (nats) | "
        "f(S) coop. (nats) | non-conv. (a1/a2/ind/coop) |",
        "|---:|---:|---:|---:|---:|",
    ]
    for j, K in enumerate(r["ks"]):
        crlbs = " / ".join(_fmt(m[n]["crlb"][j]) for n in EX3_METHODS)
        nc = "/".join(str(int(m[n]["nonconverged"][j])) for n in EX3_METHODS)
        lines.append(
            f"| {K} | {crlbs} | {_fmt(m['independent']['logdet'][j])} | "
            f"{_fmt(m['cooperative']['logdet'][j])} | {nc} |"
        )
    return "\n".join(lines)


# -- entry point --------------------------------------------------------------------------------
def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=int, default=None, help="Monte-Carlo trials per example "
                   f"(default {DEFAULT_TRIALS}, {QUICK_TRIALS} with --quick)")  # fmt: skip
    p.add_argument("--out", type=Path, default=Path("docs/figures"), help="figure directory")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED, help="master seed")
    p.add_argument("--quick", action="store_true", help=f"{QUICK_TRIALS} trials, K in {QUICK_KS}")
    args = p.parse_args(argv)
    if args.trials is None:
        args.trials = QUICK_TRIALS if args.quick else DEFAULT_TRIALS
    if args.trials < 2:
        p.error("--trials must be >= 2 (standard errors need two trials)")
    return args


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run every experiment, write the four figures, print the tables; return the numbers."""
    args = parse_args(argv)
    ks = QUICK_KS if args.quick else FULL_KS
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    ss1, ss2, ss3, ss4 = np.random.SeedSequence(args.seed).spawn(4)
    n = args.trials
    runs: list[tuple[str, Callable[[], dict[str, Any]]]] = [
        ("example1", lambda: run_single_agent("example1", ks, n, ss1)),
        ("example2", lambda: run_single_agent("example2", ks, n, ss2)),
        ("example3", lambda: run_example3(ks, n, ss3)),
        (
            "example1_moving",
            lambda: run_single_agent(
                "example1", ks, n, ss4, desc="example1 (moving target)", **MOVING_VARIANT
            ),
        ),
    ]
    results: dict[str, Any] = {name: fn() for name, fn in runs}
    results["example2_sensor_mix"] = sensor_mix("example2", max(ks), args.seed)
    paths = {name: out / f"{name}.png" for name in FIGURE_NAMES}
    plot_fig3(results["example1"], results["example1_moving"], n, paths["kirchner_fig3"])
    plot_fig5(
        results["example2"], results["example2_sensor_mix"], args.trials, paths["kirchner_fig5"]
    )
    plot_fig7(results["example3"], args.trials, paths["kirchner_fig7"])
    results["geometry_selections"] = plot_geometry(args.seed, paths["kirchner_geometry"])
    wall = time.perf_counter() - t0
    results["figures"] = {k: str(v) for k, v in paths.items()}
    results["config"] = {
        "trials": args.trials,
        "seed": args.seed,
        "quick": bool(args.quick),
        "ks": list(ks),
        "wall_time_s": wall,
    }
    print(format_tables(results))
    print(f"\ntrials={args.trials} seed={args.seed} wall time {wall:.1f} s; figures in {out}")
    return results


if __name__ == "__main__":
    main()
