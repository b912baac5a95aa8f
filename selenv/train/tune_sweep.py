r"""Ray Tune sweeps over the RL training scripts: seeds x hyper-parameters, a table with CIs.

Every trial is one run of a ``train/*_ppo.py`` script (its ``main(argv)``: its ``Config``,
envs and :func:`selenv.learned.rl.training.train`) with one hyper-parameter configuration and one
training seed, on one CPU (``torch`` and BLAS with one thread). Its checkpoint goes to
``<out>/trials/<trial id>/policy.zip`` (never ``checkpoints/``) and is evaluated, reloaded
through the ``ppo`` agent, on the held-out seeds ``eval_seed, eval_seed + 1, ...`` next to the
baseline agent on the same seeds. Training seed ``s`` seeds the ``n_envs`` training envs with
``s, ..., s + n_envs - 1`` (``VecEnv.seed``); the eval seeds must lie above all of them.

The grid is the Cartesian product of the ``--grid`` values and ``--seeds`` (``tune.grid_search``),
repeated ``--num-samples`` times; at most ``--num-workers`` trials run at once. The table has
one row per configuration (:mod:`selenv.train.tune_results`): mean held-out return over the seeds
with
its 95 % CI (percentile bootstrap of :mod:`selenv.bench.stats`, and the t-interval), min / max,
and the paired difference policy - baseline on the same eval seeds with its CI and wins / ties /
losses. Ray is started (or joined, ``--address``) and stopped by
:func:`selenv.parallel.ray_session`.

    python -m selenv.train.tune_sweep --script fim_ppo --seeds 0,1,2 --grid learning_rate=1e-4,3e-4
    \
        --timesteps 20000 --eval-episodes 30 --out runs/tune_fim_ppo

Writes ``<out>/results.md``, ``<out>/results.json`` (provenance, every trial's returns, the rows;
each replaced atomically, after the table is printed: a failed write is one line and exit 1)
and Tune's experiment state under ``<out>/tune``. ``--address HOST:PORT`` runs the trials on a
Ray cluster whose nodes see this checkout and ``--out`` (a shared file system).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import math
import os
import shutil
import sys
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from selenv.atomic import describe_os_error, write_json, write_text
from selenv.train.tune_results import format_table, summarize

SCRIPTS = {
    "fim_ppo": "selenv.train.train_fim_ppo",
    "landmark_ppo": "selenv.train.train_landmark_ppo",
    "clustering_ppo": "selenv.train.train_clustering_ppo",
    "cl_ppo": "selenv.train.train_cl_ppo",
}
#: Config fields the sweep sets itself (not --grid / --set keys) -> the option that does
MANAGED = {
    "seed": "--seeds",
    "total_timesteps": "--timesteps",
    "eval_episodes": "--eval-episodes",
    "eval_seed": "--eval-seed",
    "baselines": "--baseline",
    "out": "--out",
    "tensorboard_dir": "the sweep (no TensorBoard)",
    "progress": "the sweep (no bars)",
    "torch_threads": "the sweep (1 per trial)",
}
#: one CPU per trial: the native vector env in the trial's process, no extra evaluation variants
#: (--set undoes)
SWEEP_DEFAULTS: dict[str, Any] = {"vec_env": "native", "rank_workers": 1, "verify_top_k": ""}
POSITIVE = {"n_envs", "n_steps", "batch_size", "n_epochs", "learning_rate", "gamma"}


class UsageError(ValueError):
    """A bad option, reported as one line and exit code 2 before Ray starts."""


# -- the trial ---------------------------------------------------------------------------------
def _argv(fields: dict[str, Any]) -> list[str]:
    """Config fields as the script's ``--kebab-case`` command line."""
    out = []
    for name, value in fields.items():
        flag = name.replace("_", "-")
        if isinstance(value, bool):
            out.append(f"--{flag}" if value else f"--no-{flag}")
        else:
            out.append(f"--{flag}={value}")
    return out


def run_trial(config: dict[str, Any]) -> None:
    """Tune function trainable: train one configuration and seed, report held-out returns."""
    import torch
    from ray import tune

    torch.set_num_threads(1)
    trial_dir = Path(config["trials_dir"]) / tune.get_context().get_trial_id()
    fields = {**config["fixed"], **config["params"], "seed": config["seed"]}
    fields["out"] = str(trial_dir / "policy.zip")
    meta = importlib.import_module(SCRIPTS[config["script"]]).main(_argv(fields))
    agents = meta["metrics"]["agents"]
    returns = agents["ppo"]["returns"]
    base = config["baseline"]
    tune.report(
        {
            "mean_return": float(np.mean(returns)),
            "returns": returns,
            "baseline_returns": agents[base]["returns"] if base else None,
            "checkpoint": fields["out"],
            "train_seconds": meta["training"]["wall_seconds"],
            "timesteps_done": meta["training"]["timesteps_done"],
        }
    )


def _trial_dirname(trial: Any) -> str:
    return f"trial_{trial.trial_id}"


def _progress(total: int) -> Any:
    """A Tune callback with a tqdm bar over the trials (Tune's own reporter is silenced)."""
    from ray import tune
    from tqdm.auto import tqdm

    class TrialBar(tune.Callback):
        def setup(
            self,
            stop: Any = None,
            num_samples: int | None = None,
            total_num_samples: int | None = None,
            **info: Any,
        ) -> None:
            self.bar = tqdm(total=total, unit="trial", desc="sweep")

        def on_trial_complete(self, iteration: int, trials: Any, trial: Any, **info: Any) -> None:
            self.bar.update(1)
            self.bar.set_postfix(last=f"{trial.last_result.get('mean_return', float('nan')):.4g}")

        def on_trial_error(self, iteration: int, trials: Any, trial: Any, **info: Any) -> None:
            self.bar.update(1)
            self.bar.write(f"trial {trial.trial_id} failed: see {trial.path}")

        def on_experiment_end(self, trials: Any, **info: Any) -> None:
            self.bar.close()

    return TrialBar()


# -- options -----------------------------------------------------------------------------------
def _parse(cls: type, key: str, text: str, option: str) -> Any:
    """``text`` as the value of Config field ``key`` (checked), or :class:`UsageError`."""
    typ = str({f.name: f.type for f in dataclasses.fields(cls)}[key])
    try:
        if typ == "bool":
            if text.lower() not in ("true", "false", "1", "0"):
                raise ValueError("expected true or false")
            value: Any = text.lower() in ("true", "1")
        else:
            value = {"int": int, "float": float, "str": str}[typ](text)
        if key in POSITIVE and not value > 0:
            raise ValueError("expected a value > 0")
        if key == "env_kwargs" and not isinstance(json.loads(text), dict):
            raise ValueError("expected a JSON object")
        if key == "hidden" and not all(int(h) > 0 for h in text.split(",")):
            raise ValueError("expected comma-separated layer widths > 0")
        if key == "vec_env" and text not in ("native", "dummy", "subproc"):
            raise ValueError("expected native, dummy or subproc")
        if key == "activation" and text not in ("tanh", "relu"):
            raise ValueError("expected tanh or relu")
        if key == "algo":
            from selenv.learned.rl.candidate_policy import ALGORITHMS

            if text not in ALGORITHMS:
                raise ValueError(f"expected one of {sorted(ALGORITHMS)}")
    except ValueError as exc:  # json.JSONDecodeError is a ValueError
        raise UsageError(f"{option} {key}={text!r}: not a valid {typ} ({exc})") from None
    return value


def _key_values(cls: type, spec: str, option: str, multi: bool) -> tuple[str, list[Any]]:
    valid = [f.name for f in dataclasses.fields(cls) if f.name not in MANAGED]
    key, eq, text = spec.partition("=")
    key = key.strip().replace("-", "_")
    if not eq or not text:
        raise UsageError(f"{option} {spec!r}: expected KEY=VALUE{'S' if multi else ''}")
    if key in MANAGED:
        raise UsageError(f"{option} {key}: set by {MANAGED[key]}; valid keys: {', '.join(valid)}")
    if key not in valid:
        raise UsageError(f"{option} {key}: unknown key; valid keys: {', '.join(valid)}")
    texts = [text] if not multi else text.split(";" if ";" in text else ",")
    return key, [_parse(cls, key, t.strip(), option) for t in texts]


def _ints(text: str, option: str) -> list[int]:
    try:
        values = [int(t) for t in text.split(",")]
    except ValueError:
        raise UsageError(f"{option} {text!r}: expected comma-separated integers") from None
    if not values or min(values) < 0 or len(set(values)) != len(values):
        raise UsageError(f"{option} {text!r}: expected distinct integers >= 0")
    return values


class _Parser(argparse.ArgumentParser):
    """Usage errors as one line on stderr (no usage block), exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    """The command line (every option with its meaning and default)."""
    p = _Parser(
        prog="python -m selenv.train.tune_sweep",
        description=(__doc__ or "").split("\n")[0],
    )
    p.add_argument(
        "--script",
        required=True,
        choices=list(SCRIPTS),
        help="training script, the module selenv/train/train_<SCRIPT>.py (required)",
    )
    p.add_argument(
        "--seeds",
        default="0,1,2",
        help="comma-separated training seeds, a grid axis (default: 0,1,2)",
    )
    p.add_argument(
        "--grid",
        action="append",
        default=[],
        metavar="KEY=V1,V2",
        help="a grid axis over a Config field of the script (PPOConfig's and the script's "
        "own); separate values by ';' when they contain commas (hidden=64,64;128,128); "
        "repeatable (default: none, the script's defaults)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a fixed Config field for every trial (no splitting); repeatable; sweep "
        f"defaults where the field exists: {SWEEP_DEFAULTS}",
    )
    p.add_argument("--env-kwargs", help="JSON env kwargs (default: the script's)")
    p.add_argument("--timesteps", type=int, help="PPO timesteps per trial (default: the script's)")
    p.add_argument(
        "--eval-episodes", type=int, default=30, help="held-out episodes per trial (default: 30)"
    )
    p.add_argument(
        "--eval-seed",
        type=int,
        default=1000,
        help="first held-out episode seed; must exceed every "
        "training env seed, seed + env index (default: 1000)",
    )
    p.add_argument(
        "--baseline",
        default="greedy",
        help="agent paired with the policy on the eval seeds "
        "(the heuristic every script compares with; 'none': no paired columns) (default: greedy)",
    )
    p.add_argument(
        "--num-samples",
        type=int,
        default=1,
        help="repeats of the whole grid, same seeds "
        "again: measures run-to-run nondeterminism only (default: 1)",
    )
    p.add_argument("--num-workers", type=int, help="trials at once (default: Ray's CPUs)")
    p.add_argument("--address", help="Ray cluster HOST:PORT / auto (default: local Ray)")
    p.add_argument("--out", help="output folder (default: runs/tune_<script>)")
    p.add_argument(
        "--force",
        action="store_true",
        help="reuse a non-empty --out: its tune/, trials/ and "
        "results.* are deleted first (default: off)",
    )
    return p


def plan(args: argparse.Namespace) -> dict[str, Any]:
    """Check every option (:class:`UsageError`) and return the sweep's description."""
    module = importlib.import_module(SCRIPTS[args.script])
    cls = module.Config
    seeds = _ints(args.seeds, "--seeds")
    fixed: dict[str, Any] = {
        k: v for k, v in SWEEP_DEFAULTS.items() if k in {f.name for f in dataclasses.fields(cls)}
    }
    for spec in args.set:
        key, (value,) = _key_values(cls, spec, "--set", multi=False)
        fixed[key] = value
    if args.env_kwargs is not None:
        fixed["env_kwargs"] = _parse(cls, "env_kwargs", args.env_kwargs, "--env-kwargs")
    grid: dict[str, list[Any]] = {}
    for spec in args.grid:
        key, values = _key_values(cls, spec, "--grid", multi=True)
        grid[key] = list(dict.fromkeys(values))
    timesteps = cls.total_timesteps if args.timesteps is None else args.timesteps
    checks = [
        (timesteps >= 0, f"--timesteps {timesteps}: expected >= 0"),
        (args.eval_episodes >= 1, f"--eval-episodes {args.eval_episodes}: expected >= 1"),
        (args.num_samples >= 1, f"--num-samples {args.num_samples}: expected >= 1"),
        (args.num_workers is None or args.num_workers >= 1, "--num-workers: expected >= 1"),
    ]
    for ok, msg in checks:
        if not ok:
            raise UsageError(msg)
    n_envs = max(grid.get("n_envs", [fixed.get("n_envs", cls.n_envs)]))
    last_train = max(seeds) + n_envs - 1
    if args.eval_seed <= last_train:
        raise UsageError(
            f"--eval-seed {args.eval_seed}: held-out seeds must exceed the training env seeds "
            f"(seed + env index, up to {last_train})"
        )
    baseline = "" if args.baseline == "none" else args.baseline
    from selenv.agents import agents_for

    if baseline == "ppo":  # the trial's policy is evaluated under that name
        raise UsageError("--baseline ppo: the swept policy itself; choose a heuristic")
    if baseline and baseline not in agents_for(module.ENV_ID):
        raise UsageError(
            f"--baseline {baseline!r}: not an agent of {module.ENV_ID}; "
            f"choose from none, {', '.join(agents_for(module.ENV_ID))}"
        )
    if args.address is not None:
        from selenv.parallel import check_address

        check_address(args.address)  # ExecutorError (exit 2) before anything is written
    fixed.update(
        total_timesteps=timesteps,
        eval_episodes=args.eval_episodes,
        eval_seed=args.eval_seed,
        baselines=baseline,
        tensorboard_dir="",
        progress=False,
        torch_threads=1,
    )
    out = Path(args.out or f"runs/tune_{args.script}").resolve()
    if out.exists() and any(out.iterdir()) and not args.force:
        raise UsageError(f"--out {out}: exists and is not empty; pass --force to reuse it")
    return {
        "script": args.script,
        "env_id": module.ENV_ID,
        "seeds": seeds,
        "grid": grid,
        "fixed": fixed,
        "baseline": baseline,
        "eval_seeds": [args.eval_seed + e for e in range(args.eval_episodes)],
        "num_samples": args.num_samples,
        "out": out,
    }


# -- driver ------------------------------------------------------------------------------------
def run(sweep: dict[str, Any], args: argparse.Namespace) -> list[dict[str, Any]]:
    """Start or join Ray, run the grid with Tune, return one record per trial."""
    from ray import tune
    from ray.tune.logger import CSVLoggerCallback, JsonLoggerCallback

    from selenv.parallel import ray_session

    out: Path = sweep["out"]
    n_trials = (
        len(sweep["seeds"]) * sweep["num_samples"] * math.prod(map(len, sweep["grid"].values()))
    )
    space = {
        "script": sweep["script"],
        "fixed": sweep["fixed"],
        "baseline": sweep["baseline"],
        "trials_dir": str(out / "trials"),
        "seed": tune.grid_search(sweep["seeds"]),
        "params": {k: tune.grid_search(v) for k, v in sweep["grid"].items()},
    }
    previous = os.environ.get("TUNE_DISABLE_AUTO_CALLBACK_LOGGERS")
    os.environ["TUNE_DISABLE_AUTO_CALLBACK_LOGGERS"] = "1"  # no TensorBoard event files
    try:
        with ray_session(address=args.address) as ray:
            workers = args.num_workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
            tuner = tune.Tuner(
                tune.with_resources(run_trial, {"cpu": 1}),
                param_space=space,
                tune_config=tune.TuneConfig(
                    num_samples=sweep["num_samples"],
                    max_concurrent_trials=workers,
                    trial_dirname_creator=_trial_dirname,
                ),
                run_config=tune.RunConfig(
                    name="sweep",
                    storage_path=str(out / "tune"),
                    verbose=0,
                    callbacks=[JsonLoggerCallback(), CSVLoggerCallback(), _progress(n_trials)],
                ),
            )
            grid = tuner.fit()
    finally:
        if previous is None:
            os.environ.pop("TUNE_DISABLE_AUTO_CALLBACK_LOGGERS", None)
        else:
            os.environ["TUNE_DISABLE_AUTO_CALLBACK_LOGGERS"] = previous
    sweep["num_workers"] = workers
    trials = []
    for result in (grid[i] for i in range(len(grid))):  # ResultGrid: indexable, not typed iterable
        m, cfg = result.metrics or {}, result.config or {}
        trials.append(
            {
                "trial_id": m.get("trial_id"),
                "params": {k: cfg["params"][k] for k in sweep["grid"]},
                "seed": cfg["seed"],
                "error": None if result.error is None else repr(result.error)[:500],
                **{k: m.get(k) for k in ("checkpoint", "mean_return", "returns")},
                **{k: m.get(k) for k in ("baseline_returns", "train_seconds", "timesteps_done")},
            }
        )
    return sorted(trials, key=lambda t: (json.dumps(t["params"], sort_keys=True), t["seed"]))


def main(argv: list[str] | None = None) -> int:
    """Run the sweep, print and write the table; the exit code (2: usage error)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or an argparse error (2, message already printed)
        return int(exc.code or 0)
    from selenv.parallel import ExecutorError

    try:
        sweep = plan(args)
        out: Path = sweep["out"]
        for stale in ("tune", "trials", "results.md", "results.json"):  # only with --force
            path = out / stale
            shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
        out.mkdir(parents=True, exist_ok=True)
        trials = run(sweep, args)
    except (UsageError, ExecutorError) as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    from selenv.bench.provenance import provenance

    rows = summarize(sweep, trials)
    failed = [t for t in trials if t["error"] is not None]
    table = format_table(sweep, rows, len(failed))
    report = {
        "provenance": provenance(argv if argv is not None else sys.argv),
        **{k: v for k, v in sweep.items() if k != "out"},
        "out": str(out),
        "ci_method": "percentile bootstrap over trials (selenv.bench.stats.bootstrap_ci); "
        "ci95_t: Student t-interval",
        "configs": rows,
        "best": rows[0] if rows else None,
        "trials": trials,
    }
    print(table, end="")
    try:  # atomic: a failed write leaves no half-written table
        write_json(out / "results.json", report)
        write_text(out / "results.md", table)
    except OSError as exc:
        print(
            f"{parser.prog}: {describe_os_error(exc)} (the table is printed above)", file=sys.stderr
        )
        return 1
    return 1 if failed or not rows else 0


if __name__ == "__main__":
    raise SystemExit(main())
