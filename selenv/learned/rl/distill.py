"""One DAgger / expert-iteration loop: distil a labeller into a candidate-scoring policy.

Rounds of DAgger (Ross et al. 2011): round ``r`` collects labelled decisions (round 0 on the
labeller's or the starting policy's trajectories, later rounds on the current policy's), and
the policy's logits are fitted to all labels so far (ListNet,
:func:`selenv.learned.rl.ranking.fit_ranking`). The expert-iteration scripts
(``selenv.train.train_cl_expert``, ``selenv.train.train_landmark_expert``) run
:func:`run_expert_iteration`; the clustering DAgger round (``selenv.train.train_clustering_dagger``)
is one round of the same loop through :func:`collected` and :func:`fit_round`.

The run management is the trainer base's (:mod:`selenv.learned.trainer`): the output lock,
the ``<out stem>.last.zip`` state (+ ``.json``, ``.fit.pt`` mid-fit) written after every
collection, every ``--checkpoint-every`` fit epochs and every round, the stop on SIGINT /
SIGTERM or ``--max-minutes`` (:class:`~selenv.learned.trainer.RunStop`, checked after every
collection and every fit epoch), and ``--resume``, which continues to the weights of an
uninterrupted run, bit for bit.
"""

from __future__ import annotations

import contextlib
import copy
import inspect
import json
import shlex
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, cast

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from selenv.atomic import write_json
from selenv.envs.resolved import resolved_env_config
from selenv.exits import Terminated, UsageError
from selenv.learned.config import arg, check_outputs, usage_error
from selenv.learned.rl.agent import load_metadata
from selenv.learned.rl.ranking import (
    FitState,
    RankingData,
    check_ranking_sizes,
    fit_ranking,
    fit_state_path,
    load_labels,
    read_fit_state,
    read_resume,
    save_labels,
    save_resumable,
)
from selenv.learned.rl.safe_load import model_from_checkpoint, read_weights
from selenv.learned.rl.views import CandidateViewWrapper, view_for
from selenv.learned.trainer import (
    RESUME_FREE,
    RunStop,
    TrainingInterrupted,
    TrainingTerminated,
    check_max_minutes,
    evaluation_stops,
    last_paths,
    output_lock,
    read_checkpoint_metadata,
    rng_state,
    run_arg,
    save_final,
    set_rng_state,
    stop_exception,
    verify_pair,
)
from selenv.untrusted import json_object

__all__ = [
    "FREE_OPTIONS",
    "ExpertConfig",
    "FitOptions",
    "Progress",
    "check_expert_outputs",
    "collected",
    "evaluate_with_bench",
    "expert_outputs",
    "expert_run",
    "fit_round",
    "labels_path",
    "read_run_inputs",
    "round_path",
    "run_expert_iteration",
    "save_state",
    "state_files",
]

#: options that may differ between an interrupted run and its --resume: the run options
FREE_OPTIONS = RESUME_FREE

#: keys of the starting checkpoint's metadata that describe it rather than the new weights
#: (its results and its own expert iteration): kept under ``initialised_from``
_NOT_INHERITED = (
    "checkpoint_sha256",
    "expert_iteration",
    "held_out_bench",
    "held_out_vs_rollout",
    "initialised_from",
    "metrics",
    "resume_state",
)


# -- options -------------------------------------------------------------------------------------
@dataclass
class FitOptions:
    """The options of every distillation script: the ranking fit and the run (``--kebab-case``)."""

    epochs: int = arg(20, "epochs of the ranking fit (ListNet) per round")
    learning_rate: float = arg(5e-4, "Adam learning rate of the ranking fit")
    temperature: float = arg(
        0.1, "temperature T of the ListNet targets softmax(-dJ / (T * spread of dJ))"
    )
    workers: int = arg(2, "labelling worker processes")
    progress: bool = run_arg("progress", True)
    allow_large: bool = arg(
        False,
        "lift the ceilings of --rounds (100), --states-per-round / --states (10^6), --epochs "
        "(10,000) and --eval-episodes (100,000)",
    )
    max_minutes: float | None = run_arg(
        "max_minutes", None, unit="a collection, a fit epoch or a round"
    )


@dataclass
class ExpertConfig(FitOptions):
    """The options of an expert-iteration script; a script's ``Config`` sets its defaults."""

    checkpoint: str = arg("", "starting weights (a .zip)")
    out: str = arg(
        "runs/expert/policy.zip",
        "the trained checkpoint (.zip); also writes its .json, <out>_round<r>.zip/.json per "
        "round and <out>.bench.json",
    )
    force: bool = run_arg("force", False)
    env_kwargs: str = arg("{}", "JSON object of gymnasium.make keyword arguments")
    rounds: int = arg(3, "DAgger rounds (round 0 follows the labeller, later ones the policy)")
    states_per_round: int = arg(1500, "labelled decisions collected per round")
    top_k: int = arg(3, "the labeller scores its top-k candidates")
    horizon: int = arg(5, "filter steps the labeller simulates after the current one")
    explore: float = arg(0.05, "random action probability on the labelling trajectories")
    seed: int = arg(0, "seed of the labelling episodes (round r: 100 * seed + r) and the fit")
    eval_episodes: int = run_arg("eval_episodes", 30, note="by selenv bench")
    eval_seed: int = run_arg("eval_seed", 1000)
    checkpoint_every: int = run_arg(
        "checkpoint_every",
        5,
        unit="fit epochs",
        note="<out stem>.last.zip (+ .json) is also written after every collection and round",
    )
    resume: str = run_arg(
        "resume",
        "",
        unit="<out stem>.last.zip or a round checkpoint <out>_round<r>.zip",
        note="weights, labels so far, round, fit epoch and optimizer",
    )


# -- files ---------------------------------------------------------------------------------------
def round_path(out: str | Path, r: int) -> Path:
    """Round ``r``'s checkpoint of ``--out``: ``<out stem>_round<r>.zip``."""
    path = Path(out)
    return path.with_name(f"{path.stem}_round{r}.zip")


def labels_path(out: str | Path, r: int) -> Path:
    """The labels collected in round ``r``: ``<out stem>_round<r>.labels.npz``."""
    return round_path(out, r).with_suffix(".labels.npz")


def expert_outputs(cfg: Any) -> list[Path]:
    """Every file an expert-iteration run writes (checkpoint, rounds, bench JSON)."""
    out = Path(cfg.out)
    files = [out, out.with_suffix(".json")]
    for r in range(max(cfg.rounds, 0)):
        files += [round_path(out, r), round_path(out, r).with_suffix(".json")]
    if cfg.eval_episodes:
        files.append(out.with_suffix(".bench.json"))
    return files


def state_files(cfg: Any) -> list[Path]:
    """The resume files of a run besides :func:`expert_outputs`: labels, ``.last`` state."""
    last = last_paths(cfg.out)
    return [
        *(labels_path(cfg.out, r) for r in range(max(cfg.rounds, 0))),
        *last,
        fit_state_path(last[0]),
    ]


def check_expert_outputs(cfg: Any, prog: str) -> None:
    """Exit 2 (one line, before any work) on outputs that exist or cannot be written.

    A fresh run refuses every existing output and resume file without ``--force``, and an
    unfinished run's ``<out stem>.last.zip`` with a hint to ``--resume`` it. With
    ``--resume`` the round files are the interrupted run's (read or rewritten identically);
    only the final outputs are checked, and the ``--resume`` file must exist. A bad
    ``--max-minutes`` is refused here too.
    """
    try:
        check_max_minutes(getattr(cfg, "max_minutes", None))
    except UsageError as exc:
        usage_error(prog, exc)
    out = Path(cfg.out)
    final = [out, out.with_suffix(".json")]
    if cfg.eval_episodes:
        final.append(out.with_suffix(".bench.json"))
    if cfg.resume:
        if not Path(cfg.resume).is_file():
            usage_error(prog, f"--resume {cfg.resume}: no such checkpoint")
        check_outputs(prog, final, force=cfg.force)
        return
    last = last_paths(out)[0]
    if last.exists() and not cfg.force:
        usage_error(
            prog,
            f"{last} exists (an unfinished run of this --out): continue it with --resume "
            f"{last}, or pass --force to start over",
        )
    check_outputs(prog, [*expert_outputs(cfg), *state_files(cfg)], force=cfg.force)


@contextlib.contextmanager
def expert_run(cfg: Any, prog: str) -> Iterator[None]:
    """Check an expert-iteration run's sizes and outputs (exit 2), then hold the ``--out`` lock."""
    check_ranking_sizes(cfg)  # every size in range and under its ceiling, before any work
    check_expert_outputs(cfg, prog)
    with output_lock(cfg.out, prog):  # one run per --out
        yield


# -- the loop's steps ----------------------------------------------------------------------------
@dataclass
class Progress:
    """What a run has completed (restored from a ``--resume`` checkpoint)."""

    rounds_done: int = 0
    labels: list[dict[str, Any]] = field(default_factory=list)
    parts: list[RankingData] = field(default_factory=list)
    fit: FitState | None = None
    epochs_done: int = 0
    rounds_log: list[Any] = field(default_factory=list)
    wall_before: float = 0.0
    start: float = field(default_factory=time.perf_counter)

    def wall(self) -> float:
        """Seconds of training so far, the stopped invocations' included."""
        return round(self.wall_before + time.perf_counter() - self.start, 1)


def save_state(
    model: Any,
    meta: dict[str, Any],
    run: Progress,
    path: Path,
    interrupted: str | None = None,
    fit: FitState | None = None,
) -> None:
    """Write the resumable state of ``run`` as checkpoint ``path`` (``"complete": false``)."""
    snap = copy.deepcopy(meta)
    snap["complete"] = False
    snap["resume_state"] = {
        "rounds_done": run.rounds_done,
        "labels": list(run.labels),
        "rng": rng_state(),
        "wall_seconds": run.wall(),
    }
    if interrupted is not None:
        snap["interrupted"] = interrupted
    save_resumable(model, snap, path, fit)


Save = Callable[[str | None, FitState | None], None]


def collected(
    part: RankingData, path: Path, r: int, run: Progress, flag: RunStop, save: Save
) -> str | None:
    """Keep round ``r``'s labels ``part`` (file ``path``) and the state; the stop, if any.

    The labels and the state are written with the signals deferred; the budget is checked
    first, so a spent ``--max-minutes`` is recorded in the state that stops the run.
    """
    with flag:
        sha = save_labels(part, path)
        run.labels.append({"round": r, "states": len(part), "sha256": sha})
        run.parts.append(part)
        run.epochs_done, run.fit = 0, FitState(0, {})
        flag.check_budget()
        save(flag.signal, run.fit)  # labels collected: a resume fits them
    return flag.signal


def fit_round(
    cfg: Any,
    model: Any,
    data: RankingData,
    run: Progress,
    *,
    seed: int,
    flag: RunStop,
    save: Save,
    stop: Callable[[str], BaseException],
) -> dict[str, Any]:
    """The ranking fit of one round, resumable; returns its metrics.

    Run with the signals deferred: after every epoch the budget is checked and, every
    ``cfg.checkpoint_every`` epochs, the state saved; a signal or a spent budget ends the
    fit after the epoch in progress, saves the state and raises ``stop(name)``.
    """

    def after_epoch(state: FitState) -> bool:
        run.epochs_done, run.fit = state.epochs_done, state
        if state.epochs_done < cfg.epochs:
            flag.check_budget()  # (after the last epoch the caller checks, between rounds)
        every = cfg.checkpoint_every
        if flag.signal is None and every and state.epochs_done % every == 0:
            if state.epochs_done < cfg.epochs:
                save(None, state)
        return flag.signal is not None

    fit = fit_ranking(
        model.policy,
        data,
        epochs=cfg.epochs,
        learning_rate=cfg.learning_rate,
        temperature=cfg.temperature,
        seed=seed,
        progress=cfg.progress,
        start=run.fit,
        after_epoch=after_epoch,
    )
    if fit["epochs_done"] < cfg.epochs:  # stopped after a completed epoch
        name = flag.signal or "SIGINT"
        save(name, run.fit)
        raise stop(name)
    return fit


# -- expert iteration ----------------------------------------------------------------------------
def read_run_inputs(
    cfg: Any,
    env_id: str,
    block: str,
    free: tuple[str, ...],
    *,
    load: Callable[[Any], dict[str, Any]] = load_metadata,
) -> tuple[dict[str, Any], dict[str, Any] | None, dict[str, Any]]:
    """The env keywords, the ``--resume`` metadata (or ``None``) and the starting checkpoint's.

    ``cfg.checkpoint_every`` must be >= 0; ``cfg.env_kwargs`` a JSON object (bounded); a
    ``cfg.resume`` checkpoint's ``meta[block]`` must equal this run's options except
    ``free``; ``cfg.checkpoint`` must be a matched pair of ``env_id``. Sets torch's threads
    to 1 (the fit is small). ``load`` reads the starting checkpoint's metadata.

    Raises:
        UsageError: naming the option (exit 2).
        ValueError: ``cfg.checkpoint`` is a mismatched pair or of another env.
    """
    if cfg.checkpoint_every < 0:
        raise UsageError(f"--checkpoint-every must be >= 0, got {cfg.checkpoint_every}")
    try:  # size and nesting bounded before parsing
        kwargs = json_object(cfg.env_kwargs, "--env-kwargs")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    ours = {k: v for k, v in asdict(cfg).items() if k not in free}
    resumed = read_resume(cfg.resume, env_id=env_id, block=block, ours=ours) if cfg.resume else None
    src = load(cfg.checkpoint)
    if Path(cfg.checkpoint).with_suffix(".json").is_file():  # refuse a mismatched pair
        verify_pair(cfg.checkpoint, read_checkpoint_metadata(cfg.checkpoint))
    if src.get("env_id") != env_id:
        raise ValueError(f"--checkpoint {cfg.checkpoint} was trained on {src.get('env_id')!r}")
    torch.set_num_threads(1)
    return kwargs, resumed, src


def evaluate_with_bench(
    checkpoint: Path,
    cfg: Any,
    env_id: str,
    baseline: str = "greedy",
    agents: str | None = None,
) -> dict[str, Any]:
    """``selenv bench`` on the held-out seeds of ``cfg``; returns its JSON.

    ``agents`` (default ``baseline,rollout,ppo:checkpoint``) against ``baseline``, written to
    ``<checkpoint>.bench.json`` with the command under ``"command"``.
    """
    from selenv.cli import main as selenv_main

    out = checkpoint.with_suffix(".bench.json")
    argv = [
        "bench",
        env_id,
        "--agents",
        agents or f"{baseline},rollout,ppo:{checkpoint}",
        "--episodes",
        str(cfg.eval_episodes),
        "--seed",
        str(cfg.eval_seed),
        "--baseline",
        baseline,
        "--json",
        str(out),
    ]
    if cfg.env_kwargs.strip() not in ("", "{}"):
        argv += ["--env-kwargs", cfg.env_kwargs]
    code = selenv_main(argv)
    if code in (130, 143):  # the bench was stopped by a signal (it kept its finished episodes)
        raise KeyboardInterrupt if code == 130 else Terminated()
    if code != 0:
        raise RuntimeError(f"selenv {' '.join(argv)} exited with {code}")
    result: dict[str, Any] = json.loads(out.read_text())
    result["command"] = "selenv " + shlex.join(argv)
    return result


def run_expert_iteration(
    cfg: Any,
    argv: list[str] | None,
    env_id: str,
    collect: Callable[..., RankingData],
    script: str,
    baseline: str,
) -> dict[str, Any]:
    """Expert iteration: ``cfg.rounds`` rounds of (collect with ``collect``, fit), evaluated.

    Existing outputs without ``cfg.force`` exit with code 2 (the scripts check first). A
    SIGINT / SIGTERM or a spent ``--max-minutes`` keeps the last completed step as
    ``<out stem>.last.zip`` (+ ``.json``) and raises
    :class:`~selenv.learned.trainer.TrainingInterrupted` /
    :class:`~selenv.learned.trainer.TrainingTerminated` /
    :class:`~selenv.learned.trainer.TrainingBudgetReached` naming it and the ``--resume``
    option; ``cfg.resume`` continues such a run.
    """
    prog = f"python -m {script}"
    out = Path(cfg.out)
    if out.suffix != ".zip":
        raise UsageError(f"--out must end in .zip, got {cfg.out!r}")
    check_expert_outputs(cfg, prog)
    if cfg.rounds < 1:
        raise UsageError(f"--rounds must be >= 1, got {cfg.rounds}")
    kwargs, resumed, src = read_run_inputs(cfg, env_id, "expert_iteration", FREE_OPTIONS)
    flag = RunStop(getattr(cfg, "max_minutes", None))  # the budget counts from here
    started = time.perf_counter()
    env = gym.make(env_id, **kwargs)
    view = getattr(cfg, "view", None) or src.get("view")
    wrapped = CandidateViewWrapper(env, view_for(env_id, env, view))
    model = model_from_checkpoint(cfg.checkpoint, src, wrapped, device="cpu")
    space = cast(spaces.Dict, wrapped.observation_space)
    n = int(np.prod(space["action_mask"].shape or (0,)))
    meta: dict[str, Any] = {
        **{k: v for k, v in src.items() if k not in _NOT_INHERITED},
        # the starting weights' own results and iteration describe them, not this run's
        "initialised_from": {
            "checkpoint": str(cfg.checkpoint),
            **{k: src[k] for k in _NOT_INHERITED if k in src},
        },
        "view": view,
        "env_kwargs": kwargs,
        "env_config": resolved_env_config(env),
        "obs_layout": {**src["obs_layout"], "n_candidates_trained": n},
        "expert_iteration": {
            **asdict(cfg),
            "command": f"python -m {script} " + shlex.join(sys.argv[1:] if argv is None else argv),
            "rounds_log": [],
        },
        "metrics": None,
    }
    rows = {k: tuple(sp.shape or ()) for k, sp in space.spaces.items()}
    run = Progress()
    if resumed is not None:
        run = _restore(cfg, resumed, model, rows, n)
        meta["expert_iteration"]["rounds_log"] = run.rounds_log
    run.start = started
    last = last_paths(out)[0]

    def where() -> str:
        r = run.rounds_done
        if len(run.labels) > r:
            return f"round {r}'s labels collected, {run.epochs_done} of {cfg.epochs} fit epochs"
        return f"{r} of {cfg.rounds} rounds done"

    def stop(name: str) -> BaseException:
        return stop_exception(
            name,
            f"saved the last completed step ({where()}) as {last} (+ .json); continue with the "
            f"same command and --resume {last}",
        )

    def save(interrupted: str | None, fit: FitState | None) -> None:
        save_state(model, meta, run, last, interrupted, fit)

    try:
        _rounds(cfg, env_id, collect, out, view, kwargs, model, meta, run, flag, save, stop)
    except (KeyboardInterrupt, Terminated) as exc:  # outside a deferred section: collecting
        if isinstance(exc, TrainingInterrupted | TrainingTerminated) or flag.signal is not None:
            raise  # a stop already saved, or a second signal: abandon at once
        name = "SIGINT" if isinstance(exc, KeyboardInterrupt) else "SIGTERM"
        with flag:
            save(name, None)  # the weights and labels of the last completed step
        raise stop(name) from None
    meta["expert_iteration"]["wall_seconds"] = run.wall()
    meta["complete"] = True
    save_final(model, meta, out, [*last_paths(out), fit_state_path(last)], flag)
    if cfg.eval_episodes:
        with evaluation_stops(out):
            bench = evaluate_with_bench(out, cfg, env_id, baseline)
        meta["metrics"] = {
            "command": bench["command"],
            "results": bench["results"],
            "provenance": bench.get("provenance"),
        }
        write_json(out.with_suffix(".json"), meta)
    return meta


def _rounds(
    cfg: Any,
    env_id: str,
    collect: Callable[..., RankingData],
    out: Path,
    view: str | None,
    kwargs: dict[str, Any],
    model: Any,
    meta: dict[str, Any],
    run: Progress,
    flag: RunStop,
    save: Save,
    stop: Callable[[str], BaseException],
) -> None:
    """The rounds from ``run.rounds_done`` on: collect (abandoned on a signal), then fit."""
    last = last_paths(out)[0]
    for r in range(run.rounds_done, cfg.rounds):
        t0 = time.perf_counter()
        if len(run.labels) == r:  # collect round r's labels (a signal abandons them)
            # a collector that labels through a candidate view gets the checkpoint's view
            extra = {"view": view} if "view" in inspect.signature(collect).parameters else {}
            part = collect(
                kwargs,
                cfg.states_per_round,
                cfg.seed * 100 + r,
                **extra,
                top_k=cfg.top_k,
                horizon=cfg.horizon,
                explore=cfg.explore,
                behaviour=str(round_path(out, r - 1)) if r else None,
                workers=cfg.workers,
                progress=cfg.progress,
            )
            name = collected(part, labels_path(out, r), r, run, flag, save)
            if name is not None:
                raise stop(name)
        data = RankingData.concatenate(run.parts)
        with flag:
            fit = fit_round(
                cfg, model, data, run, seed=cfg.seed + r, flag=flag, save=save, stop=stop
            )
            log = {"round": r, "states": len(data), **fit}
            log["seconds"] = round(time.perf_counter() - t0)
            meta["expert_iteration"]["rounds_log"].append(log)
            run.rounds_done, run.fit, run.epochs_done = r + 1, None, 0
            print(json.dumps(log))
            save_state(model, meta, run, round_path(out, r))
            if r + 1 < cfg.rounds:
                flag.check_budget()  # a spent budget ends the run between rounds
            save_state(model, meta, run, last, flag.signal)
        if flag.signal is not None:
            raise stop(flag.signal)


def _restore(
    cfg: Any, meta: dict[str, Any], model: Any, rows: dict[str, tuple[int, ...]], n: int
) -> Progress:
    """The progress, weights, labels, fit state and generators of ``cfg.resume``.

    Raises:
        UsageError: a malformed resume state, a missing or altered labels, optimizer or
            round file, or weights that do not fit the model (one line naming the file).
    """
    path = Path(cfg.resume)
    state = meta["resume_state"]
    done = state.get("rounds_done")
    labels = state.get("labels")
    if (
        isinstance(done, bool)
        or not isinstance(done, int)
        or not 0 <= done <= cfg.rounds
        or not isinstance(labels, list)
        or len(labels) not in (done, done + 1)
        or len(labels) > cfg.rounds
        or not all(isinstance(e, dict) for e in labels)
    ):
        raise UsageError(f"--resume {path}: malformed resume state (rounds {done!r})")
    run = Progress(rounds_done=done, labels=list(labels))
    try:
        for r, entry in enumerate(labels):
            run.parts.append(
                load_labels(
                    labels_path(cfg.out, r),
                    sha256=str(entry.get("sha256")),
                    rows=cfg.states_per_round,
                    row_shapes=rows,
                    n_actions=n,
                )
            )
        run.fit = read_fit_state(path, state.get("fit")) if len(labels) > done else None
        weights = read_weights(path)
        model.policy.load_state_dict(weights, strict=True)
        if done and len(labels) == done:  # round `done` is collected by round done-1's policy
            behaviour = round_path(cfg.out, done - 1)
            theirs = read_weights(behaviour)
            if set(theirs) != set(weights) or not all(
                torch.equal(theirs[k], weights[k]) for k in weights
            ):
                raise ValueError(f"{behaviour} does not hold the weights of round {done - 1}")
        set_rng_state(state["rng"])
    except (ValueError, RuntimeError, KeyError, TypeError) as exc:
        raise UsageError(f"--resume {path}: {exc}") from None
    run.epochs_done = run.fit.epochs_done if run.fit is not None else 0
    log = meta["expert_iteration"].get("rounds_log")
    run.rounds_log = list(log[:done]) if isinstance(log, list) else []
    wall = state.get("wall_seconds")
    run.wall_before = float(wall) if isinstance(wall, int | float) else 0.0
    return run
