"""Expert iteration on ``CLScheduling-v1``: distil the non-myopic ``rollout`` into the policy.

Rounds of DAgger (:mod:`selenv.learned.rl.expert`): round 0 labels the states the ``rollout``
reference visits, every later round the states the current policy visits; every labelled
decision carries rollout's score of stop and of its ``top_k`` pairs; the candidate-scoring
policy's logits are fitted to all labels so far (ListNet,
:func:`selenv.learned.rl.ranking.fit_ranking`).
The policy starts from ``--checkpoint`` (default: the shipped CL policy, a softened greedy on
the previewed fused gains) and plays in the ``cl_pairs_fused_top3`` view: the candidates
rollout considers (stop and the three pairs of largest previewed gain), ranked by the
network. At play time it costs one greedy preview plus one network evaluation per decision
instead of rollout's ``top_k + 1`` simulated trajectories.

The result is evaluated by ``selenv bench`` against ``greedy`` and ``rollout`` on the
held-out seeds ``--eval-seed .. --eval-seed + --eval-episodes - 1`` (training episodes use
seeds >= 10**6), and the bench's paired statistics and the exact command are written into
the checkpoint's metadata.

    python -m selenv.train.train_cl_expert   # -> runs/train_cl_expert/policy.zip (~25 min, 2 cores)

Outputs (all refused if they exist, unless ``--force``): ``<out>.zip`` + ``.json``, every
round's ``<out>_round<r>.zip`` + ``.json`` with the labels it collected,
``<out>_round<r>.labels.npz``, and, with ``--eval-episodes``, ``<out>.bench.json``. Each
checkpoint and its JSON are written as an atomic pair (the JSON records the zip's
``checkpoint_sha256`` and the labels files' SHA-256).

Stopping and resuming (a stopped run loses at most the step in progress):

* the run's state ``<out stem>.last.zip`` (+ ``.json``, and ``.fit.pt``, the fit's Adam
  state, mid-fit) is written after every collection, every ``--checkpoint-every`` fit epochs
  and every round (``"complete": false``), and removed when the run completes;
* SIGINT / SIGTERM while labelling abandons the round's labels (the worker processes stop at
  once; they also die with this process after ``kill -9``); during a fit the current epoch
  completes. The state is saved with ``"interrupted": "SIGINT"`` / ``"SIGTERM"`` and the
  command exits 130 / 143 with one line naming the file and the ``--resume`` option; a
  second signal abandons at once (the files on disk stay intact);
* ``--resume <out stem>.last.zip`` (or a round checkpoint ``<out>_round<r>.zip``), with the
  options of the interrupted run, restores the weights, the rounds done, the labels so far
  (each file checked against its recorded SHA-256 and its array headers before it is read),
  the fit's epoch and optimizer and the random generators, and ends with the same weights as
  an uninterrupted run. Other options (seed, env, rounds, ...) or a checkpoint without a
  resume state are refused (exit 2, one line naming the difference).
"""

from __future__ import annotations

import copy
import json
import shlex
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, cast

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from selenv.atomic import write_json
from selenv.envs.resolved import resolved_env_config
from selenv.exits import DeferredSignals, Terminated, UsageError
from selenv.learned.config import arg, check_outputs, parse_config, usage_error
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, load_metadata
from selenv.learned.rl.expert import CL_ID, collect_cl_rollout_labels
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
from selenv.learned.rl.training import (
    TrainingInterrupted,
    TrainingTerminated,
    _rng_state,
    _set_rng_state,
    _stop_exception,
    last_paths,
    output_lock,
    read_checkpoint_metadata,
    run_cli,
    save_checkpoint,
    verify_pair,
)
from selenv.learned.rl.views import CandidateViewWrapper, view_for
from selenv.untrusted import json_object

SCRIPT = "selenv.train.train_cl_expert"


@dataclass
class Config:
    """Every field is a ``--kebab-case`` option."""

    checkpoint: str = arg(str(DEFAULT_CHECKPOINTS[CL_ID]), "starting weights (a .zip)")
    out: str = arg(
        "runs/train_cl_expert/policy.zip",
        "the trained checkpoint (.zip); also writes its .json, <out>_round<r>.zip/.json per "
        "round and <out>.bench.json",
    )
    force: bool = arg(False, "overwrite existing outputs of --out")
    env_kwargs: str = arg(
        "{}", "JSON object of gymnasium.make keyword arguments ({}: the benchmark preset)"
    )
    view: str = arg(
        "cl_pairs_fused_top3", "candidate view: the labeller's candidate set (stop + top-3 by gain)"
    )
    rounds: int = arg(3, "DAgger rounds (round 0 follows the labeller, later ones the policy)")
    states_per_round: int = arg(1500, "labelled decisions collected per round")
    top_k: int = arg(3, "the labeller (the bench's rollout reference) scores stop and its top-k")
    horizon: int = arg(5, "filter steps the labeller simulates after the current one")
    explore: float = arg(0.05, "random action probability on the labelling trajectories")
    epochs: int = arg(20, "epochs of the ranking fit (ListNet) per round")
    learning_rate: float = arg(5e-4, "Adam learning rate of the ranking fit")
    temperature: float = arg(
        0.1, "temperature T of the ListNet targets softmax(-dJ / (T * spread of dJ))"
    )
    workers: int = arg(2, "labelling worker processes")
    seed: int = arg(0, "seed of the labelling episodes (round r: 100 * seed + r) and the fit")
    progress: bool = arg(True, "show tqdm bars")
    eval_episodes: int = arg(
        30, "held-out episodes of the selenv bench evaluation after training (0: none)"
    )
    eval_seed: int = arg(1000, "seed of the first held-out episode (then +1, +2, ...)")
    checkpoint_every: int = arg(
        5,
        "fit epochs between the periodic state <out stem>.last.zip (+ .json) within a round; it "
        "is also written after every collection and round, and on SIGINT / SIGTERM (0: only "
        "then)",
    )
    allow_large: bool = arg(
        False,
        "lift the ceilings of --rounds (100), --states-per-round / --states (10^6), --epochs "
        "(10,000) and --eval-episodes (100,000)",
    )
    resume: str = arg(
        "",
        "continue an interrupted run (same options) from its <out stem>.last.zip or a round "
        "checkpoint <out>_round<r>.zip: weights, labels so far, round, fit epoch and optimizer",
    )


def expert_outputs(cfg: Any) -> list[Path]:
    """Every file an expert-iteration run writes (checkpoint, rounds, bench JSON)."""
    out = Path(cfg.out)
    files = [out, out.with_suffix(".json")]
    for r in range(max(cfg.rounds, 0)):
        files += [round_path(out, r), round_path(out, r).with_suffix(".json")]
    if cfg.eval_episodes:
        files.append(out.with_suffix(".bench.json"))
    return files


def parse_args(argv: list[str] | None = None) -> Config:
    """The run's :class:`Config` from the command line (and ``--config FILE``)."""
    return parse_config(Config, argv, (__doc__ or "").split("\n")[0], script=SCRIPT)


def outputs(cfg: Config) -> list[Path]:
    """The files the run writes."""
    return expert_outputs(cfg)


def evaluate_with_bench(
    checkpoint: Path,
    cfg: Any,
    env_id: str = CL_ID,
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


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Collect, fit (per round), save, evaluate; return the checkpoint's metadata."""
    cfg = parse_args(argv)
    check_ranking_sizes(cfg)  # every size in range and under its ceiling, before any work
    check_expert_outputs(cfg, f"python -m {SCRIPT}")
    with output_lock(cfg.out, f"python -m {SCRIPT}"):  # one run per --out
        return run_expert_iteration(cfg, argv, CL_ID, collect_cl_rollout_labels, SCRIPT, "greedy")


def round_path(out: str | Path, r: int) -> Path:
    """Round ``r``'s checkpoint of ``--out``: ``<out stem>_round<r>.zip``."""
    path = Path(out)
    return path.with_name(f"{path.stem}_round{r}.zip")


def labels_path(out: str | Path, r: int) -> Path:
    """The labels collected in round ``r``: ``<out stem>_round<r>.labels.npz``."""
    return round_path(out, r).with_suffix(".labels.npz")


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
    only the final outputs are checked, and the ``--resume`` file must exist.
    """
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


#: options that may differ between an interrupted run and its --resume
_FREE = (
    "out",
    "force",
    "progress",
    "eval_episodes",
    "eval_seed",
    "resume",
    "checkpoint_every",
    "allow_large",
)


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


def run_expert_iteration(
    cfg: Any,
    argv: list[str] | None,
    env_id: str,
    collect: Callable[..., RankingData],
    script: str,
    baseline: str,
) -> dict[str, Any]:
    """The DAgger loop shared by the expert-iteration scripts (module docstring).

    Existing outputs without ``cfg.force`` exit with code 2 (the scripts check first). A
    SIGINT / SIGTERM keeps the last completed step as ``<out stem>.last.zip`` (+ ``.json``)
    and raises :class:`~selenv.learned.rl.training.TrainingInterrupted` /
    :class:`~selenv.learned.rl.training.TrainingTerminated` naming it and the ``--resume``
    option; ``cfg.resume`` continues such a run (module docstring).
    """
    prog = f"python -m {script}"
    out = Path(cfg.out)
    if out.suffix != ".zip":
        raise UsageError(f"--out must end in .zip, got {cfg.out!r}")
    check_expert_outputs(cfg, prog)
    if cfg.rounds < 1:
        raise UsageError(f"--rounds must be >= 1, got {cfg.rounds}")
    if cfg.checkpoint_every < 0:
        raise UsageError(f"--checkpoint-every must be >= 0, got {cfg.checkpoint_every}")
    try:  # size and nesting bounded before parsing
        kwargs = json_object(cfg.env_kwargs, "--env-kwargs")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    ours = {k: v for k, v in asdict(cfg).items() if k not in _FREE}
    resumed = (
        read_resume(cfg.resume, env_id=env_id, block="expert_iteration", ours=ours)
        if cfg.resume
        else None
    )
    src = load_metadata(cfg.checkpoint)
    if Path(cfg.checkpoint).with_suffix(".json").is_file():  # refuse a mismatched pair
        verify_pair(cfg.checkpoint, read_checkpoint_metadata(cfg.checkpoint))
    if src.get("env_id") != env_id:
        raise ValueError(f"--checkpoint {cfg.checkpoint} was trained on {src.get('env_id')!r}")
    torch.set_num_threads(1)
    start = time.perf_counter()
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
    run = _Progress()
    if resumed is not None:
        run = _restore(cfg, resumed, model, rows, n)
        meta["expert_iteration"]["rounds_log"] = run.rounds_log
    last = last_paths(out)[0]
    flag = DeferredSignals()

    def save(path: Path, interrupted: str | None = None, fit: FitState | None = None) -> None:
        snap = copy.deepcopy(meta)
        snap["complete"] = False
        snap["resume_state"] = {
            "rounds_done": run.rounds_done,
            "labels": list(run.labels),
            "rng": _rng_state(),
            "wall_seconds": round(run.wall_before + time.perf_counter() - start, 1),
        }
        if interrupted is not None:
            snap["interrupted"] = interrupted
        save_resumable(model, snap, path, fit)

    def where() -> str:
        r = run.rounds_done
        if len(run.labels) > r:
            return f"round {r}'s labels collected, {run.epochs_done} of {cfg.epochs} fit epochs"
        return f"{r} of {cfg.rounds} rounds done"

    def stop(name: str) -> BaseException:
        return _stop_exception(
            name,
            f"saved the last completed step ({where()}) as {last} (+ .json); continue with the "
            f"same command and --resume {last}",
        )

    try:
        _rounds(cfg, env_id, collect, out, view, kwargs, model, meta, run, flag, save, stop)
    except (KeyboardInterrupt, Terminated) as exc:  # outside a deferred section: collecting
        if isinstance(exc, TrainingInterrupted | TrainingTerminated) or flag.signal is not None:
            raise  # a stop already saved, or a second signal: abandon at once
        name = "SIGINT" if isinstance(exc, KeyboardInterrupt) else "SIGTERM"
        with flag:
            save(last, name)  # the weights and labels of the last completed step
        raise stop(name) from None
    meta["expert_iteration"]["wall_seconds"] = round(
        run.wall_before + time.perf_counter() - start, 1
    )
    meta["complete"] = True
    with flag:
        save_checkpoint(model, meta, out)
        for stale in [*last_paths(out), fit_state_path(last)]:  # superseded by the result
            stale.unlink(missing_ok=True)
    if flag.signal is not None:
        raise _stop_exception(
            flag.signal,
            f"training had completed: saved {out} (+ .json); its evaluation was skipped",
        )
    if cfg.eval_episodes:
        try:
            bench = evaluate_with_bench(out, cfg, env_id, baseline)
        except (KeyboardInterrupt, Terminated) as exc:
            name = "SIGINT" if isinstance(exc, KeyboardInterrupt) else "SIGTERM"
            raise _stop_exception(
                name, f"during the evaluation: {out} (+ .json) is complete, without metrics"
            ) from None
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
    run: _Progress,
    flag: DeferredSignals,
    save: Callable[..., None],
    stop: Callable[[str], BaseException],
) -> None:
    """The rounds from ``run.rounds_done`` on: collect (abandoned on a signal), then fit.

    The fit and every save run with the signals deferred (``flag``): a signal there ends the
    run after the current epoch, with the ``.last`` state saved (``stop``).
    """
    last = last_paths(out)[0]
    for r in range(run.rounds_done, cfg.rounds):
        t0 = time.perf_counter()
        if len(run.labels) == r:  # collect round r's labels (a signal abandons them)
            extra = {"view": view} if env_id == CL_ID else {}
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
            with flag:
                sha = save_labels(part, labels_path(out, r))
                run.labels.append({"round": r, "states": len(part), "sha256": sha})
                run.parts.append(part)
                run.epochs_done, run.fit = 0, FitState(0, {})
                save(last, flag.signal, run.fit)  # labels collected: a resume fits them
            if flag.signal is not None:
                raise stop(flag.signal)
        data = RankingData.concatenate(run.parts)

        def after_epoch(state: FitState) -> bool:
            run.epochs_done, run.fit = state.epochs_done, state
            every = cfg.checkpoint_every
            if flag.signal is None and every and state.epochs_done % every == 0:
                if state.epochs_done < cfg.epochs:
                    save(last, None, state)
            return flag.signal is not None

        with flag:
            fit = fit_ranking(
                model.policy,
                data,
                epochs=cfg.epochs,
                learning_rate=cfg.learning_rate,
                temperature=cfg.temperature,
                seed=cfg.seed + r,
                progress=cfg.progress,
                start=run.fit,
                after_epoch=after_epoch,
            )
            if fit["epochs_done"] < cfg.epochs:  # stopped by a signal after a completed epoch
                name = flag.signal or "SIGINT"
                save(last, name, run.fit)
                raise stop(name)
            log = {"round": r, "states": len(data), **fit}
            log["seconds"] = round(time.perf_counter() - t0)
            meta["expert_iteration"]["rounds_log"].append(log)
            run.rounds_done, run.fit, run.epochs_done = r + 1, None, 0
            print(json.dumps(log))
            save(round_path(out, r))
            save(last, flag.signal)
        if flag.signal is not None:
            raise stop(flag.signal)


@dataclass
class _Progress:
    """What a run has completed (restored from a ``--resume`` checkpoint)."""

    rounds_done: int = 0
    labels: list[dict[str, Any]] = field(default_factory=list)
    parts: list[RankingData] = field(default_factory=list)
    fit: FitState | None = None
    epochs_done: int = 0
    rounds_log: list[Any] = field(default_factory=list)
    wall_before: float = 0.0


def _restore(
    cfg: Any, meta: dict[str, Any], model: Any, rows: dict[str, tuple[int, ...]], n: int
) -> _Progress:
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
    run = _Progress(rounds_done=done, labels=list(labels))
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
        _set_rng_state(state["rng"])
    except (ValueError, RuntimeError, KeyError, TypeError) as exc:
        raise UsageError(f"--resume {path}: {exc}") from None
    run.epochs_done = run.fit.epochs_done if run.fit is not None else 0
    log = meta["expert_iteration"].get("rounds_log")
    run.rounds_log = list(log[:done]) if isinstance(log, list) else []
    wall = state.get("wall_seconds")
    run.wall_before = float(wall) if isinstance(wall, int | float) else 0.0
    return run


def cli() -> None:
    """Console-script entry point (same options as ``main``).

    Exit code 0 after a run, 2 on a usage error or a busy ``--out``, 1 on an I/O failure,
    130 / 143 after SIGINT / SIGTERM.
    """
    raise SystemExit(run_cli(main, f"python -m {SCRIPT}"))


if __name__ == "__main__":
    cli()
