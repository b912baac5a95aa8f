"""Train one shared candidate-scoring RLModule with RLlib's multi-agent PPO (PettingZoo envs).

RLlib new API stack: ``PPOConfig`` with the env adapter
:class:`selenv.learned.rl.rllib_env.SelenvMultiAgentEnv` (only the agents on turn observe and act,
shared team reward, per-agent candidate views), every agent mapped to the one module id
``"shared"`` (parameter sharing) whose class is
:class:`selenv.learned.rl.rllib_module.CandidateScoringRLModule` (permutation-equivariant logits
masked by ``action_mask``, value from the pooled embedding). Ray is started (or joined with
``--address``) by :func:`selenv.parallel.ray_session` and stopped at the end if started here.

Outputs, next to ``--out`` (default ``runs/rllib_<env>/policy``; refused if they exist,
unless ``--force``, before Ray starts):

* ``<out>.pth`` + ``<out>.json``: the trained module, exported without pickle
  (:func:`selenv.learned.rl.rllib_agent.export_module`), playable by ``selenv bench`` as
  ``rllib:path=<out>.json``; RLlib's own (pickled) checkpoints are not written;
* ``<out>.metrics.json``: one record per iteration (RLlib's sampled returns, summed over
  agents, the learner's losses, steps, wall time), plus TensorBoard scalars with
  ``--tensorboard-dir``.

The outputs are written atomically (:mod:`selenv.atomic`): the ``.pth`` and ``.json`` as one
pair, so a failed or killed write leaves the previous files byte-identical. A second run on
the same ``--out`` is refused while this one holds its lock (exit 2, one line). SIGINT /
SIGTERM stop the run after keeping the module of the last completed iteration (its JSON marked
``"complete": false`` and ``"interrupted"``) and its metrics: exit 130 / 143 with one line.
``--hidden`` / ``--vf`` widths beyond the loaders' ceilings
(:data:`selenv.learned.resources.CHECKPOINT_LIMITS`) are refused up front (exit 2).

After training, ``--eval-episodes`` held-out episodes (seeds ``--eval-seed ...``) are played by
``greedy`` and the exported module through ``selenv bench``'s runner (team return, paired
difference with its 95 % CI); the summary goes into the JSON.

    python -m selenv.train.train_rllib_marl --env fim_selection_v0 --iterations 40
    python -m selenv.train.train_rllib_marl --config configs/rllib_fim_selection_v0.toml \
        --out checkpoints/rllib_fim_selection_v0 --force     # the shipped module's run
    selenv bench selenv.multiagent.fim_selection_v0 --agents greedy,random,rllib:path=P

with ``P = runs/rllib_fim_selection_v0/policy.json``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import torch as th
from tqdm.auto import tqdm

from selenv.atomic import OutputBusyError, OutputLock, write_json
from selenv.exits import Terminated
from selenv.learned.config import arg, check_outputs, parse_config, usage_error
from selenv.learned.resources import bounded_widths, read_metadata
from selenv.learned.rl.candidate_policy import obs_layout
from selenv.learned.rl.rllib_env import SelenvMultiAgentEnv, resolve_env
from selenv.learned.rl.training import TrainingInterrupted, TrainingTerminated, run_cli

__all__ = ["Config", "UsageError", "build_config", "main", "outputs", "parse_args"]

ENVS = ("fim_selection_v0", "receiver_clustering_v1")
#: --gain-skip-init when not given: 0 (near uniform) as the shipped fim_marl run; 1 for
#: clustering, whose view gives the "stay" label the only positive gain (p(stay) ~ 0.999)
GAIN_SKIP_DEFAULTS = {"fim_selection_v0": 0.0, "receiver_clustering_v1": 1.0}
SCRIPT = "selenv.train.train_rllib_marl"
PROG = f"python -m {SCRIPT}"


class UsageError(ValueError):
    """A bad command line (reported on one line, exit code 2)."""


@dataclass
class Config:
    """Every option of the command line (``--kebab-case``); see ``--help`` for each."""

    env: str = arg("fim_selection_v0", "PettingZoo module of selenv.multiagent to train on",
                   choices=ENVS)  # fmt: skip
    iterations: int = arg(
        20, "PPO iterations (each samples --train-batch-size env steps, then learns)"
    )
    max_minutes: float = arg(
        0.0,
        "stop early, before an iteration that would end past this many minutes since "
        "the start (0: run every iteration)",
    )
    seed: int = arg(0, "seed of RLlib (env runners' env resets, torch initialisation, minibatches)")
    env_kwargs: str = arg(
        "{}", "JSON object of the env constructor's keywords ({}: the env's defaults)"
    )
    num_env_runners: int = arg(
        0, "remote RLlib env runners (Ray actors) sampling in parallel; 0 samples in this process"
    )
    num_envs_per_env_runner: int = arg(1, "envs stepped together by each env runner")
    address: str | None = arg(
        None,
        "join the running Ray cluster at HOST:PORT (or 'auto'); None: start a local "
        "Ray instance and stop it at the end",
    )
    num_cpus: int | None = arg(None, "CPUs of the local Ray instance (None: all of this machine's)")
    out: str | None = arg(
        None,
        "output stem: writes OUT.pth, OUT.json, OUT.metrics.json (None: runs/rllib_<env>/policy)",
    )
    force: bool = arg(False, "overwrite existing output files")
    train_batch_size: int = arg(
        2000, "env steps sampled per iteration (RLlib train_batch_size_per_learner)"
    )
    minibatch_size: int = arg(256, "minibatch size of the PPO epochs (agent steps)")
    num_epochs: int = arg(4, "passes over each iteration's batch")
    lr: float = arg(1e-3, "Adam learning rate")
    gamma: float = arg(1.0, "discount (1: the undiscounted team return is the objective)")
    lambda_: float = arg(0.95, "GAE lambda")
    clip_param: float = arg(0.2, "PPO clip range")
    entropy_coeff: float = arg(1e-3, "entropy bonus coefficient")
    vf_loss_coeff: float = arg(0.5, "value loss coefficient")
    vf_clip_param: float = arg(
        1e6,
        "clip of the squared value error (RLlib's default 10 stops value learning when "
        "returns are ~36 nats; large = no clip)",
    )
    grad_clip: float = arg(0.5, "max global gradient norm (0: none)")
    hidden: str = arg("64,64", "comma-separated widths of the shared per-candidate MLP")
    vf: str = arg("64", "comma-separated widths of the value MLP on the pooled embedding")
    activation: str = arg("tanh", "activation of both MLPs", choices=("tanh", "relu"))
    gain_skip_init: float | None = arg(
        None,
        "initial weight w of the relative-gain skip w r_k in every logit (None: per env "
        f"{GAIN_SKIP_DEFAULTS}; 1 starts receiver clustering near 'stay')",
    )
    eval_episodes: int = arg(
        20, "held-out episodes played by greedy and the trained module after training (0: none)"
    )
    eval_seed: int = arg(10_000, "seed of the first held-out episode")
    tensorboard_dir: str = arg(
        "", "also write TensorBoard scalars there (empty: only OUT.metrics.json)"
    )
    progress: bool = arg(True, "show a tqdm bar over the iterations")
    torch_threads: int = arg(1, "torch CPU threads of this process")


def _fail(message: object) -> NoReturn:
    usage_error(PROG, message)


def _widths(text: str, option: str) -> list[int]:
    try:
        widths = [int(w) for w in text.split(",") if w.strip()]
    except ValueError:
        raise UsageError(f"{option} must be comma-separated positive ints, got {text!r}") from None
    if (option == "--hidden" and not widths) or any(w < 1 for w in widths):
        raise UsageError(f"{option} must be comma-separated positive ints, got {text!r}")
    try:  # the loaders refuse larger exports: refuse them before training, not after
        return bounded_widths(widths, option, "model_config")
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def parse_args(argv: list[str] | None = None) -> tuple[Config, dict[str, Any]]:
    """The config and the parsed env kwargs; usage errors exit 2 with a one-line reason.

    ``--config FILE`` (TOML) supplies defaults (:func:`selenv.learned.config.parse_config`).
    Existing outputs are checked by :func:`main` (:func:`outputs`), not here.
    """
    cfg = parse_config(Config, argv, (__doc__ or "").split("\n")[0], script=SCRIPT)
    try:
        env_kwargs = _check(cfg)
    except UsageError as exc:
        _fail(exc)
    return cfg, env_kwargs


def outputs(cfg: Config) -> list[Path]:
    """The files the run writes: ``<out>.json``, ``<out>.pth``, ``<out>.metrics.json``."""
    return list(_outputs(cfg))


def _check(cfg: Config) -> dict[str, Any]:
    """Validate ``cfg`` (module docstring); return the env kwargs. Raises :class:`UsageError`."""
    at_least = {
        "iterations": 1, "seed": 0, "num_env_runners": 0, "num_envs_per_env_runner": 1,
        "train_batch_size": 1, "minibatch_size": 1, "num_epochs": 1, "eval_episodes": 0,
        "eval_seed": 0, "torch_threads": 1,
    }  # fmt: skip
    for name, low in at_least.items():
        if getattr(cfg, name) < low:
            raise UsageError(f"--{name.replace('_', '-')} must be >= {low}")
    if cfg.gain_skip_init is not None and not math.isfinite(cfg.gain_skip_init):
        raise UsageError("--gain-skip-init must be finite")
    if cfg.num_cpus is not None and cfg.num_cpus < 1:
        raise UsageError("--num-cpus must be >= 1")
    if cfg.minibatch_size > cfg.train_batch_size:
        raise UsageError("--minibatch-size must not exceed --train-batch-size")
    positive = ("lr", "clip_param", "vf_clip_param")
    nonneg = ("entropy_coeff", "vf_loss_coeff", "grad_clip", "max_minutes")
    for name in (*positive, *nonneg):
        value = getattr(cfg, name)
        if not math.isfinite(value) or value < 0 or (name in positive and value == 0):
            kind = "> 0" if name in positive else ">= 0"
            raise UsageError(f"--{name.replace('_', '-')} must be finite and {kind}")
    if not (0 < cfg.gamma <= 1 and 0 <= cfg.lambda_ <= 1):
        raise UsageError("--gamma must be in (0, 1] and --lambda in [0, 1]")
    _widths(cfg.hidden, "--hidden")
    _widths(cfg.vf, "--vf")
    try:
        env_kwargs = json.loads(cfg.env_kwargs)
    except RecursionError:
        raise UsageError("--env-kwargs is nested too deeply") from None
    except ValueError as exc:  # JSONDecodeError, ints beyond the digit limit
        raise UsageError(f"--env-kwargs is not valid JSON: {exc}") from None
    if not isinstance(env_kwargs, dict):
        raise UsageError(f"--env-kwargs must be a JSON object, got {cfg.env_kwargs!r}")
    try:  # the env rejects bad keywords now, not inside an env runner
        SelenvMultiAgentEnv({"env": cfg.env, "env_kwargs": env_kwargs}).close()
    except (TypeError, ValueError) as exc:
        raise UsageError(f"--env-kwargs rejected by {cfg.env}: {exc}") from None
    return env_kwargs


def _outputs(cfg: Config) -> tuple[Path, Path, Path]:
    from selenv.learned.rl.rllib_agent import export_paths

    json_path, pth_path = export_paths(cfg.out or f"runs/rllib_{cfg.env}/policy")
    return json_path, pth_path, json_path.with_suffix(".metrics.json")


def _shared(agent_id: Any, episode: Any, **kwargs: Any) -> str:
    """Policy mapping: every agent plays the one shared module (parameter sharing)."""
    from selenv.learned.rl.rllib_module import SHARED_MODULE_ID

    return SHARED_MODULE_ID


def build_config(cfg: Config, env_kwargs: dict[str, Any]) -> Any:
    """The RLlib ``PPOConfig`` of ``cfg`` (new API stack, one shared RLModule)."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    from selenv.learned.rl.rllib_module import SHARED_MODULE_ID, CandidateScoringRLModule

    env_config = {"env": cfg.env, "env_kwargs": env_kwargs}
    probe = SelenvMultiAgentEnv(env_config)
    spec = RLModuleSpec(
        module_class=CandidateScoringRLModule,
        observation_space=probe.agent_observation_space,
        action_space=probe.agent_action_space,
        model_config=_model_config(cfg),
    )
    probe.close()
    return (
        PPOConfig()
        .api_stack(enable_rl_module_and_learner=True, enable_env_runner_and_connector_v2=True)
        .environment(SelenvMultiAgentEnv, env_config=env_config)
        .env_runners(
            num_env_runners=cfg.num_env_runners,
            num_envs_per_env_runner=cfg.num_envs_per_env_runner,
        )
        .learners(num_learners=0)
        .multi_agent(policies={SHARED_MODULE_ID}, policy_mapping_fn=_shared)
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs={SHARED_MODULE_ID: spec}))
        .training(
            train_batch_size_per_learner=cfg.train_batch_size,
            minibatch_size=cfg.minibatch_size,
            num_epochs=cfg.num_epochs,
            lr=cfg.lr,
            gamma=cfg.gamma,
            lambda_=cfg.lambda_,
            clip_param=cfg.clip_param,
            vf_clip_param=cfg.vf_clip_param,
            entropy_coeff=cfg.entropy_coeff,
            vf_loss_coeff=cfg.vf_loss_coeff,
            grad_clip=cfg.grad_clip or None,
            use_kl_loss=False,  # clipped surrogate only, as SB3's PPO
        )
        .debugging(seed=cfg.seed, log_level="ERROR")
    )


def _model_config(cfg: Config) -> dict[str, Any]:
    return {
        "hidden": _widths(cfg.hidden, "--hidden"),
        "vf": _widths(cfg.vf, "--vf"),
        "activation": cfg.activation,
        "gain_skip_init": (
            GAIN_SKIP_DEFAULTS[cfg.env] if cfg.gain_skip_init is None else cfg.gain_skip_init
        ),
    }


def _get(result: dict[str, Any], *path: str) -> float | None:
    node: Any = result
    for key in path:
        if not isinstance(node, dict) or key not in node:
            return None
        node = node[key]
    try:
        return float(node)
    except (TypeError, ValueError):
        return None


def _record(it: int, result: dict[str, Any], seconds: float) -> dict[str, Any]:
    """One metrics record of an iteration's result (``None`` where RLlib reported nothing)."""
    from selenv.learned.rl.rllib_module import SHARED_MODULE_ID

    learner = ("learners", SHARED_MODULE_ID)
    return {
        "iteration": it,
        "wall_seconds": round(seconds, 3),
        "sample_seconds": _get(result, "timers", "env_runner_sampling_timer"),
        "learn_seconds": _get(result, "timers", "learner_update_timer"),
        "env_steps_lifetime": _get(result, "env_runners", "num_env_steps_sampled_lifetime"),
        "module_steps_lifetime": _get(
            result, "env_runners", "num_module_steps_sampled_lifetime", SHARED_MODULE_ID
        ),
        "episodes": _get(result, "env_runners", "num_episodes"),
        "episode_return_mean_sum_over_agents": _get(result, "env_runners", "episode_return_mean"),
        "agent_episode_returns_mean": {
            str(a): float(v)
            for a, v in result.get("env_runners", {}).get("agent_episode_returns_mean", {}).items()
        },
        "episode_len_mean": _get(result, "env_runners", "episode_len_mean"),
        "policy_loss": _get(result, *learner, "policy_loss"),
        "vf_loss": _get(result, *learner, "vf_loss"),
        "vf_explained_var": _get(result, *learner, "vf_explained_var"),
        "entropy": _get(result, *learner, "entropy"),
    }


def _evaluate(cfg: Config, env_kwargs: dict[str, Any], json_path: Path) -> dict[str, Any]:
    """Greedy and the exported module on the held-out seeds, through the bench's runner."""
    from selenv.bench import run_bench

    env_id = resolve_env(cfg.env)
    spec = f"rllib:path={json_path}"
    res = run_bench(
        env_id, ["greedy", spec], episodes=cfg.eval_episodes, seed=cfg.eval_seed,
        env_kwargs=env_kwargs, progress=False, baseline="greedy",
    )  # fmt: skip
    doc = res.to_json()
    out = {}
    for name, agent in doc["agents"].items():
        keep = ("mean_return", "std_return", "mean_final_objective", "paired", "skipped")
        out["rllib" if name == spec else name] = {k: agent[k] for k in keep if k in agent}
    return {
        "seeds": [cfg.eval_seed, cfg.eval_seed + cfg.eval_episodes - 1],
        "episodes": cfg.eval_episodes,
        "env_kwargs": env_kwargs,
        "baseline": "greedy",
        "agents": out,
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Train, export, evaluate; return the exported metadata (the JSON's content).

    The outputs are locked for the run (a second run on the same ``--out``: exit 2, one
    line). SIGINT / SIGTERM (the latter while :func:`selenv.exits.sigterm_raises` is active,
    as under :func:`cli`) stop the run: the module of the last completed iteration is
    exported (marked ``"complete": false``, ``"interrupted": "SIGINT"``) with the metrics so
    far, the evaluation is skipped, and ``TrainingInterrupted`` / ``TrainingTerminated`` is
    raised (exit 130 / 143 with one line through :func:`cli`).
    """
    cfg, env_kwargs = parse_args(argv)
    folders = [cfg.tensorboard_dir] if cfg.tensorboard_dir else []
    check_outputs(PROG, outputs(cfg), force=cfg.force, folders=folders)
    json_path, _, _ = _outputs(cfg)
    lock = OutputLock(json_path)
    try:
        lock.acquire()
    except OutputBusyError as exc:
        _fail(exc)
    try:
        return _train(cfg, env_kwargs)
    finally:
        lock.release()


def _train(cfg: Config, env_kwargs: dict[str, Any]) -> dict[str, Any]:
    """:func:`main` after the checks, under the output lock."""
    import ray

    from selenv.learned.rl.rllib_agent import export_module
    from selenv.learned.rl.rllib_module import SHARED_MODULE_ID, build_module
    from selenv.parallel import ExecutorError, ray_session

    th.set_num_threads(cfg.torch_threads)
    json_path, _, metrics_path = _outputs(cfg)
    records: list[dict[str, Any]] = []
    writer = None
    if cfg.tensorboard_dir:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(cfg.tensorboard_dir)
    start = time.perf_counter()
    stopped: str | None = None
    weights: dict[str, Any] | None = None  # the module after the last completed iteration
    with contextlib.ExitStack() as stack:
        try:
            stack.enter_context(ray_session(cfg.address, cfg.num_cpus))
        except ExecutorError as exc:
            _fail(exc)
        algo = build_config(cfg, env_kwargs).build_algo()
        stack.callback(algo.stop)
        bar = tqdm(range(1, cfg.iterations + 1), desc=f"rllib {cfg.env}", unit="it",
                   disable=not cfg.progress)  # fmt: skip
        longest = 0.0
        try:
            for it in bar:
                t0 = time.perf_counter()
                if cfg.max_minutes and t0 + longest - start > 60.0 * cfg.max_minutes:
                    break
                result = algo.train()
                longest = max(longest, time.perf_counter() - t0)
                record = _record(it, result, time.perf_counter() - t0)
                current = algo.learner_group.get_weights(module_ids=[SHARED_MODULE_ID])
                weights = {k: np.array(v, copy=True) for k, v in current[SHARED_MODULE_ID].items()}
                records.append(record)
                ret = record["episode_return_mean_sum_over_agents"]
                if ret is not None and np.isfinite(ret):
                    bar.set_postfix_str(f"return(sum over agents)={ret:.3f}")
                if writer is not None:
                    for key, value in record.items():
                        if isinstance(value, int | float) and key != "iteration":
                            writer.add_scalar(f"rllib/{key}", value, it)
        except KeyboardInterrupt:
            stopped = "SIGINT"
        except Terminated:
            stopped = "SIGTERM"
        bar.close()
        n_ray_version = ray.__version__
    wall = time.perf_counter() - start
    if writer is not None:
        writer.close()
    stop_error = TrainingInterrupted if stopped == "SIGINT" else TrainingTerminated
    how = f"{'interrupted' if stopped == 'SIGINT' else 'terminated'} ({stopped})"
    if weights is None:
        if stopped is not None:
            raise stop_error(f"{how} before the first iteration completed: nothing was written")
        raise ValueError("no iteration ran (--max-minutes too small?)")
    probe = SelenvMultiAgentEnv({"env": cfg.env, "env_kwargs": env_kwargs})
    layout = obs_layout(probe.agent_observation_space)
    probe.close()
    module = build_module(layout["n"], layout["whitened_dim"], _model_config(cfg))
    module.load_state_dict({k: th.as_tensor(v) for k, v in weights.items()}, strict=True)
    from selenv import __version__ as selenv_version

    metadata = {
        "env_id": resolve_env(cfg.env),
        "env_kwargs": env_kwargs,
        "training": {
            **{k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("force", "progress")},
            "algorithm": "RLlib PPO (new API stack), one shared RLModule",
            "iterations_done": len(records),
            "env_steps": records[-1]["env_steps_lifetime"] if records else 0,
            "agent_steps": records[-1]["module_steps_lifetime"] if records else 0,
            "wall_seconds": round(wall, 1),
            "metrics_file": metrics_path.name,
            "complete": stopped is None,
            **({"interrupted": stopped} if stopped else {}),
        },
        "iterations": len(records),
        "ray_version": n_ray_version,
        "torch_version": th.__version__,
        "selenv_version": selenv_version,
    }
    json_path, _ = export_module(module, json_path, metadata)
    write_json(metrics_path, records, indent=1)
    metadata = read_metadata(json_path, "RLlib export metadata")
    if stopped is not None:
        raise stop_error(
            f"{how} after iteration {len(records)} of {cfg.iterations}: kept {json_path} "
            "(+ .pth, .metrics.json) of the last completed iteration, marked incomplete"
        )
    if cfg.eval_episodes:
        metadata["eval"] = _evaluate(cfg, env_kwargs, json_path)
        write_json(json_path, metadata)  # the weights are unchanged: the pair still matches
    print(f"wrote {json_path} (+ .pth, .metrics.json) in {wall:.0f} s", file=sys.stderr)
    return metadata


def cli(argv: list[str] | None = None) -> int:
    """Command-line entry point: :func:`main` with the exit codes of :mod:`selenv.exits`.

    Returns 0 after a run; 1 with one line for an I/O failure (the previous outputs are left
    as they were); 130 / 143 with one line naming what was kept after SIGINT / SIGTERM.
    A usage error or a busy output exits 2 with one line (``SystemExit``, as argparse does).
    """
    return run_cli(main, PROG, argv)


if __name__ == "__main__":
    sys.exit(cli())
