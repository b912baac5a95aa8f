"""Reproduce the results section (Sec. 6, Figs. 2-7) of Kirchner, Hespanha & Garagić (2020).

Monte-Carlo comparison of FIM-based greedy measurement selection (Algorithm 1) against uniformly
random selection, in two readings of the paper's examples:

* the paper's reading (presets ``example1`` one camera, ``example2`` camera + Doppler,
  ``example3`` two agents with camera + Doppler, independent vs cooperative selection): one
  stationary vehicle (Example 1: "a stationary vehicle"; Example 2 reuses Example 1's
  trajectories; every figure marks one ground-truth location), so only its position (and the
  Doppler offsets) are estimated;
* the moving-target variant (``example1_moving``, ``example2_moving``, ``example3_moving``):
  the same pools, velocity and curvature (theta_2, theta_3 of eq. 18) estimated too.

The geometry is fixed (``randomize=False``); per trial the true parameter vector is a fresh
draw from the prior (``make_problem`` on a per-trial generator). Selection uses only the
Jacobians at the prior mean (``problem.G``); measurements of the selected candidates are sampled
at the truth and ``theta`` is estimated by MAP (Gauss-Newton, prior ``N(mu0, P0)``). The metric
is the position error ``||theta_hat[:2] - theta_true[:2]||`` (m) at the window start. Fig. 2's
selection pattern is examined by a sweep of the camera altitude (``altitude_m``) in Example 1.
Results and the comparison with the paper: ``docs/reproductions/kirchner.md``.

Usage::

    python scripts/reproduce_kirchner.py [--trials N] [--out docs/figures] [--seed S] [--quick]
                                         [--allow-large]

``--trials`` above its ceiling (:data:`CEILINGS`, 10,000) is refused before any work (exit 2)
unless ``--allow-large`` is given.

Writes ``kirchner_fig3.png``, ``kirchner_fig5.png``, ``kirchner_fig7.png``,
``kirchner_geometry.png`` and ``kirchner_altitude.png`` into ``--out`` and prints the result
tables (Markdown). ``main(argv)`` returns every number as a dict.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, NullFormatter
from tqdm import tqdm

from selenv.agents.fim_solvers import cooperative_greedy, greedy_whitened
from selenv.atomic import describe_os_error, probe_writable, save_figure
from selenv.core.estimation import gauss_newton_map
from selenv.core.information import information_matrix, logdet_objective
from selenv.exits import UsageError, check_size, guarded_main
from selenv.families.fim import models as km
from selenv.families.fim.scenario import (
    CAMERA,
    DOPPLER,
    FIMProblem,
    config_from,
    make_problem,
)
from selenv.learned.config import UsageParser

#: budgets K of the full run (per agent in example 3)
FULL_KS: tuple[int, ...] = (2, 3, 4, 5, 6, 8, 10, 15, 20, 30, 50)
#: budgets K of ``--quick``
QUICK_KS: tuple[int, ...] = (2, 10, 30)
#: budget shown in the geometry figure (Figs. 2, 4, 6 show 10 selections)
GEOMETRY_K = 10
DEFAULT_TRIALS, QUICK_TRIALS = 100, 20
DEFAULT_SEED = 2020
EX3_METHODS = ("agent1", "agent2", "independent", "cooperative")
#: the two readings: preset of each example (paper = stationary target, moving = variant)
READINGS: dict[str, tuple[str, str, str]] = {
    "paper": ("example1", "example2", "example3"),
    "moving": ("example1_moving", "example2_moving", "example3_moving"),
}
#: Monte-Carlo runs in the order of their seed streams. The first four keep the streams of the
#: script from before the presets followed the paper (where ``example2`` / ``example3`` were
#: the moving presets), so their numbers are unchanged.
RUN_ORDER: tuple[str, ...] = (
    "example1", "example2_moving", "example3_moving", "example1_moving", "example2", "example3",
)  # fmt: skip
#: camera altitudes (m) of the Fig. 2 sweep (Example 1); the presets fly at 50 m
ALTITUDES_M: tuple[float, ...] = (2.0, 3.0, 5.0, 7.0, 10.0, 12.0, 14.0, 15.0, 20.0, 30.0, 50.0)
#: altitude of the Example 1 panel that shows the paper's closeness / viewing-angle compromise
GEOMETRY_ALTITUDE_M = 5.0
#: bearings (deg, seen from the nominal target) further apart than this are distinct directions
DIRECTION_GAP_DEG = 5.0
FIGURE_NAMES = (
    "kirchner_fig3", "kirchner_fig5", "kirchner_fig7", "kirchner_geometry", "kirchner_altitude",
)  # fmt: skip


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


# -- selections -----------------------------------------------------------------------------------
class SelectionCache:
    """Greedy selections per budget, recomputed only when the whitened pool ``G`` changes.

    With a fixed geometry ``problem.G`` (Jacobians at the prior mean) and hence every greedy
    selection is the same in every trial; the cache checks that instead of assuming it.
    """

    def __init__(self, select: Callable[[FIMProblem, int], Any]) -> None:
        self._select = select
        self._G: np.ndarray | None = None
        self._Q0: np.ndarray | None = None
        self._by_k: dict[int, Any] = {}

    def __call__(self, problem: FIMProblem, K: int) -> Any:
        """The selection of ``K`` picks on ``problem`` (computed once per distinct pool)."""
        same = (
            self._G is not None
            and self._Q0 is not None
            and np.array_equal(self._G, problem.G)
            and np.array_equal(self._Q0, problem.Q0)
        )
        if not same:
            self._G, self._Q0, self._by_k = problem.G, problem.Q0, {}
        if K not in self._by_k:
            self._by_k[K] = self._select(problem, K)
        return self._by_k[K]


def greedy_indices(problem: FIMProblem, K: int) -> np.ndarray:
    """Algorithm 1 on the whole pool: ``K`` candidate indices in pick order."""
    return np.asarray(greedy_whitened(problem.Q0, problem.G, K).indices, dtype=np.intp)


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
    greedy = SelectionCache(greedy_indices)
    for t, tss in enumerate(tqdm(ss.spawn(trials), desc=desc or preset, unit="trial")):
        rng_problem, rng_noise, rng_select = _trial_rngs(tss)
        problem = make_problem(cfg, rng_problem)
        Y = problem.sample_measurements(rng_noise)  # all candidates: common noise for both
        for j, K in enumerate(ks):
            fim = greedy(problem, K)
            rnd = rng_select.choice(problem.N, size=K, replace=False)
            _evaluate(recs["fim"], t, j, problem, Y, fim)
            _evaluate(recs["random"], t, j, problem, Y, rnd)
            n_camera[t, j] = int(np.sum(problem.sensor[fim] == CAMERA))
            n_doppler[t, j] = int(np.sum(problem.sensor[fim] == DOPPLER))
    return {
        "preset": preset,
        "overrides": dict(overrides),
        "param_names": list(problem.param_names),
        "ks": list(ks),
        "methods": {name: summarize(rec) for name, rec in recs.items()},
        "fim_n_camera": n_camera.mean(axis=0),
        "fim_n_doppler": n_doppler.mean(axis=0),
    }


def sensor_mix(preset: str, k_max: int, seed: int) -> dict[str, Any]:
    """Camera / Doppler counts of the greedy selection for every K in 1..k_max.

    ``problem.G`` is evaluated at the prior mean on the fixed geometry, so it (and hence the
    greedy selection) is the same for every trial; one problem suffices.
    """
    problem = make_problem(config_from(preset, randomize=False), np.random.default_rng(seed))
    ks = np.arange(1, k_max + 1)
    cam, dop = [], []
    for K in ks:
        sel = greedy_indices(problem, int(K))
        cam.append(int(np.sum(problem.sensor[sel] == CAMERA)))
        dop.append(int(np.sum(problem.sensor[sel] == DOPPLER)))
    cam_a, dop_a = np.array(cam), np.array(dop)
    return {
        "preset": preset,
        "ks": ks,
        "n_camera": cam_a,
        "n_doppler": dop_a,
        "camera_fraction": cam_a / ks,
        "doppler_fraction": dop_a / ks,
    }


# -- Fig. 2: selection pattern vs camera altitude -----------------------------------------------
def pick_directions(problem: FIMProblem, idx: np.ndarray) -> dict[str, Any]:
    """Where the picks ``idx`` view the target from (relative to its nominal track).

    Returns per pick (in time order) the time (s), horizontal range (m) and bearing (deg, from
    the nominal target position at that time, relative to the bearing of the path's end, the
    closest approach), the number of distinct viewing directions (bearings split wherever two
    consecutive sorted bearings are more than ``DIRECTION_GAP_DEG`` apart), the bearing spread
    (max - min, deg) and the number of picks more than ``DIRECTION_GAP_DEG`` away from the
    final bearing ("away from the closest approach").
    """
    ix = np.sort(np.asarray(idx, dtype=np.intp))
    full_mean = problem.full_theta(problem.theta_prior_mean)
    q, _ = km.target_state(full_mean, problem.times[ix])
    rel = problem.positions[ix, :2] - q
    pool = problem.pool(int(problem.agent[ix[0]]))
    last = pool[np.argmax(problem.times[pool])]
    q_end, _ = km.target_state(full_mean, problem.times[[last]])
    end = problem.positions[last, :2] - q_end[0]
    bearing = np.degrees(np.arctan2(rel[:, 1], rel[:, 0]) - np.arctan2(end[1], end[0]))
    bearing = (bearing + 180.0) % 360.0 - 180.0
    b = np.sort(bearing)
    return {
        "times": problem.times[ix],
        "ranges": np.hypot(rel[:, 0], rel[:, 1]),
        "bearings": bearing,
        "n_directions": 1 + int(np.sum(np.diff(b) > DIRECTION_GAP_DEG)),
        "spread_deg": float(b[-1] - b[0]),
        "n_away": int(np.sum(np.abs(bearing) > DIRECTION_GAP_DEG)),
    }


def altitude_sweep(
    altitudes: Sequence[float], K: int, seed: int, preset: str = "example1"
) -> dict[str, Any]:
    """Example 1 with the camera at each altitude: where the ``K`` picks lie.

    ``preset``: ``"example1"`` (the paper's reading, stationary target) or
    ``"example1_moving"`` (the variant: velocity and curvature estimated too). The greedy
    selection depends only on the geometry and the prior mean (not on the truth draw), so one
    problem per altitude gives the exact selection.
    """
    rows = []
    for alt in altitudes:
        cfg = config_from(preset, randomize=False, altitude_m=float(alt))
        problem = make_problem(cfg, np.random.default_rng(seed))
        rows.append(
            {"altitude_m": float(alt), **pick_directions(problem, greedy_indices(problem, K))}
        )
    return {"K": K, "preset": preset, "rows": rows}


# -- example 3 ----------------------------------------------------------------------------------
def position_interest(problem: FIMProblem) -> list[int]:
    """Indices of the target position ``(x, y)`` among the estimated parameters."""
    names = list(problem.param_names)
    return [names.index("x"), names.index("y")]


def ex3_selections(problem: FIMProblem, K: int, objective: str = "logdet") -> dict[str, np.ndarray]:
    """Global candidate indices of each example-3 method for ``K`` picks per agent.

    ``objective``: the criterion of every agent's greedy, ``"logdet"`` (eq. 5/9, the paper's)
    or ``"trace"`` (eq. 6 on the target position ``(x, y)``: the A-optimal position MSE).
    """
    pools = [problem.pool(i) for i in range(problem.config.n_agents)]
    pairs = [(problem.H[p], problem.R[p]) for p in pools]
    crit: dict[str, Any] = {}
    if objective != "logdet":
        crit = {"objective": objective, "interest": position_interest(problem)}
    out: dict[str, np.ndarray] = {}
    for mode in ("independent", "cooperative"):
        coop = cooperative_greedy(problem.Q0, pairs, [K] * len(pools), mode=mode, **crit)
        per_agent = [p[list(s.indices)] for p, s in zip(pools, coop.selections, strict=True)]
        out[mode] = np.concatenate(per_agent).astype(np.intp)
        if mode == "independent":  # each agent alone = its own Algorithm-1 selection on Q0
            out["agent1"], out["agent2"] = per_agent[0], per_agent[1]
    return out


def run_example3(
    preset: str,
    ks: Sequence[int],
    trials: int,
    ss: np.random.SeedSequence,
    objective: str = "logdet",
) -> dict[str, Any]:
    """Agent 1 alone, agent 2 alone, both independent, cooperative (``K`` picks per agent).

    ``objective``: the selection criterion (:func:`ex3_selections`); trials depend on ``ss``
    only, so two runs from equal seed sequences see the same truths and noise (paired).
    """
    cfg = config_from(preset, randomize=False)
    recs = {name: _new_record(trials, len(ks)) for name in EX3_METHODS}
    select = SelectionCache(lambda problem, K: ex3_selections(problem, K, objective))
    for t, tss in enumerate(tqdm(ss.spawn(trials), desc=preset, unit="trial")):
        rng_problem, rng_noise, _ = _trial_rngs(tss)
        problem = make_problem(cfg, rng_problem)
        Y = problem.sample_measurements(rng_noise)
        for j, K in enumerate(ks):
            sels = select(problem, K)
            for name in EX3_METHODS:
                _evaluate(recs[name], t, j, problem, Y, sels[name])
    return {
        "preset": preset,
        "objective": objective,
        "param_names": list(problem.param_names),
        "ks": list(ks),
        "methods": {name: summarize(rec) for name, rec in recs.items()},
    }


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


READING_TITLES = {
    "paper": "paper's reading: stationary target",
    "moving": "variant: moving target (velocity, curvature estimated)",
}


def plot_fig3(paper: dict[str, Any], moving: dict[str, Any], trials: int, path: Path) -> None:
    fig = Figure(figsize=(13, 5), layout="constrained")
    axes = fig.subplots(1, 2, sharey=True)
    for ax, r, reading in zip(axes, (paper, moving), READING_TITLES, strict=True):
        _error_curve(ax, r["ks"], r["methods"]["fim"], "red", "FIM greedy")
        _error_curve(ax, r["ks"], r["methods"]["random"], "blue", "random")
        title = f"Fig. 3 ({r['preset']}, one camera), {trials} trials\n{READING_TITLES[reading]}"
        _style_error_axes(ax, "number of measurements selected K (of 1000)", title)
    axes[1].yaxis.set_tick_params(labelleft=True)
    save_figure(fig, path, dpi=120)


def plot_fig5(
    paper: dict[str, Any],
    moving: dict[str, Any],
    mixes: dict[str, dict[str, Any]],
    trials: int,
    path: Path,
) -> None:
    fig = Figure(figsize=(18, 5.2), layout="constrained")
    ax_a, ax_m, ax_b = fig.subplots(1, 3)
    for ax, r, reading in ((ax_a, paper, "paper"), (ax_m, moving, "moving")):
        _error_curve(ax, r["ks"], r["methods"]["fim"], "red", "FIM greedy")
        _error_curve(ax, r["ks"], r["methods"]["random"], "blue", "random")
        _style_error_axes(
            ax,
            "number of measurements selected K (of 1000 camera + 1000 RF)",
            f"Fig. 5a ({r['preset']}), {trials} trials\n{READING_TITLES[reading]}",
        )
    ax_m.sharey(ax_a)
    for reading, ls in (("paper", "-"), ("moving", "--")):
        mix = mixes[reading]
        k, tag = mix["ks"], "stationary" if reading == "paper" else "moving"
        ax_b.plot(k, mix["camera_fraction"], ls, color="red", marker="o", ms=3,
                  label=f"camera, {tag} ({mix['preset']})")  # fmt: skip
        ax_b.plot(k, mix["doppler_fraction"], ls, color="blue", marker="s", ms=3,
                  label=f"RF (Doppler), {tag}")  # fmt: skip
    ax_b.axhline(2 / 3, color="red", ls=":", lw=1, label="paper: ~2/3 camera")
    ax_b.axhline(1 / 3, color="blue", ls=":", lw=1, label="paper: ~1/3 RF")
    mix = mixes["paper"]
    if GEOMETRY_K <= len(mix["ks"]):
        c, d = mix["n_camera"][GEOMETRY_K - 1], mix["n_doppler"][GEOMETRY_K - 1]
        cm = mixes["moving"]["n_camera"][GEOMETRY_K - 1]
        dm = mixes["moving"]["n_doppler"][GEOMETRY_K - 1]
        ax_b.annotate(
            f"K={GEOMETRY_K}: {c} camera + {d} RF (stationary),\n"
            f"{cm} + {dm} (moving); paper: 7 + 3",
            (GEOMETRY_K, c / GEOMETRY_K),
            xytext=(GEOMETRY_K + 5, 0.95),
            arrowprops={"arrowstyle": "->"},
            fontsize=8,
        )
    ax_b.set_ylim(0, 1.05)
    ax_b.set_xlabel("number of measurements selected K")
    ax_b.set_ylabel("fraction of FIM-selected measurements")
    ax_b.set_title("Fig. 5b: sensor mix of the greedy selection")
    ax_b.grid(True, alpha=0.3)
    ax_b.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2)
    save_figure(fig, path, dpi=120)


def plot_fig7(paper: dict[str, Any], moving: dict[str, Any], trials: int, path: Path) -> None:
    fig = Figure(figsize=(13, 5.2), layout="constrained")
    axes = fig.subplots(1, 2)
    styles = {
        "agent1": ("blue", "agent 1 only"),
        "agent2": ("green", "agent 2 only"),
        "independent": ("cyan", "both, independent selection"),
        "cooperative": ("red", "both, cooperative selection"),
    }
    for ax, res, reading in zip(axes, (paper, moving), READING_TITLES, strict=True):
        ks, m = np.asarray(res["ks"]), res["methods"]
        for i, (name, (color, label)) in enumerate(styles.items()):
            s = m[name]
            x = ks * (1.0 + 0.015 * (i - 1.5))  # small offsets keep the error bars apart
            ax.errorbar(x, s["mean"], yerr=s["se"], fmt="o-", color=color, lw=2, ms=4,
                        capsize=3, label=f"{label} (mean ± s.e.)")  # fmt: skip
            ax.plot(ks, s["crlb"], ":", color=color, lw=1.2)
        ax.plot([], [], ":", color="gray", label="CRLB at prior mean (same colours)")
        _style_error_axes(
            ax,
            "measurements selected per agent K",
            f"Fig. 7 ({res['preset']}, two agents), {trials} trials\n{READING_TITLES[reading]}",
        )
    save_figure(fig, path, dpi=120)


def _plot_geometry_panel(
    ax: Axes, problem: FIMProblem, sels: dict[str, np.ndarray], title: str
) -> None:
    for i in range(problem.config.n_agents):
        pool = problem.pool(i)
        cams = pool[problem.sensor[pool] == CAMERA]
        ax.plot(*problem.positions[cams, :2].T, "k-", lw=1, label="agent path" if i == 0 else None)
        start = problem.positions[cams[0], :2]
        ax.annotate(
            f"agent {i + 1} start",
            (start[0], start[1]),
            fontsize=7,
            xytext=(3, 3),
            textcoords="offset points",
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
            ax.scatter(pts[:, 0], pts[:, 1], s=size, marker=marker, facecolors=face,
                       edgecolors=color, zorder=3, label=label)  # fmt: skip
    s = np.linspace(0.0, problem.config.window_s, 200)
    q_true, _ = km.target_state(problem.full_theta(problem.theta_true), s)
    if problem.config.stationary:
        ax.plot(*problem.theta_true[:2], "g*", ms=14, mec="k", label="target truth (stationary)")
    else:
        ax.plot(*q_true.T, "g-", lw=2, label="target truth (window)")
        ax.plot(*problem.theta_true[:2], "g*", ms=14, mec="k", label="target truth at t=0")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2)


def plot_geometry(seed: int, path: Path) -> dict[str, Any]:
    """Figs. 2/4/6 (paper's reading): paths, greedy selections at K = 10, one truth draw.

    Example 1 is drawn twice: with the presets' 50 m camera altitude and at
    ``GEOMETRY_ALTITUDE_M``, where the picks show the paper's closeness / viewing-angle
    compromise (see :func:`altitude_sweep`).
    """
    fig = Figure(figsize=(16, 15), layout="constrained")
    axes = fig.subplots(2, 2).ravel()
    panels: tuple[tuple[str, dict[str, float], str, str], ...] = (
        ("example1", {}, "2", "1000"),
        ("example1", {"altitude_m": GEOMETRY_ALTITUDE_M}, "2", "1000"),
        ("example2", {}, "4", "1000 camera + 1000 RF"),
        ("example3", {}, "6", ""),
    )
    info: dict[str, Any] = {}
    for ax, (preset, over, fig_no, pool) in zip(axes, panels, strict=True):
        cfg = config_from(preset, randomize=False, **over)
        problem = make_problem(cfg, np.random.default_rng(seed))
        alt = f"camera at {cfg.altitude_m:g} m"
        key = preset if not over else f"{preset}_altitude_{cfg.altitude_m:g}m"
        if preset == "example3":
            ex3 = ex3_selections(problem, GEOMETRY_K)
            coop2 = np.setdiff1d(ex3["cooperative"], ex3["independent"])
            sels = {"selected": ex3["independent"], "cooperative": coop2}
            title = (
                f"Example 3 (Fig. {fig_no}), {alt}: {GEOMETRY_K} per agent, independent greedy\n"
                "(filled); hollow diamonds: agent-2 picks that change under cooperative selection"
            )
        else:
            sels = {"selected": greedy_indices(problem, GEOMETRY_K)}
            title = (
                f"Example {preset[-1]} (Fig. {fig_no}), {alt}: {GEOMETRY_K} greedy picks of {pool}"
            )
            if preset == "example1":
                d = pick_directions(problem, sels["selected"])
                title += (
                    f"\n{d['n_directions']} viewing direction(s), bearing spread "
                    f"{d['spread_deg']:.0f}°, {d['n_away']} picks away from the closest approach"
                )
        info[key] = {k: v.tolist() for k, v in sels.items()}
        _plot_geometry_panel(ax, problem, sels, title)
    fig.suptitle(
        "Geometry, paper's reading (stationary target): agent paths (candidate positions), "
        "K = 10 selections, target"
    )
    save_figure(fig, path, dpi=100)
    return info


def _altitude_axis(ax: Axes, alts: np.ndarray) -> None:
    ax.set_xscale("log")
    ax.set_xticks(alts)
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())


def plot_altitude(sweep: dict[str, Any], path: Path) -> None:
    """Fig. 2 pattern vs camera altitude: bearing and time of each pick, spread, directions."""
    fig = Figure(figsize=(13, 4.8), layout="constrained")
    ax_b, ax_s = fig.subplots(1, 2)
    rows = sweep["rows"]
    alts = np.array([r["altitude_m"] for r in rows])
    for r in rows:
        sc = ax_b.scatter(np.full(r["bearings"].size, r["altitude_m"]), r["bearings"],
                          c=r["times"], cmap="viridis", vmin=0, vmax=60, s=25)  # fmt: skip
    fig.colorbar(sc, ax=ax_b, label="time of the pick (s); path ends (closest) at 60 s")
    ax_b.axvline(GEOMETRY_ALTITUDE_M, color="gray", ls=":", lw=1)
    _altitude_axis(ax_b, alts)
    ax_b.set_xlabel("camera altitude (m)")
    ax_b.set_ylabel("bearing of the pick from the target,\nrelative to the closest approach (deg)")
    ax_b.set_title(f"Example 1: where the {sweep['K']} greedy picks view the target from")
    ax_b.grid(True, alpha=0.3)
    ax_s.plot(
        alts, [r["spread_deg"] for r in rows], "o-", color="red", label="bearing spread (deg)"
    )
    _altitude_axis(ax_s, alts)
    ax_s.set_xlabel("camera altitude (m)")
    ax_s.set_ylabel("bearing spread of the picks (deg)", color="red")
    ax_t = ax_s.twinx()
    ax_t.plot(alts, [r["n_away"] for r in rows], "s-", color="blue",
              label="picks away from the closest approach")  # fmt: skip
    ax_t.set_ylabel("picks away from the closest approach", color="blue")
    ax_s.set_title("closeness (0 away) vs viewing-angle diversity")
    ax_s.grid(True, alpha=0.3)
    h1, l1 = ax_s.get_legend_handles_labels()
    h2, l2 = ax_t.get_legend_handles_labels()
    ax_s.legend(h1 + h2, l1 + l2, fontsize=8, loc="center right")
    save_figure(fig, path, dpi=120)


# -- report -------------------------------------------------------------------------------------
def _fmt(x: float, digits: int = 2) -> str:
    return f"{x:.{digits}f}" if np.isfinite(x) else "nan"


def paired_difference(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-K mean and standard error of ``a - b`` over trials (same truth and noise per trial)."""
    d = a - b
    return d.mean(axis=0), d.std(axis=0, ddof=1) / np.sqrt(d.shape[0])


def _single_agent_table(r: dict[str, Any], heading: str) -> list[str]:
    f, rn = r["methods"]["fim"], r["methods"]["random"]
    dm, ds = paired_difference(rn["errors"], f["errors"])
    lines = [
        heading,
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
    return [*lines, ""]


def _example3_tables(r: dict[str, Any], label: str) -> list[str]:
    m = r["methods"]
    dm, ds = paired_difference(m["independent"]["errors"], m["cooperative"]["errors"])
    solo = [paired_difference(m[a]["errors"], m["independent"]["errors"]) for a in EX3_METHODS[:2]]
    lines = [
        f"### Fig. 7 ({label}): mean ± s.e. (median) position error (m), K per agent",
        "",
        "| K | agent 1 only | agent 2 only | independent | cooperative | "
        "a1 − indep., a2 − indep., paired (m) | indep./coop. | indep. − coop., paired (m) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for j, K in enumerate(r["ks"]):
        cells = [
            f"{_fmt(m[n]['mean'][j])} ± {_fmt(m[n]['se'][j])} ({_fmt(m[n]['median'][j])})"
            for n in EX3_METHODS
        ]
        alone = ", ".join(f"{_fmt(d[0][j], 3)} ± {_fmt(d[1][j], 3)}" for d in solo)
        ratio = m["independent"]["mean"][j] / m["cooperative"]["mean"][j]
        lines.append(
            f"| {K} | {' | '.join(cells)} | {alone} | {ratio:.2f} | "
            f"{_fmt(dm[j], 3)} ± {_fmt(ds[j], 3)} |"
        )
    lines += [
        "",
        f"### Fig. 7 ({label}): bounds at the prior mean, K per agent",
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
    return [*lines, ""]


def format_tables(results: dict[str, Any]) -> str:
    """Markdown tables of every figure's numbers, paper's reading first, then the variant."""
    lines: list[str] = []
    for ex, fig in (
        ("example1", "Fig. 3, paper's reading (stationary target)"),
        ("example1_moving", "Fig. 3 variant, moving target"),
        ("example2", "Fig. 5a, paper's reading (stationary target)"),
        ("example2_moving", "Fig. 5a variant, moving target"),
    ):
        params = ", ".join(results[ex]["param_names"])
        lines += _single_agent_table(results[ex], f"### {fig} ({ex}; estimated: {params})")
    mixes = {name: results[f"{name}_sensor_mix"] for name in ("example2", "example2_moving")}
    lines += [
        "### Fig. 5b: sensor mix of the FIM greedy selection (camera + RF, camera fraction)",
        "",
        "| K | example2 (stationary) | example2_moving |",
        "|---:|---:|---:|",
    ]
    for K in results["example2"]["ks"]:
        cells = []
        for mix in mixes.values():
            if K <= len(mix["ks"]):
                c, d = int(mix["n_camera"][K - 1]), int(mix["n_doppler"][K - 1])
                cells.append(f"{c} + {d} ({c / K:.2f})")
        if cells:
            lines.append(f"| {K} | {' | '.join(cells)} |")
    lines.append("")
    lines += _example3_tables(results["example3"], "example3, paper's reading")
    lines += _example3_tables(results["example3_moving"], "example3_moving, variant")
    lines += _example3_tables(
        results["example3_trace"], "example3, paper's reading, trace objective on (x, y)"
    )
    lt, tr = results["example3"]["methods"], results["example3_trace"]["methods"]
    lines += [
        "### Fig. 7: trace vs log-det selection on the same trials (example3), position error",
        "",
        "| K | independent: logdet − trace, paired (m) | cooperative: logdet − trace, paired (m) |",
        "|---:|---:|---:|",
    ]
    for j, K in enumerate(results["example3"]["ks"]):
        cells = []
        for mode in ("independent", "cooperative"):
            d, se = paired_difference(lt[mode]["errors"], tr[mode]["errors"])
            cells.append(f"{_fmt(d[j], 3)} ± {_fmt(se[j], 3)}")
        lines.append(f"| {K} | {' | '.join(cells)} |")
    lines.append("")
    for key in ("altitude_sweep", "altitude_sweep_moving"):
        if key in results:
            lines += format_sweep(results[key])
    return "\n".join(lines)


def format_sweep(sweep: dict[str, Any]) -> list[str]:
    """The Fig. 2 altitude sweep of one preset as a Markdown table (one row per altitude)."""
    lines = [
        f"### Fig. 2: {sweep['preset']} picks (K = {sweep['K']}) vs camera altitude",
        "",
        "| altitude (m) | pick times (s) | viewing directions | bearing spread (deg) | "
        "picks away from closest approach | horizontal range of the picks (m) |",
        "|---:|---|---:|---:|---:|---:|",
    ]
    for row in sweep["rows"]:
        times = ", ".join(f"{t:.1f}" for t in row["times"])
        lines.append(
            f"| {row['altitude_m']:g} | {times} | {row['n_directions']} | "
            f"{row['spread_deg']:.0f} | {row['n_away']} | "
            f"{row['ranges'].min():.0f}-{row['ranges'].max():.0f} |"
        )
    return [*lines, ""]


# -- entry point --------------------------------------------------------------------------------
PROG = "reproduce_kirchner.py"
#: ceilings on the work of one run, checked before anything runs (``--allow-large`` lifts them):
#: 100 trials take ~200 s on 2 cores, so 10,000 take about 5-6 hours
CEILINGS: dict[str, int] = {"--trials": 10_000}


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Command line (see the module docstring); usage errors are one line, exit 2."""
    p = UsageParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--trials", type=int, default=None, help="Monte-Carlo trials per example "
                   f"(default {DEFAULT_TRIALS}, {QUICK_TRIALS} with --quick; at least 2; "
                   f"ceiling {CEILINGS['--trials']:,})")  # fmt: skip
    p.add_argument("--out", type=Path, default=Path("docs/figures"), help="figure directory")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED, help="master seed (>= 0)")
    p.add_argument("--quick", action="store_true", help=f"{QUICK_TRIALS} trials, K in {QUICK_KS}")
    p.add_argument("--allow-large", action="store_true",
                   help="run sizes above the ceilings (--trials "
                   f"{CEILINGS['--trials']:,}), which are there to catch typos")  # fmt: skip
    args = p.parse_args(argv)
    if args.trials is None:
        args.trials = QUICK_TRIALS if args.quick else DEFAULT_TRIALS
    return args


def check_args(args: argparse.Namespace) -> None:
    """Every size and seed checked before any work (:class:`UsageError` naming the option).

    ``--trials`` must be >= 2 (standard errors need two trials) and at most its ceiling
    (:data:`CEILINGS`) unless ``--allow-large``; ``--seed`` must be >= 0.
    """
    check_size("--trials", args.trials, low=2, note=" (standard errors need two trials)")
    check_size("--trials", args.trials, ceiling=CEILINGS["--trials"], lifted=args.allow_large)
    check_size("--seed", args.seed, low=0)


def _check_out(folder: Path) -> None:
    """A real write probe of the output folder before any work (usage error: exit 2)."""
    try:
        probe_writable(folder / ".write-probe")
    except OSError as exc:
        raise UsageError(f"--out: {describe_os_error(exc, folder)}") from None


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run every experiment, write the five figures, print the tables; return the numbers."""
    args = parse_args(argv)
    check_args(args)
    ks = QUICK_KS if args.quick else FULL_KS
    out: Path = args.out
    _check_out(out)
    t0 = time.perf_counter()
    streams = dict(
        zip(RUN_ORDER, np.random.SeedSequence(args.seed).spawn(len(RUN_ORDER)), strict=True)
    )
    n = args.trials

    def runner(preset: str) -> Callable[[], dict[str, Any]]:
        if preset.startswith("example3"):
            return lambda: run_example3(preset, ks, n, streams[preset])
        return lambda: run_single_agent(preset, ks, n, streams[preset])

    results: dict[str, Any] = {preset: runner(preset)() for preset in RUN_ORDER}
    ex3 = streams["example3"]  # the same trials again (a fresh copy of the stream): paired
    same = np.random.SeedSequence(ex3.entropy, spawn_key=ex3.spawn_key)
    results["example3_trace"] = run_example3("example3", ks, n, same, objective="trace")
    for preset in ("example2", "example2_moving"):
        results[f"{preset}_sensor_mix"] = sensor_mix(preset, max(ks), args.seed)
    results["altitude_sweep"] = altitude_sweep(ALTITUDES_M, GEOMETRY_K, args.seed)
    results["altitude_sweep_moving"] = altitude_sweep(
        ALTITUDES_M, GEOMETRY_K, args.seed, preset="example1_moving"
    )
    paths = {name: out / f"{name}.png" for name in FIGURE_NAMES}
    plot_fig3(results["example1"], results["example1_moving"], n, paths["kirchner_fig3"])
    mixes = {
        "paper": results["example2_sensor_mix"],
        "moving": results["example2_moving_sensor_mix"],
    }
    plot_fig5(results["example2"], results["example2_moving"], mixes, n, paths["kirchner_fig5"])
    plot_fig7(results["example3"], results["example3_moving"], n, paths["kirchner_fig7"])
    results["geometry_selections"] = plot_geometry(args.seed, paths["kirchner_geometry"])
    plot_altitude(results["altitude_sweep"], paths["kirchner_altitude"])
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
    sys.exit(guarded_main(main, PROG))
