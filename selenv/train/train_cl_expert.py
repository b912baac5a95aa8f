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
round's ``<out>_round<r>.zip`` + ``.json`` and, with ``--eval-episodes``, ``<out>.bench.json``.
Each checkpoint and its JSON are written as an atomic pair (the JSON records the zip's
``checkpoint_sha256``): an interrupted run keeps every round completed so far, intact.
"""

from __future__ import annotations

import json
import shlex
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, cast

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from selenv.atomic import write_json
from selenv.envs.resolved import resolved_env_config
from selenv.learned.config import arg, check_outputs, parse_config
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS, load_metadata
from selenv.learned.rl.expert import CL_ID, collect_cl_rollout_labels
from selenv.learned.rl.ranking import RankingData, fit_ranking
from selenv.learned.rl.safe_load import model_from_checkpoint
from selenv.learned.rl.training import (
    output_lock,
    read_checkpoint_metadata,
    run_cli,
    save_checkpoint,
    verify_pair,
)
from selenv.learned.rl.views import CandidateViewWrapper, view_for

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


def expert_outputs(cfg: Any) -> list[Path]:
    """Every file an expert-iteration run writes (checkpoint, rounds, bench JSON)."""
    out = Path(cfg.out)
    files = [out, out.with_suffix(".json")]
    for r in range(max(cfg.rounds, 0)):
        round_path = out.with_name(f"{out.stem}_round{r}.zip")
        files += [round_path, round_path.with_suffix(".json")]
    if cfg.eval_episodes:
        files.append(out.with_suffix(".bench.json"))
    return files


def parse_args(argv: list[str] | None = None) -> Config:
    """The run's :class:`Config` from the command line (and ``--config FILE``)."""
    return parse_config(Config, argv, (__doc__ or "").split("\n")[0], script=SCRIPT)


def outputs(cfg: Config) -> list[Path]:
    """The files the run writes."""
    return expert_outputs(cfg)


def _save(model: Any, meta: dict[str, Any], path: Path) -> None:
    """``path`` and its ``.json`` as an atomic pair (``training.save_checkpoint``)."""
    save_checkpoint(model, meta, path)


def evaluate_with_bench(
    checkpoint: Path, cfg: Any, env_id: str = CL_ID, baseline: str = "greedy"
) -> dict[str, Any]:
    """``selenv bench`` of ``ppo:checkpoint`` vs ``baseline`` and rollout; returns its JSON."""
    from selenv.cli import main as selenv_main

    out = checkpoint.with_suffix(".bench.json")
    argv = [
        "bench",
        env_id,
        "--agents",
        f"{baseline},rollout,ppo:{checkpoint}",
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
    if code != 0:
        raise RuntimeError(f"selenv {' '.join(argv)} exited with {code}")
    result: dict[str, Any] = json.loads(out.read_text())
    result["command"] = "selenv " + shlex.join(argv)
    return result


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Collect, fit (per round), save, evaluate; return the checkpoint's metadata."""
    cfg = parse_args(argv)
    check_outputs(f"python -m {SCRIPT}", outputs(cfg), force=cfg.force)
    with output_lock(cfg.out, f"python -m {SCRIPT}"):  # one run per --out
        return run_expert_iteration(cfg, argv, CL_ID, collect_cl_rollout_labels, SCRIPT, "greedy")


def run_expert_iteration(
    cfg: Any,
    argv: list[str] | None,
    env_id: str,
    collect: Callable[..., RankingData],
    script: str,
    baseline: str,
) -> dict[str, Any]:
    """The DAgger loop shared by the expert-iteration scripts (module docstring).

    Existing outputs without ``cfg.force`` exit with code 2 (the scripts check first).
    """
    out = Path(cfg.out)
    if out.suffix != ".zip":
        raise ValueError(f"--out must end in .zip, got {cfg.out!r}")
    check_outputs(f"python -m {script}", expert_outputs(cfg), force=cfg.force)
    if cfg.rounds < 1:
        raise ValueError(f"--rounds must be >= 1, got {cfg.rounds}")
    kwargs = json.loads(cfg.env_kwargs)
    if not isinstance(kwargs, dict):
        raise ValueError(f"--env-kwargs must be a JSON object, got {cfg.env_kwargs!r}")
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
        **src,
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
    parts: list[RankingData] = []
    behaviour: str | None = None
    for r in range(cfg.rounds):
        t0 = time.perf_counter()
        extra = {"view": view} if env_id == CL_ID else {}
        parts.append(
            collect(
                kwargs,
                cfg.states_per_round,
                cfg.seed * 100 + r,
                **extra,
                top_k=cfg.top_k,
                horizon=cfg.horizon,
                explore=cfg.explore,
                behaviour=behaviour,
                workers=cfg.workers,
                progress=cfg.progress,
            )
        )
        data = RankingData.concatenate(parts)
        fit = fit_ranking(
            model.policy,
            data,
            epochs=cfg.epochs,
            learning_rate=cfg.learning_rate,
            temperature=cfg.temperature,
            seed=cfg.seed + r,
            progress=cfg.progress,
        )
        log = {"round": r, "states": len(data), **fit, "seconds": round(time.perf_counter() - t0)}
        meta["expert_iteration"]["rounds_log"].append(log)
        print(json.dumps(log))
        round_path = out.with_name(f"{out.stem}_round{r}.zip")
        _save(model, meta, round_path)
        behaviour = str(round_path)
    meta["expert_iteration"]["wall_seconds"] = round(time.perf_counter() - start, 1)
    _save(model, meta, out)
    if cfg.eval_episodes:
        bench = evaluate_with_bench(out, cfg, env_id, baseline)
        meta["metrics"] = {
            "command": bench["command"],
            "results": bench["results"],
            "provenance": bench.get("provenance"),
        }
        write_json(out.with_suffix(".json"), meta)
    return meta


def cli() -> None:
    """Console-script entry point (same options as ``main``).

    Exit code 0 after a run, 2 on a usage error or a busy ``--out``, 1 on an I/O failure,
    130 / 143 after SIGINT / SIGTERM.
    """
    raise SystemExit(run_cli(main, f"python -m {SCRIPT}"))


if __name__ == "__main__":
    cli()
