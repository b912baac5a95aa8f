"""Learning curves of the PPO trainer: the current policy's held-out score against env steps.

With ``--curve-every N`` (:class:`~selenv.learned.rl.training.PPOConfig.curve_every`),
:func:`~selenv.learned.rl.training.train` evaluates the policy being trained at the first
iteration boundary after every ``N`` environment steps, once before PPO starts (step 0, after
any pre-training) and once at the end, on ``--curve-episodes`` fixed held-out seeds
``eval_seed``, ``eval_seed + 1``, ... The agents of ``--baselines`` (e.g. ``greedy``,
``random``) are evaluated once, on the same seeds, with the first point. The checkpoint's
JSON records::

    "learning_curve": {"seeds": [first, last], "episodes": K,
                       "points": [{"timesteps": t, "mean_return": r, "wall_seconds": w}, ...],
                       "baselines": {"greedy": mean, "random": mean}}

``wall_seconds`` is the run's elapsed wall time at the point (training plus these
evaluations, summed over resumed runs). With TensorBoard on, each point is also logged as
``eval/mean_return`` and ``eval/normalized_score`` (:func:`normalized_score`: random 0,
greedy 1) at its step.

How the policy is evaluated: each point saves the live model as a scratch checkpoint pair in
a temporary folder (:func:`~selenv.learned.rl.training.save_checkpoint`, the metadata of the
run) and plays it through the ``ppo`` agent
(:class:`~selenv.learned.rl.agent.SB3PolicyAgent`) on the raw evaluation env, the same path as
the final evaluation (:func:`~selenv.learned.rl.training.evaluate_checkpoint`): the candidate
view, the masks, the deterministic action and a pool size other than the training one are
handled exactly as the saved checkpoint will be. The cost, one small zip written and read per
point, is small next to the episodes.

The training is not affected: the evaluation runs on its own envs (seeded by the held-out
seeds), and the ``random`` / ``numpy`` / ``torch`` global generators (which rebuilding the
policy draws from) are restored afterwards, so a run with a curve trains the same weights as
one without. A pending SIGINT / SIGTERM abandons the point being evaluated (between episodes)
and the run stops as usual. The points so far travel in the ``.last`` checkpoint's JSON, and a
``--resume`` run continues the list.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from selenv.agents import Agent
from selenv.bench.runner import AgentResult, run_episode
from selenv.exits import DeferredSignals, UsageError
from selenv.learned.rl.training import (
    _NOT_SAVED,
    PPOConfig,
    _rng_state,
    _set_rng_state,
    save_checkpoint,
)

__all__ = [
    "CURVE_KEY",
    "CurveCallback",
    "CurveRecorder",
    "check_curve",
    "normalized_score",
    "resumed_curve",
]

#: the metadata key of the learning curve
CURVE_KEY = "learning_curve"


def normalized_score(mean_return: float, baselines: dict[str, float]) -> float | None:
    """``(R - R_random) / (R_greedy - R_random)``: random 0, greedy 1.

    ``None`` when ``baselines`` lacks ``greedy`` or ``random`` or they score alike.
    """
    greedy, rand = baselines.get("greedy"), baselines.get("random")
    if greedy is None or rand is None or greedy == rand:
        return None
    return (mean_return - rand) / (greedy - rand)


def _number(value: Any) -> bool:
    return (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and math.isfinite(float(value))
    )


def _integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def check_curve(record: Any, name: str) -> dict[str, Any]:
    """``record`` checked as a ``learning_curve`` block (untrusted JSON); returned as is.

    Raises:
        ValueError: naming ``name`` and the malformed field.
    """
    where = f"{name}: learning_curve"
    if not isinstance(record, dict):
        raise ValueError(f"{where} must be an object")
    seeds = record.get("seeds")
    if not (isinstance(seeds, list) and len(seeds) == 2 and all(_integer(s) for s in seeds)):
        raise ValueError(f"{where}.seeds must be [first, last] integers, got {seeds!r:.80}")
    episodes = record.get("episodes")
    if not isinstance(episodes, int) or isinstance(episodes, bool) or episodes < 1:
        raise ValueError(f"{where}.episodes must be an integer >= 1, got {episodes!r:.80}")
    baselines = record.get("baselines")
    if not isinstance(baselines, dict) or not all(
        isinstance(k, str) and _number(v) for k, v in baselines.items()
    ):
        raise ValueError(f"{where}.baselines must map agent names to numbers")
    points = record.get("points")
    if not isinstance(points, list):
        raise ValueError(f"{where}.points must be a list")
    previous = -1
    for i, point in enumerate(points):
        ok = (
            isinstance(point, dict)
            and _integer(point.get("timesteps"))
            and _number(point.get("mean_return"))
            and _number(point.get("wall_seconds"))
        )
        if not ok:
            raise ValueError(
                f"{where}.points[{i}] must hold integer timesteps and numbers mean_return, "
                "wall_seconds"
            )
        if point["timesteps"] <= previous:
            raise ValueError(f"{where}.points must be in increasing timesteps (at [{i}])")
        previous = point["timesteps"]
    return record


def resumed_curve(cfg: PPOConfig, meta: dict[str, Any]) -> dict[str, Any] | None:
    """The learning curve a ``--resume`` checkpoint's metadata ``meta`` carries, checked.

    Its points after the checkpoint's step count are dropped. ``None`` when it carries none
    (a run with ``--curve-every`` then starts its curve at the resumed step).

    Raises:
        UsageError: malformed, or recorded on other held-out episodes (``--curve-episodes``,
            ``--eval-seed``), or present while ``--curve-every`` is 0.
    """
    path = cfg.resume
    if CURVE_KEY not in meta:
        return None
    try:
        record = check_curve(meta[CURVE_KEY], f"--resume {path}")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if not cfg.curve_every:
        raise UsageError(
            f"--resume {path}: it records a learning curve; continue it with the --curve-every "
            "of the interrupted run"
        )
    first = record["seeds"][0]
    if record["episodes"] != cfg.curve_episodes or first != cfg.eval_seed:
        raise UsageError(
            f"--resume {path}: its learning curve was evaluated on {record['episodes']} "
            f"episodes from seed {first}, this run has --curve-episodes {cfg.curve_episodes} "
            f"--eval-seed {cfg.eval_seed}; resume with the options of the interrupted run"
        )
    done = int(meta["resume_state"]["num_timesteps"])
    return {**record, "points": [p for p in record["points"] if p["timesteps"] <= done]}


class CurveRecorder:
    """Evaluates the live model at the curve's points and keeps the ``learning_curve`` block.

    Args:
        cfg: the run's options (``curve_every``, ``curve_episodes``, ``eval_seed``,
            ``baselines``).
        env_id: the env the ``ppo`` agent plays.
        make_eval_env: builds the raw evaluation env (as for the final evaluation).
        metadata: the run's metadata now (written next to the scratch checkpoint).
        clock: the run's elapsed wall seconds.
        flag: the run's deferred signals; a pending one abandons a point.
        resumed: the curve of a ``--resume`` checkpoint (:func:`resumed_curve`), continued.
    """

    def __init__(
        self,
        cfg: PPOConfig,
        *,
        env_id: str,
        make_eval_env: Callable[[], gym.Env[Any, Any]],
        metadata: Callable[[], dict[str, Any]],
        clock: Callable[[], float],
        flag: DeferredSignals,
        resumed: dict[str, Any] | None = None,
    ) -> None:
        self.every = cfg.curve_every
        self.seeds = [cfg.eval_seed + i for i in range(cfg.curve_episodes)]
        self.baseline_names = [b.strip() for b in cfg.baselines.split(",") if b.strip()]
        self.env_id = env_id
        self.make_eval_env = make_eval_env
        self.metadata = metadata
        self.clock = clock
        self.flag = flag
        self.points: list[dict[str, Any]] = list(resumed["points"]) if resumed else []
        self.baselines: dict[str, float] | None = dict(resumed["baselines"]) if resumed else None

    def due(self, timesteps: int, *, final: bool = False) -> bool:
        """Whether a point belongs at ``timesteps`` (``final``: the end of the run)."""
        if not self.points:
            return True
        last = int(self.points[-1]["timesteps"])
        if timesteps <= last:
            return False
        return final or timesteps - last >= self.every

    def record(self, upto: int | None = None) -> dict[str, Any]:
        """The ``learning_curve`` block (points at or before step ``upto`` when given)."""
        points = [p for p in self.points if upto is None or p["timesteps"] <= upto]
        return {
            "seeds": [self.seeds[0], self.seeds[-1]],
            "episodes": len(self.seeds),
            "points": [dict(p) for p in points],
            "baselines": dict(self.baselines or {}),
        }

    def add_point(self, model: Any) -> bool:
        """Evaluate ``model``'s policy now (and the baselines, the first time); record it.

        Returns ``False`` when a pending signal abandoned the evaluation (nothing recorded).
        The global random generators are left as they were.
        """
        from selenv.agents import make as make_agent
        from selenv.learned.rl.agent import SB3PolicyAgent

        timesteps = int(model.num_timesteps)
        state = _rng_state()
        try:
            baselines = self.baselines
            if baselines is None:
                agents = {name: make_agent(name, self.env_id) for name in self.baseline_names}
                baselines = self._mean_returns(agents)
                if baselines is None:
                    return False
            with tempfile.TemporaryDirectory(prefix="selenv-curve-") as tmp:
                scratch = Path(tmp) / "policy.zip"
                save_checkpoint(model, self.metadata(), scratch, exclude=_NOT_SAVED)
                policy = SB3PolicyAgent(scratch, env_id=self.env_id)
                result = self._mean_returns({"ppo": policy})
            if result is None:
                return False
        finally:
            _set_rng_state(state)
        self.baselines = baselines
        point = {
            "timesteps": timesteps,
            "mean_return": result["ppo"],
            "wall_seconds": round(self.clock(), 2),
        }
        self.points.append(point)
        self._log(model, point)
        return True

    def _mean_returns(self, agents: dict[str, Agent]) -> dict[str, float] | None:
        """Each agent's mean return over the held-out seeds; ``None`` on a pending signal."""
        out: dict[str, float] = {}
        for name, agent in agents.items():
            env = self.make_eval_env()
            result = AgentResult(name)
            returns: list[float] = []
            try:
                for seed in self.seeds:
                    if self.flag.signal is not None:
                        return None
                    ret, _objective = run_episode(env, agent, seed, result)
                    returns.append(ret)
            finally:
                env.close()
            out[name] = round(float(np.mean(returns)), 5)
        return out

    def _log(self, model: Any, point: dict[str, Any]) -> None:
        """``eval/mean_return`` and ``eval/normalized_score`` to TensorBoard, when it is on."""
        from stable_baselines3.common.logger import TensorBoardOutputFormat

        logger = getattr(model, "_logger", None)  # set by learn(); absent before any learn
        if logger is None:
            return
        score = normalized_score(point["mean_return"], self.baselines or {})
        for fmt in logger.output_formats:
            if isinstance(fmt, TensorBoardOutputFormat):
                step = point["timesteps"]
                fmt.writer.add_scalar("eval/mean_return", point["mean_return"], step)
                if score is not None:
                    fmt.writer.add_scalar("eval/normalized_score", score, step)
                fmt.writer.flush()


class CurveCallback(BaseCallback):
    """Adds the curve's points at the iteration boundaries (rollout starts) that are due.

    Placed before the checkpoint callback, so a periodic ``.last`` checkpoint written at the
    same boundary carries the point.
    """

    def __init__(self, recorder: CurveRecorder) -> None:
        super().__init__()
        self.recorder = recorder

    def _on_rollout_start(self) -> None:
        n = int(self.model.num_timesteps)
        if self.recorder.flag.signal is None and self.recorder.due(n):
            self.recorder.add_point(self.model)

    def _on_step(self) -> bool:
        return True
