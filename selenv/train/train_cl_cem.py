"""Train the ``cem`` scorer of ``CLScheduling-v1`` by the cross-entropy method on returns.

The agent (:mod:`selenv.learned.families.cooperative`) scores a pair by greedy's one-step gain, or a
``--horizon``-step lookahead of greedy, plus ``theta . phi`` over 12 pair features; this
script searches ``theta`` with the cross-entropy method (:mod:`selenv.learned.rl.cem`): each
generation plays ``--population`` parameter vectors on the same ``--train-episodes`` training
seeds (``--train-seed``, ``+1``, ...; >= 10**6, disjoint from the bench's) and refits the
sampling distribution to the ``--elite`` best mean returns. The search runs in units of
``--param-scale`` (the weights are ``param_scale * search vector``; the gains are ~1e-3).

    python -m selenv.train.train_cl_cem --out runs/cl_cem.json   # ~20 min on 2 cores (h = 1)

Outputs (refused if they exist, unless ``--force``): the checkpoint ``<out>`` (JSON: the
weights, the features, the lookahead, the env configuration, the command, the search
history), and with ``--eval-episodes`` the bench JSON ``<out stem>.bench.json`` of
``selenv bench`` against greedy, ``rollout`` and ``fast_rollout`` on the held-out seeds
``--eval-seed ..``, whose paired statistics are copied into the checkpoint.

Stopping and resuming: the search state ``<out stem>.last.json`` (the options, the sampling
distribution, the sampler's generator state, the history) is written atomically after every
generation; SIGINT / SIGTERM stop after the generation in progress is abandoned (exit 130 /
143, the last completed generation kept), ``--max-minutes M`` stops after the first
generation that ends past ``M`` minutes (``"interrupted": "max-minutes"`` in the state, exit
75), and ``--resume <out stem>.last.json`` with the same options continues to the same result
as an uninterrupted run. The state file is removed when the run completes. The run
management (lock, stops, exit codes) is the trainer base's (:mod:`selenv.learned.trainer`).
"""

from __future__ import annotations

import multiprocessing
import shlex
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from selenv.atomic import write_json
from selenv.exits import Terminated, UsageError, check_size
from selenv.learned.config import arg, check_outputs, parse_config, usage_error
from selenv.learned.resources import read_metadata
from selenv.learned.rl.cem import CEMSettings, cem_generation, new_state, state_from_json
from selenv.learned.trainer import (
    BUDGET,
    RESUME_FREE,
    RunStop,
    check_run_options,
    output_lock,
    run_arg,
    run_cli,
    stop_exception,
)
from selenv.parallel.executors import max_pool_workers
from selenv.untrusted import json_object

SCRIPT = "selenv.train.train_cl_cem"
ENV_ID = "selenv/CLScheduling-v1"
#: generations and episodes above these need --allow-large
CEILINGS = {
    "generations": 1000,
    "population": 1000,
    "train_episodes": 10_000,
    "eval_episodes": 100_000,
}


@dataclass
class Config:
    """Every field is a ``--kebab-case`` option."""

    out: str = arg("runs/train_cl_cem/scorer.json", "the trained checkpoint (.json)")
    force: bool = run_arg("force", False)
    env_kwargs: str = arg(
        "{}", "JSON object of gymnasium.make keyword arguments ({}: the benchmark preset)"
    )
    horizon: int = arg(1, "lookahead filter steps of greedy behind each score (0: one-step gain)")
    top_k: int = arg(3, "pairs scored besides stop when --horizon >= 1")
    generations: int = arg(
        12,
        "cross-entropy generations (the shipped cl_scheduling_cem.json: these defaults, 6,912 "
        "episodes, 11 min on 2 cores)",
    )
    population: int = arg(24, "parameter vectors per generation (the first is the mean)")
    elite: int = arg(6, "best vectors the next distribution is fitted to")
    init_std: float = arg(2.0, "initial standard deviation of every search coordinate")
    min_std: float = arg(0.05, "floor added to the refitted standard deviations")
    param_scale: float = arg(1e-3, "weights = param_scale * search vector")
    train_episodes: int = arg(24, "training episodes per evaluation (the same seeds for all)")
    train_seed: int = arg(5_000_000, "seed of the first training episode (>= 10**6)")
    seed: int = arg(0, "seed of the sampler")
    workers: int = arg(2, "evaluation processes")
    eval_episodes: int = run_arg("eval_episodes", 30, note="by selenv bench")
    eval_seed: int = run_arg("eval_seed", 1000)
    progress: bool = arg(True, "print one line per generation")
    allow_large: bool = arg(
        False, "lift the ceilings of the sizes (selenv.train.train_cl_cem.CEILINGS)"
    )
    resume: str = run_arg(
        "resume", "", unit="<out stem>.last.json", note="the search state after a generation"
    )
    max_minutes: float | None = run_arg("max_minutes", None, unit="a generation")


#: options that may differ between an interrupted run and its resumption
_FREE = (*RESUME_FREE, "workers")


def state_path(out: str | Path) -> Path:
    """The search state of ``--out``: ``<out stem>.last.json``."""
    path = Path(out)
    return path.with_name(f"{path.stem}.last.json")


def bench_path(out: str | Path) -> Path:
    """The held-out bench JSON of ``--out``: ``<out stem>.bench.json``."""
    path = Path(out)
    return path.with_name(f"{path.stem}.bench.json")


def parse_args(argv: list[str] | None = None) -> Config:
    """The run's :class:`Config` from the command line (and ``--config FILE``)."""
    return parse_config(Config, argv, (__doc__ or "").split("\n")[0], script=SCRIPT)


def outputs(cfg: Config) -> list[Path]:
    """The files the run writes: the checkpoint and, with ``--eval-episodes``, its bench JSON."""
    return [Path(cfg.out)] + ([bench_path(cfg.out)] if cfg.eval_episodes else [])


def _check(cfg: Config, prog: str) -> dict[str, Any]:
    """Validate the options before any work (exit 2, one line); the env keyword arguments."""
    if Path(cfg.out).suffix != ".json":
        usage_error(prog, f"--out must end in .json, got {cfg.out!r}")
    check_run_options(cfg, prog)
    for name, low in (
        ("generations", 1),
        ("population", 2),
        ("elite", 1),
        ("train_episodes", 1),
        ("workers", 1),
        ("eval_episodes", 0),
        ("top_k", 1),
        ("horizon", 0),
    ):
        value = getattr(cfg, name)
        if value < low:
            usage_error(prog, f"--{name.replace('_', '-')} must be >= {low}, got {value}")
        if name in CEILINGS and value > CEILINGS[name] and not cfg.allow_large:
            usage_error(
                prog,
                f"--{name.replace('_', '-')} {value} exceeds {CEILINGS[name]} (pass --allow-large)",
            )
    try:  # the pool's ceiling, before any process starts
        check_size("--workers", cfg.workers, low=1, high=max_pool_workers(),
                   note=" (evaluation processes on this machine)")  # fmt: skip
    except UsageError as exc:
        usage_error(prog, exc)
    if cfg.elite > cfg.population:
        usage_error(prog, f"--elite must be <= --population ({cfg.population}), got {cfg.elite}")
    if cfg.horizon > 5:
        usage_error(prog, f"--horizon must be <= 5 (the reference's lookahead), got {cfg.horizon}")
    if cfg.train_seed < 10**6:
        usage_error(
            prog, f"--train-seed must be >= 10**6 (bench seeds are below), got {cfg.train_seed}"
        )
    for name in ("init_std", "param_scale"):
        if not (np.isfinite(getattr(cfg, name)) and getattr(cfg, name) > 0):
            usage_error(prog, f"--{name.replace('_', '-')} must be a number > 0")
    if not (np.isfinite(cfg.min_std) and cfg.min_std >= 0):
        usage_error(prog, "--min-std must be a number >= 0")
    try:  # size and nesting bounded before parsing
        kwargs = json_object(cfg.env_kwargs, "--env-kwargs")
    except ValueError as exc:
        usage_error(prog, exc)
    final = outputs(cfg)
    if cfg.resume:
        if not Path(cfg.resume).is_file():
            usage_error(prog, f"--resume {cfg.resume}: no such file")
        check_outputs(prog, final, force=cfg.force)
    else:
        last = state_path(cfg.out)
        if last.exists() and not cfg.force:
            usage_error(
                prog,
                f"{last} exists (an unfinished run of this --out): continue it with "
                f"--resume {last}, or pass --force to start over",
            )
        check_outputs(prog, [*final, last], force=cfg.force)
    return kwargs


# -- evaluation in worker processes ----------------------------------------------------------
_WORKER: dict[str, Any] = {}


def _init_worker(
    env_kwargs: dict[str, Any], horizon: int, top_k: int, seeds: list[int], scale: float
) -> None:
    """Each process: one BLAS thread, its own env, the training seeds."""
    from selenv.threads import set_blas_threads

    set_blas_threads(1)
    import gymnasium as gym

    import selenv  # noqa: F401  (registers the envs)

    _WORKER.update(
        env=gym.make(ENV_ID, **env_kwargs), horizon=horizon, top_k=top_k, seeds=seeds, scale=scale
    )


def episode_return(agent: Any, env: Any, seed: int) -> float:
    """The return of one episode of ``agent`` on ``env`` reset with ``seed`` (the bench's loop)."""
    from selenv.bench.results import AgentResult
    from selenv.bench.runner import run_episode

    return run_episode(env, agent, seed, AgentResult(agent.name))[0]


def _evaluate(vector: np.ndarray) -> float:
    """Mean return over the training seeds of the agent with ``theta = scale * vector``."""
    from selenv.learned.families.cooperative import CLLearnedScorerAgent

    w = _WORKER
    agent = CLLearnedScorerAgent(w["scale"] * np.asarray(vector), w["horizon"], w["top_k"])
    return float(np.mean([episode_return(agent, w["env"], s) for s in w["seeds"]]))


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Search, save, evaluate; return the checkpoint's contents (one run per ``--out``)."""
    cfg = parse_args(argv)
    prog = f"python -m {SCRIPT}"
    _check(cfg, prog)
    with output_lock(cfg.out, prog):
        return _run(cfg, argv)


def _run(cfg: Config, argv: list[str] | None) -> dict[str, Any]:
    """The search of :func:`main` with its options checked."""
    import gymnasium as gym

    import selenv  # noqa: F401
    from selenv.families.cooperative.features import FEATURE_NAMES
    from selenv.learned.families.cooperative import CHECKPOINT_FORMAT, env_config

    kwargs = _check(cfg, f"python -m {SCRIPT}")
    out = Path(cfg.out)
    options = {k: v for k, v in asdict(cfg).items() if k not in _FREE}
    settings = CEMSettings(cfg.population, cfg.elite, cfg.init_std, cfg.min_std)
    dim = len(FEATURE_NAMES)
    if cfg.resume:
        try:
            saved = read_metadata(cfg.resume, "CEM state")
        except (OSError, ValueError) as exc:
            raise UsageError(f"--resume {cfg.resume}: {exc}") from None
        if not isinstance(saved, dict) or saved.get("options") != options:
            theirs = saved.get("options", {}) if isinstance(saved, dict) else {}
            diff = sorted(k for k in options if theirs.get(k) != options[k])
            raise UsageError(f"--resume {cfg.resume}: other options than this run's ({diff})")
        state = state_from_json(saved.get("state"), dim)
    else:
        state = new_state(dim, settings, cfg.seed)
    base = gym.make(ENV_ID, **kwargs).unwrapped
    trained_on = env_config(base)
    if trained_on["model"] != "ins":
        raise UsageError(
            f"--env-kwargs: the scorer's features need model 'ins', got {trained_on['model']!r}"
        )
    seeds = list(range(cfg.train_seed, cfg.train_seed + cfg.train_episodes))
    init = (kwargs, cfg.horizon, cfg.top_k, seeds, cfg.param_scale)
    last = state_path(out)
    started = time.perf_counter()
    budget = RunStop(cfg.max_minutes)  # signals raise here (a generation is abandoned)
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(cfg.workers, initializer=_init_worker, initargs=init) as pool:
        while state.generation < cfg.generations:
            t0 = time.perf_counter()
            try:
                state = cem_generation(state, settings, _evaluate, pool.map)
            except (KeyboardInterrupt, Terminated) as exc:
                pool.terminate()
                kept = (
                    f"{last} keeps generation {state.generation}"
                    if last.exists()
                    else "no generation was completed"
                )
                signal = "SIGINT" if isinstance(exc, KeyboardInterrupt) else "SIGTERM"
                raise stop_exception(
                    signal, f"{kept}; continue with --resume {last} and the same options"
                ) from None
            saved = {"script": SCRIPT, "options": options, "state": state.to_json()}
            spent = state.generation < cfg.generations and budget.check_budget()
            if spent:
                saved["interrupted"] = BUDGET
            write_json(last, saved)
            if cfg.progress:
                rec = state.history[-1]
                print(
                    f"generation {rec['generation'] + 1}/{cfg.generations}: mean "
                    f"{rec['mean_value']:.5f}, best {rec['best_value']:.5f}, elite "
                    f"{rec['elite_value']:.5f} ({time.perf_counter() - t0:.0f} s)",
                    file=sys.stderr,
                    flush=True,
                )
            if spent:
                pool.terminate()
                raise stop_exception(
                    BUDGET,
                    f"{last} keeps generation {state.generation}; continue with --resume {last} "
                    "and the same options",
                )
        final_value = float(pool.map(_evaluate, [np.asarray(state.mean)])[0])
    theta = (cfg.param_scale * np.asarray(state.mean)).tolist()
    command = f"python -m {SCRIPT} " + shlex.join(sys.argv[1:] if argv is None else argv)
    data: dict[str, Any] = {
        "format": CHECKPOINT_FORMAT,
        "env_id": ENV_ID,
        "env_kwargs": kwargs,
        "env_config": trained_on,
        "features": list(FEATURE_NAMES),
        "theta": theta,
        "lookahead": {"horizon": cfg.horizon, "top_k": cfg.top_k},
        "training": {
            "command": command.strip(),
            "options": options,
            "method": "cross-entropy method on mean episode return (common random numbers)",
            "train_seeds": [seeds[0], seeds[-1]],
            "generations": state.generation,
            "episodes_played": state.generation * cfg.population * cfg.train_episodes,
            "wall_time_s": round(time.perf_counter() - started, 1),
            "final_mean_train_return": final_value,
            "history": state.history,
        },
    }
    write_json(out, data)
    last.unlink(missing_ok=True)
    if cfg.eval_episodes:
        from selenv.learned.rl.distill import evaluate_with_bench

        agents = f"greedy,rollout,fast_rollout,cem:checkpoint={out}"
        bench = evaluate_with_bench(out, cfg, ENV_ID, "greedy", agents)
        agents = bench["results"][0]["agents"]
        data["held_out_bench"] = {
            "command": bench["command"],
            "file": bench_path(out).name,
            "agents": {
                name: {
                    "mean_return": a["mean_return"],
                    "paired_vs_greedy": a.get("paired"),
                    "decision_ms": 1e3 * a["decision_seconds_mean"],
                }
                for name, a in agents.items()
            },
        }
        write_json(out, data)
    return data


if __name__ == "__main__":
    sys.exit(run_cli(main, f"python -m {SCRIPT}"))
