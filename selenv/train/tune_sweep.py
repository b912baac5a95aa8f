r"""Ray Tune sweeps over the RL training scripts: seeds x hyper-parameters, a table with CIs.

Every trial is one run of a ``train/*_ppo.py`` script (its ``main(argv)``: its ``Config``,
envs and :func:`selenv.learned.rl.training.train`) with one hyper-parameter configuration and one
training seed, on one CPU (``torch`` and BLAS with one thread). Its checkpoint goes to
``<out>/trials/<trial key>/policy.zip`` (never ``checkpoints/``) and is evaluated, reloaded
through the ``ppo`` agent, on the held-out seeds ``eval_seed, eval_seed + 1, ...`` next to the
baseline agent on the same seeds. Training seed ``s`` seeds the ``n_envs`` training envs with
``s, ..., s + n_envs - 1`` (``VecEnv.seed``); the eval seeds must lie above all of them. A
finished trial writes its record ``<out>/trials/<trial key>/result.json`` (atomically).

The trials are the Cartesian product of the ``--grid`` values and ``--seeds``, repeated
``--num-samples`` times; at most ``--num-workers`` trials run at once. The table has
one row per configuration (:mod:`selenv.train.tune_results`): mean held-out return over the seeds
with its 95 % CI (percentile bootstrap of :mod:`selenv.bench.stats`, and the t-interval),
min / max, and the paired difference policy - baseline on the same eval seeds with its CI and
wins / ties / losses. Ray is started (or joined, ``--address``) and stopped by
:func:`selenv.parallel.ray_session`.

    python -m selenv.train.tune_sweep --script fim_ppo --seeds 0,1,2 --grid learning_rate=1e-4,3e-4
    \
        --timesteps 20000 --eval-episodes 30 --out runs/tune_fim_ppo

Writes ``<out>/sweep.json`` (the trials' options, first), ``<out>/results.md`` and
``<out>/results.json`` (provenance, every trial's returns, the rows; replaced together
atomically after the table is printed: a failed write is one line and exit 1) and Tune's
experiment state under ``<out>/tune``. ``--address HOST:PORT`` runs the trials on a Ray cluster
whose nodes see this checkout and ``--out`` (a shared file system).

Sizes are bounded before anything starts (exit 2, one line naming the option and the ceiling):
per trial the training scripts' ceilings (:data:`selenv.learned.rl.training.LIMITS`:
``--timesteps``, ``--eval-episodes``, ``n_envs``, ``n_steps``, ...), and the sweep's own: at most
:data:`MAX_TRIALS` trials (seeds x configurations x ``--num-samples``), at most
:data:`MAX_SWEEP_TIMESTEPS` timesteps over all trials, ``--num-workers`` at most this
machine's CPUs (:data:`MAX_CLUSTER_WORKERS` with ``--address``). ``--allow-large`` lifts them.

SIGINT / SIGTERM stop the sweep: running trials are stopped through Tune's stopper, Ray is shut
down, the completed trials' results are written (``results.json`` / ``results.md`` marked
incomplete) and the command exits 130 / 143 with one line saying how many trials completed and
where. ``--resume`` with the same options and ``--out`` runs only the trials without a record
(the records of the completed ones are read back, never Tune's pickled experiment state); a
second signal stops at once (the trial records on disk stay).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import itertools
import json
import math
import os
import shutil
import signal
import sys
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from selenv.atomic import OutputLock, atomic_paths, describe_os_error, write_json
from selenv.exits import DeferredSignals, Terminated, UsageError, guarded_main
from selenv.train.tune_results import format_table, summarize
from selenv.untrusted import json_object

__all__ = [
    "MAX_CLUSTER_WORKERS",
    "MAX_SWEEP_TIMESTEPS",
    "MAX_TRIALS",
    "UsageError",
    "build_parser",
    "main",
    "plan",
    "run_trial",
    "trial_specs",
]

PROG = "python -m selenv.train.tune_sweep"
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
    "force": "the sweep (a trial without a record starts over)",
    "resume": "the sweep (--resume reruns a trial without a record from the start)",
    "allow_large": "--allow-large",
    "tensorboard_dir": "the sweep (no TensorBoard)",
    "progress": "the sweep (no bars)",
    "torch_threads": "the sweep (1 per trial)",
}
#: one CPU per trial: the native vector env in the trial's process, no extra evaluation variants
#: (--set undoes)
SWEEP_DEFAULTS: dict[str, Any] = {"vec_env": "native", "rank_workers": 1, "verify_top_k": ""}
POSITIVE = {"n_envs", "n_steps", "batch_size", "n_epochs", "learning_rate", "gamma"}

#: ceiling of the number of trials (seeds x configurations x --num-samples); --allow-large lifts
MAX_TRIALS = 1000
#: ceiling of the PPO timesteps over all trials (trials x --timesteps); --allow-large lifts
MAX_SWEEP_TIMESTEPS = 10**10
#: ceiling of --num-workers with --address (a cluster's CPUs are not known before it is joined)
MAX_CLUSTER_WORKERS = 1024
#: the sweep's description, written first: what --resume compares its options with
SWEEP_FILE = "sweep.json"
#: a finished trial's record, in its folder under <out>/trials
RECORD_FILE = "result.json"
#: what the sweep writes into --out (deleted first by --force)
OUTPUTS = ("tune", "trials", "results.md", "results.json", SWEEP_FILE)
#: what must agree between a stopped sweep and the --resume options (-> the option to name)
RESUME_KEYS = {
    "script": "--script",
    "env_id": "--script",
    "seeds": "--seeds",
    "grid": "--grid",
    "num_samples": "--num-samples",
    "baseline": "--baseline",
    "eval_seeds": "--eval-seed / --eval-episodes",
}
EXIT_CODES = {"SIGINT": 130, "SIGTERM": 143}


# -- the trials --------------------------------------------------------------------------------
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


def trial_specs(sweep: dict[str, Any]) -> list[dict[str, Any]]:
    """Every trial of the sweep, in a fixed order: ``key``, ``params``, ``seed``, ``sample``.

    The key (``0003_seed1``: the position, then the seed) names the trial's folder and record;
    the same options give the same keys, which is what ``--resume`` relies on.
    """
    names = list(sweep["grid"])
    specs: list[dict[str, Any]] = []
    for sample in range(sweep["num_samples"]):
        for combo in itertools.product(*(sweep["grid"][k] for k in names)):
            for seed in sweep["seeds"]:
                specs.append(
                    {
                        "key": f"{len(specs):04d}_seed{seed}",
                        "params": dict(zip(names, combo, strict=True)),
                        "seed": seed,
                        "sample": sample,
                    }
                )
    return specs


def run_trial(config: dict[str, Any]) -> None:
    """Tune function trainable: train one trial, write its record, report the mean return.

    A folder left by an unfinished earlier attempt of the trial (no record) is removed first:
    the trial starts over. The record goes to ``<trials_dir>/<key>/result.json`` atomically,
    after the checkpoint and its evaluation are complete.
    """
    import torch
    from ray import tune

    torch.set_num_threads(1)
    spec = config["trial"]
    trial_dir = Path(config["trials_dir"]) / spec["key"]
    if trial_dir.exists():  # an interrupted attempt: only trials without a record are run
        shutil.rmtree(trial_dir)
    fields = {**config["fixed"], **spec["params"], "seed": spec["seed"]}
    fields["out"] = str(trial_dir / "policy.zip")
    meta = importlib.import_module(SCRIPTS[config["script"]]).main(_argv(fields))
    agents = meta["metrics"]["agents"]
    returns = agents["ppo"]["returns"]
    base = config["baseline"]
    record = {
        **spec,
        "error": None,
        "checkpoint": fields["out"],
        "mean_return": float(np.mean(returns)),
        "returns": returns,
        "baseline_returns": agents[base]["returns"] if base else None,
        "train_seconds": meta["training"]["wall_seconds"],
        "timesteps_done": meta["training"]["timesteps_done"],
    }
    write_json(trial_dir / RECORD_FILE, record, indent=None)  # compact: 1e5 returns fit the limit
    tune.report({"mean_return": record["mean_return"], "key": spec["key"]})


def _read_record(sweep: dict[str, Any], spec: dict[str, Any]) -> dict[str, Any] | None:
    """The record of trial ``spec`` (``None``: none written), checked against the sweep.

    Read as bounded JSON (:func:`selenv.learned.resources.read_metadata`), never unpickled.

    Raises:
        ValueError: unreadable, or not the complete result of this trial (the message names
            the file and what differs).
    """
    from selenv.learned.resources import read_metadata

    path = sweep["out"] / "trials" / spec["key"] / RECORD_FILE
    if not path.exists():
        return None
    rec = read_metadata(path, "trial result")
    if not isinstance(rec, dict):
        raise ValueError(f"{path}: expected a JSON object")
    want = json.loads(json.dumps(spec))
    for key, value in want.items():
        if rec.get(key) != value:
            raise ValueError(
                f"{path}: records {key} = {rec.get(key)!r}, trial {spec['key']} of this sweep "
                f"has {value!r}"
            )
    n = len(sweep["eval_seeds"])
    columns = ["returns", "baseline_returns"] if sweep["baseline"] else ["returns"]
    for col in columns:
        values = rec.get(col)
        if not (
            isinstance(values, list)
            and len(values) == n
            and all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)
        ):
            raise ValueError(f"{path}: {col} must be a list of {n} numbers (one per eval seed)")
    if rec.get("error") is not None:
        raise ValueError(f"{path}: error must be null in a finished trial's record")
    return rec


def _trial_dirname(trial: Any) -> str:
    return str(trial.config["trial"]["key"])


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
            # no bar when stderr is not a terminal (logs keep their one-line messages)
            self.bar = tqdm(total=total, unit="trial", desc="sweep", disable=None)

        def on_trial_complete(self, iteration: int, trials: Any, trial: Any, **info: Any) -> None:
            self.bar.update(1)
            self.bar.set_postfix(last=f"{trial.last_result.get('mean_return', float('nan')):.4g}")

        def on_trial_error(self, iteration: int, trials: Any, trial: Any, **info: Any) -> None:
            self.bar.update(1)
            self.bar.write(f"trial {trial.trial_id} failed: see {trial.path}")

        def on_experiment_end(self, trials: Any, **info: Any) -> None:
            self.bar.close()

    return TrialBar()


def _stopper(stop: DeferredSignals) -> Any:
    """A Tune stopper that ends the whole experiment once ``stop`` recorded a signal."""
    from ray import tune

    class StopOnSignal(tune.Stopper):
        def __init__(self, flag: DeferredSignals | None) -> None:
            self.flag = flag

        def __call__(self, trial_id: str, result: dict[str, Any]) -> bool:
            return False

        def stop_all(self) -> bool:
            return self.flag is not None and self.flag.signal is not None

        def __reduce__(self) -> tuple[Any, ...]:  # Tune may pickle its run config: no handlers
            return (type(self), (None,))

    return StopOnSignal(stop)


def _rearm(stop: DeferredSignals) -> None:
    """Point SIGINT / SIGTERM at ``stop`` again (``ray.init`` replaces the driver's handlers).

    Ray installs a SIGTERM handler (``sys.exit``) and, in its core worker, a native crash
    handler; the ones ``stop`` saved when it was entered are still restored when it exits.
    Only the signals ``stop`` handles: a SIGINT ignored on entry (``nohup``) stays ignored.
    """
    for signum in list(stop._previous):
        try:
            signal.signal(signum, stop._handle)
        except ValueError:  # not the main thread: nothing was installed either
            return


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
        if key == "env_kwargs":  # size and nesting bounded before parsing
            json_object(text, "env_kwargs")
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
        raise UsageError(f"{option} {key}={text!r:.200}: not a valid {typ} ({exc})") from None
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


def _cpus() -> int:
    """CPUs this process may run on (its affinity mask where the platform has one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


class _Parser(argparse.ArgumentParser):
    """Usage errors as one line on stderr (no usage block), exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    """The command line (every option with its meaning and default)."""
    p = _Parser(prog=PROG, description=(__doc__ or "").split("\n")[0])
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
    p.add_argument(
        "--timesteps",
        type=int,
        help="PPO timesteps per trial (default: the script's; ceiling 1e9, and 1e10 over all "
        "trials)",
    )
    p.add_argument(
        "--eval-episodes",
        type=int,
        default=30,
        help="held-out episodes per trial (default: 30; ceiling 100000)",
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
        "again: measures run-to-run nondeterminism only (default: 1; at most "
        f"{MAX_TRIALS} trials in all)",
    )
    p.add_argument(
        "--num-workers",
        type=int,
        help="trials at once (default: Ray's CPUs; ceiling: this machine's CPUs, "
        f"{MAX_CLUSTER_WORKERS} with --address)",
    )
    p.add_argument("--address", help="Ray cluster HOST:PORT / auto (default: local Ray)")
    p.add_argument("--out", help="output folder (default: runs/tune_<script>)")
    p.add_argument(
        "--force",
        action="store_true",
        help="reuse a non-empty --out: its sweep.json, tune/, trials/ and results.* are "
        "deleted first (default: off)",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the stopped sweep in --out (same options): trials with a record are "
        "read back, the others are run (default: off)",
    )
    p.add_argument(
        "--allow-large",
        action="store_true",
        help="lift the ceilings: the training scripts' per trial (--timesteps 1e9, "
        "--eval-episodes 100000, n_envs 1024, n_steps 65536, batch_size 1048576, n_epochs "
        f"1000, hidden 16 x 4096) and the sweep's ({MAX_TRIALS} trials, "
        f"1e{round(math.log10(MAX_SWEEP_TIMESTEPS))} timesteps over all trials, --num-workers "
        "<= this machine's CPUs; with more, the local Ray instance declares that many CPUs) "
        "(default: off)",
    )
    return p


def _bounds_option(message: str, grid: dict[str, list[Any]]) -> str:
    """A training script's bound message with the sweep's option in place of the script's."""
    option, _, rest = message.partition(" ")
    field = option.removeprefix("--").replace("-", "_")
    if field in MANAGED:
        label = MANAGED[field]
    else:
        label = f"--{'grid' if field in grid else 'set'} {field}"
    return f"{label} {rest}"


def check_sizes(
    cls: type,
    fixed: dict[str, Any],
    grid: dict[str, list[Any]],
    n_seeds: int,
    args: argparse.Namespace,
) -> int:
    """Check every size against its ceiling before anything starts; the number of trials.

    Per trial the training scripts' own :func:`~selenv.learned.rl.training.check_bounds`
    (with every ``--grid`` value), then the sweep's: :data:`MAX_TRIALS`,
    :data:`MAX_SWEEP_TIMESTEPS` and ``--num-workers`` against the CPUs (``--address``:
    :data:`MAX_CLUSTER_WORKERS`). ``args.allow_large`` lifts the ceilings (not the lower
    bounds).

    Raises:
        UsageError: the option, its value, the ceiling and ``--allow-large``.
    """
    from selenv.learned.rl.training import check_bounds

    names = {f.name for f in dataclasses.fields(cls)}
    base = {k: v for k, v in fixed.items() if k in names}
    probes = [base] + [{**base, key: v} for key, values in grid.items() for v in values]
    for fields in probes:  # each bound is per field: every value once, not every combination
        try:
            check_bounds(cls(**{**fields, "allow_large": args.allow_large}))
        except UsageError as exc:
            raise UsageError(_bounds_option(str(exc), grid)) from None
    lift = "pass --allow-large to lift the ceilings"
    n_configs = math.prod(len(v) for v in grid.values())
    n_trials = n_seeds * n_configs * args.num_samples
    if n_trials > MAX_TRIALS and not args.allow_large:
        raise UsageError(
            f"--seeds x --grid x --num-samples: {n_seeds} seeds x {n_configs} "
            f"configurations x {args.num_samples} samples = {n_trials} trials is above the "
            f"ceiling of {MAX_TRIALS} trials: {lift}"
        )
    total = n_trials * fixed["total_timesteps"]
    if total > MAX_SWEEP_TIMESTEPS and not args.allow_large:
        raise UsageError(
            f"--timesteps {fixed['total_timesteps']} x {n_trials} trials = {total} timesteps "
            f"over all trials is above the ceiling of {MAX_SWEEP_TIMESTEPS}: {lift}"
        )
    if args.num_workers is not None and not args.allow_large:
        local = args.address is None
        ceiling = _cpus() if local else MAX_CLUSTER_WORKERS
        if args.num_workers > ceiling:
            what = "this machine's CPUs" if local else "with --address"
            raise UsageError(
                f"--num-workers {args.num_workers} is above its ceiling {ceiling} ({what}): {lift}"
            )
    return n_trials


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
    baseline = "" if args.baseline == "none" else args.baseline
    fixed.update(
        total_timesteps=timesteps,
        eval_episodes=args.eval_episodes,
        eval_seed=args.eval_seed,
        baselines=baseline,
        tensorboard_dir="",
        progress=False,
        torch_threads=1,
    )
    if args.allow_large:
        fixed["allow_large"] = True
    n_trials = check_sizes(cls, fixed, grid, len(seeds), args)
    n_envs = max(grid.get("n_envs", [fixed.get("n_envs", cls.n_envs)]))
    last_train = max(seeds) + n_envs - 1
    if args.eval_seed <= last_train:
        raise UsageError(
            f"--eval-seed {args.eval_seed}: held-out seeds must exceed the training env seeds "
            f"(seed + env index, up to {last_train})"
        )
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
    out = Path(args.out or f"runs/tune_{args.script}").resolve()
    if args.resume:
        if args.force:
            raise UsageError("--resume continues the sweep in --out, --force deletes it: use one")
        if not (out / SWEEP_FILE).is_file():
            raise UsageError(
                f"--resume: {out} holds no sweep to continue (no {SWEEP_FILE}); start one "
                "without --resume"
            )
    elif out.exists() and any(out.iterdir()) and not args.force:
        raise UsageError(
            f"--out {out}: exists and is not empty; pass --resume to continue the sweep in it "
            "or --force to start over"
        )
    return {
        "script": args.script,
        "env_id": module.ENV_ID,
        "seeds": seeds,
        "grid": grid,
        "fixed": fixed,
        "baseline": baseline,
        "eval_seeds": [args.eval_seed + e for e in range(args.eval_episodes)],
        "num_samples": args.num_samples,
        "n_trials": n_trials,
        "out": out,
    }


def _described(sweep: dict[str, Any]) -> dict[str, Any]:
    """The sweep as JSON values (what ``sweep.json`` holds)."""
    return json.loads(json.dumps({k: v for k, v in sweep.items() if k != "out"}))


def check_resume(sweep: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Compare the options with the stopped sweep in ``--out``; the records of its trials.

    Raises:
        UsageError: ``sweep.json`` unreadable, an option that differs (named, with both
            values), or a trial record that is not a result of this sweep.
    """
    from selenv.learned.resources import read_metadata

    path = sweep["out"] / SWEEP_FILE
    try:
        stored = read_metadata(path, "sweep description")
    except (FileNotFoundError, ValueError) as exc:
        raise UsageError(f"--resume: {exc}") from None
    if not isinstance(stored, dict):
        raise UsageError(f"--resume: {path} must hold a JSON object")
    ours = _described(sweep)
    mismatch = None
    theirs_fixed = stored.get("fixed")
    if not isinstance(theirs_fixed, dict):
        theirs_fixed = {}
    for key in sorted((set(ours["fixed"]) | set(theirs_fixed)) - {"allow_large"}):
        if ours["fixed"].get(key) != theirs_fixed.get(key):
            option = MANAGED.get(key, f"--set {key}")
            if key == "env_kwargs":
                option = "--env-kwargs"
            mismatch = (option, theirs_fixed.get(key), ours["fixed"].get(key))
            break
    if mismatch is None:
        for key, option in RESUME_KEYS.items():
            if stored.get(key) != ours[key]:
                mismatch = (option, stored.get(key), ours[key])
                break
    if mismatch is not None:
        option, theirs, mine = mismatch
        raise UsageError(
            f"--resume: {option} differs from the stopped sweep in {sweep['out']} (it has "
            f"{_short(theirs)}, this command {_short(mine)}); resume with its options"
        )
    done = {}
    for spec in trial_specs(sweep):
        try:
            rec = _read_record(sweep, spec)
        except (FileNotFoundError, ValueError) as exc:
            raise UsageError(
                f"--resume: {exc}; remove the folder {path.parent / 'trials' / spec['key']} "
                "to run that trial again"
            ) from None
        if rec is not None:
            done[spec["key"]] = rec
    return done


def _short(value: Any, limit: int = 80) -> str:
    text = json.dumps(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


# -- driver ------------------------------------------------------------------------------------
def run(
    sweep: dict[str, Any],
    specs: list[dict[str, Any]],
    args: argparse.Namespace,
    stop: DeferredSignals,
) -> dict[str, str]:
    """Start or join Ray, run ``specs`` with Tune until done or ``stop`` records a signal.

    Returns the errors of the trials that failed (key -> message); the results are the
    records the trials wrote. Ray is shut down before this returns, however it returns.
    """
    from ray import tune
    from ray.tune.logger import CSVLoggerCallback, JsonLoggerCallback

    from selenv.parallel import ray_session

    out: Path = sweep["out"]
    space = {
        "script": sweep["script"],
        "fixed": sweep["fixed"],
        "baseline": sweep["baseline"],
        "trials_dir": str(out / "trials"),
        "trial": tune.grid_search(specs),
    }
    runs = out / "tune"
    name = "sweep" if not (runs / "sweep").exists() else f"resume_{len(list(runs.iterdir()))}"
    env = {  # no TensorBoard event files; SIGINT goes to `stop`, not to Tune's own handler
        "TUNE_DISABLE_AUTO_CALLBACK_LOGGERS": "1",
        "TUNE_DISABLE_SIGINT_HANDLER": "1",
    }
    previous = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    num_cpus = args.num_workers if args.address is None else None
    errors: dict[str, str] = {}
    try:
        with ray_session(address=args.address, num_cpus=num_cpus) as ray:
            _rearm(stop)
            workers = args.num_workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
            sweep["num_workers"] = workers
            if stop.signal is not None:  # arrived while Ray started
                return errors
            tuner = tune.Tuner(
                tune.with_resources(run_trial, {"cpu": 1}),
                param_space=space,
                tune_config=tune.TuneConfig(
                    max_concurrent_trials=workers, trial_dirname_creator=_trial_dirname
                ),
                run_config=tune.RunConfig(
                    name=name,
                    storage_path=str(runs),
                    verbose=0,
                    stop=_stopper(stop),
                    callbacks=[JsonLoggerCallback(), CSVLoggerCallback(), _progress(len(specs))],
                ),
            )
            try:
                grid = tuner.fit()
            finally:  # a second signal stops the trials at once, never Ray's shutdown
                stop.second_raises = False
            for result in (grid[i] for i in range(len(grid))):  # indexable, not typed iterable
                if result.error is not None:
                    key = (result.config or {}).get("trial", {}).get("key", "?")
                    errors[key] = repr(result.error)[:500]
    finally:
        for k, v in previous.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return errors


def _collect(
    sweep: dict[str, Any], specs: list[dict[str, Any]], done: dict[str, Any], errors: dict[str, str]
) -> tuple[list[dict[str, Any]], list[str]]:
    """Every trial's entry (records read back, failures) and the keys of the trials not run."""
    trials, missing = [], []
    for spec in specs:
        rec = done.get(spec["key"])
        if rec is None:
            try:
                rec = _read_record(sweep, spec)
            except (FileNotFoundError, ValueError) as exc:
                rec = {**spec, "error": f"unreadable record: {exc}"}
        if rec is None and spec["key"] in errors:
            rec = {**spec, "error": errors[spec["key"]]}
        if rec is None:
            missing.append(spec["key"])
            continue
        for col in ("checkpoint", "mean_return", "returns", "baseline_returns"):
            rec.setdefault(col, None)
        trials.append(rec)
    trials.sort(key=lambda t: (json.dumps(t["params"], sort_keys=True), t["seed"], t["sample"]))
    return trials, missing


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or an argparse error (2, message already printed)
        return int(exc.code or 0)
    from selenv.parallel import ExecutorError

    try:
        sweep = plan(args)
    except ExecutorError as exc:
        raise UsageError(str(exc)) from None
    out: Path = sweep["out"]
    specs = trial_specs(sweep)
    with OutputLock(out / SWEEP_FILE):  # one sweep per --out (busy: exit 2)
        if args.resume:
            done = check_resume(sweep)
        else:
            for stale in OUTPUTS:  # only with --force (or leftovers of an empty --out)
                path = out / stale
                shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
            write_json(out / SWEEP_FILE, {"argv": _command(argv), **_described(sweep)})
            done = {}
        todo = [s for s in specs if s["key"] not in done]
        errors: dict[str, str] = {}
        stop = DeferredSignals()
        with stop:  # a signal stops the trials through Tune; a second one at once
            try:
                if todo:
                    errors = run(sweep, todo, args, stop)
            except (KeyboardInterrupt, Terminated):  # the second signal: Ray is shut down
                pass
            except ExecutorError as exc:
                raise UsageError(str(exc)) from None
            trials, missing = _collect(sweep, specs, done, errors)
            code = _report(sweep, trials, missing, stop.signal, argv)
    return code


def _command(argv: list[str] | None) -> list[str]:
    return list(argv) if argv is not None else sys.argv[1:]


def _report(
    sweep: dict[str, Any],
    trials: list[dict[str, Any]],
    missing: list[str],
    stopped: str | None,
    argv: list[str] | None,
) -> int:
    """Print the table, write ``results.json`` and ``results.md`` together; the exit code."""
    from selenv.bench.provenance import provenance

    out: Path = sweep["out"]
    rows = summarize(sweep, trials)
    failed = [t for t in trials if t["error"] is not None]
    completed = len(trials) - len(failed)
    n = sweep["n_trials"]
    status = None
    if missing:
        why = f"stopped by {stopped}" if stopped else "not run"
        failures = f", {len(failed)} failed" if failed else ""
        status = (
            f"{completed} of {n} trials completed ({len(missing)} {why}{failures}); continue "
            "with the same options and --resume"
        )
    table = format_table(sweep, rows, len(failed), incomplete=status)
    report = {
        "provenance": provenance(argv if argv is not None else sys.argv),
        **{k: v for k, v in sweep.items() if k != "out"},
        "out": str(out),
        "complete": not missing,
        "stopped": stopped,
        "n_completed": completed,
        "not_run": missing,
        "ci_method": "percentile bootstrap over trials (selenv.bench.stats.bootstrap_ci); "
        "ci95_t: Student t-interval",
        "configs": rows,
        "best": rows[0] if rows else None,
        "trials": trials,
    }
    text = json.dumps(report, indent=2) + "\n"
    print(table, end="")
    try:  # atomic, both files together: a failed write leaves the previous pair
        with atomic_paths([out / "results.json", out / "results.md"]) as (tmp_json, tmp_md):
            tmp_json.write_text(text, encoding="utf-8")
            tmp_md.write_text(table, encoding="utf-8")
    except OSError as exc:
        print(f"{PROG}: {describe_os_error(exc)} (the table is printed above)", file=sys.stderr)
        return 1
    if stopped is not None:
        word = "interrupted" if stopped == "SIGINT" else "terminated"
        where = f"{out / 'results.json'} and results.md"
        if completed < n:
            what = (
                f"{completed} of {n} trials completed, their results are in {where}"
                f"{' (marked incomplete)' if missing else ''}; continue with the same options "
                "and --resume"
            )
        else:
            what = f"all {n} trials had finished, their results are in {where}"
        print(f"{PROG}: {word} ({stopped}): {what}", file=sys.stderr)
        return EXIT_CODES[stopped]
    return 1 if failed or not rows else 0


def main(argv: list[str] | None = None) -> int:
    """Run the sweep, print and write the table; the exit code.

    0: done; 1: a trial failed or an output could not be written; 2: usage error (before
    anything starts); 130 / 143: stopped by SIGINT / SIGTERM (completed trials kept, see
    ``--resume``).
    """
    return guarded_main(_main, PROG, argv)


if __name__ == "__main__":
    raise SystemExit(main())
