"""Run agents on one env over identical seeded episodes and collect their results.

Every agent gets its own env (``gymnasium.make(env_id, **env_kwargs)``, built once per agent;
selenv's own envs with ``invalid_action="raise"`` unless ``env_kwargs`` says otherwise, so an
agent that picks a masked action fails loudly) and plays the same episodes: episode ``e``
starts with ``env.reset(seed=seed + e)`` and ``agent.reset(env, seed=seed + e)``. The wall
time of each ``agent.act`` call is measured with :func:`time.perf_counter`; the episode return
is the sum of the rewards and the final objective is ``info["objective"]`` after the last step.

An agent that raises :class:`ValueError` while being built, reset or asked to act (for
instance brute force's size guard) is recorded as skipped with the message and the run goes
on; any other exception propagates. Usage errors (unknown env or agent, an agent that does not
apply to the env, ``episodes < 1``, env kwargs the env rejects) raise :class:`BenchError`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any

import gymnasium as gym
import numpy as np
from tqdm import tqdm

import selenv
from selenv.agents import AGENTS, Agent, agents_for, make, parse_spec
from selenv.envs import ENV_IDS

__all__ = [
    "AgentRefused",
    "AgentResult",
    "BenchError",
    "EnvBenchResult",
    "EnvKwargsError",
    "run_bench",
    "run_episode",
]


class BenchError(ValueError):
    """A usage error of the benchmark (bad env id, agent name, episode count or env kwargs)."""


class EnvKwargsError(BenchError):
    """``gymnasium.make(env_id, **env_kwargs)`` rejected the keyword arguments."""


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


def _std(values: list[float]) -> float:
    return float(np.std(values)) if values else float("nan")


@dataclass
class AgentResult:
    """What one agent achieved over the episodes of one env.

    Attributes:
        name: registry name of the agent.
        returns: undiscounted return (sum of rewards) of each episode.
        final_objectives: ``info["objective"]`` after the last step of each episode.
        decision_seconds: total wall time spent in ``agent.act``.
        decisions: number of ``agent.act`` calls.
        cost_evaluations: objective evaluations the agent's searches made, summed over the
            episodes, for envs that count them (``info["cost_evaluations"]`` after the last
            step, e.g. Algorithm 1 calls of ``ReceiverClustering-v0``); ``None`` otherwise.
        skipped: why the agent was not run (``None`` when it ran).
    """

    name: str
    returns: list[float] = field(default_factory=list)
    final_objectives: list[float] = field(default_factory=list)
    decision_seconds: float = 0.0
    decisions: int = 0
    cost_evaluations: int | None = None
    skipped: str | None = None

    @property
    def mean_return(self) -> float:
        """Mean episode return (NaN if skipped)."""
        return _mean(self.returns)

    @property
    def std_return(self) -> float:
        """Population standard deviation of the episode returns."""
        return _std(self.returns)

    @property
    def mean_final_objective(self) -> float:
        """Mean final objective (NaN if skipped)."""
        return _mean(self.final_objectives)

    @property
    def std_final_objective(self) -> float:
        """Population standard deviation of the final objectives."""
        return _std(self.final_objectives)

    @property
    def decision_seconds_mean(self) -> float:
        """Mean wall time of one ``agent.act`` call, over every decision of every episode."""
        return self.decision_seconds / self.decisions if self.decisions else float("nan")

    @property
    def cost_evaluations_per_decision(self) -> float | None:
        """Mean objective evaluations per decision (``None`` if the env does not count them)."""
        if self.cost_evaluations is None or not self.decisions:
            return None
        return self.cost_evaluations / self.decisions

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict: the contract keys, or ``{"skipped": reason}``."""
        if self.skipped is not None:
            return {"skipped": self.skipped}
        extra: dict[str, Any] = {}
        if self.cost_evaluations is not None:
            extra["cost_evaluations_per_decision"] = self.cost_evaluations_per_decision
        return {
            "returns": [float(r) for r in self.returns],
            "mean_return": self.mean_return,
            "std_return": self.std_return,
            "final_objectives": [float(f) for f in self.final_objectives],
            "mean_final_objective": self.mean_final_objective,
            "std_final_objective": self.std_final_objective,
            "decision_seconds_mean": self.decision_seconds_mean,
            "decisions": self.decisions,
            **extra,
        }


@dataclass
class EnvBenchResult:
    """The results of every agent on one env, with the settings that reproduce them.

    Attributes:
        env_id: Gymnasium id.
        env_kwargs: keyword arguments given to ``gymnasium.make``.
        seed: seed of episode 0 (episode ``e`` uses ``seed + e``).
        episodes: number of episodes per agent.
        agents: agent name -> result, in the order the agents were run.
        timestamp: UTC time the run started (ISO 8601).
    """

    env_id: str
    env_kwargs: dict[str, Any]
    seed: int
    episodes: int
    agents: dict[str, AgentResult] = field(default_factory=dict)
    timestamp: str = field(
        default_factory=lambda: datetime.now(timezone.utc).isoformat(timespec="seconds")
    )

    @property
    def best_return(self) -> float | None:
        """Largest mean return among the agents that ran (``None`` if none ran)."""
        ran = [r.mean_return for r in self.agents.values() if r.skipped is None]
        return max(ran) if ran else None

    def gap_percent(self, name: str) -> float | None:
        """Shortfall of agent ``name``'s mean return from the best one, in % of ``|best|``.

        Returns are compared (not objectives) because a return is always to be maximised,
        whereas an objective may be a log det (maximised) or an MSE (minimised). ``None`` for a
        skipped agent; when the best return is 0 the absolute shortfall times 100 is returned.
        """
        res, best = self.agents[name], self.best_return
        if res.skipped is not None or best is None:
            return None
        return 100.0 * (best - res.mean_return) / (abs(best) or 1.0)

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict following the contract of ``DESIGN.md`` section 2."""
        agents = {}
        for name, res in self.agents.items():
            agents[name] = res.to_json()
            if res.skipped is None:
                agents[name]["gap_to_best_percent"] = self.gap_percent(name)
        return {
            "env_id": self.env_id,
            "env_kwargs": self.env_kwargs,
            "seed": self.seed,
            "episodes": self.episodes,
            "agents": agents,
            "selenv_version": selenv.__version__,
            "timestamp": self.timestamp,
        }


class AgentRefused(Exception):
    """An agent raised ``ValueError`` in ``reset`` or ``act``: it refuses this env or episode.

    Wrapping it keeps a ``ValueError`` raised by the env itself (e.g. a masked action, a bug
    of the agent that sent it) apart: that one propagates.
    """


def run_episode(
    env: gym.Env[Any, Any], agent: Agent, seed: int, result: AgentResult
) -> tuple[float, float]:
    """Play one episode with ``agent`` from ``env.reset(seed=seed)``; time its decisions.

    The decision time and count are added to ``result`` as they happen.

    Returns:
        The episode return and ``info["objective"]`` after the last step.

    Raises:
        AgentRefused: the agent raised ``ValueError`` in ``reset`` or ``act``.
        RuntimeError: the env does not report ``info["objective"]``.
    """
    obs, info = env.reset(seed=seed)
    try:
        agent.reset(env, seed=seed)
    except ValueError as exc:
        raise AgentRefused(str(exc)) from exc
    total, done = 0.0, False
    while not done:
        t0 = time.perf_counter()
        try:
            action = agent.act(obs, info)
        except ValueError as exc:
            raise AgentRefused(str(exc)) from exc
        result.decision_seconds += time.perf_counter() - t0
        result.decisions += 1
        obs, reward, terminated, truncated, info = env.step(action)
        total += float(reward)
        done = bool(terminated or truncated)
    if "objective" not in info:
        env_id = env.spec.id if env.spec is not None else type(env.unwrapped).__name__
        raise RuntimeError(f"{env_id} does not report info['objective'] (see DESIGN.md)")
    if "cost_evaluations" in info:
        result.cost_evaluations = (result.cost_evaluations or 0) + int(info["cost_evaluations"])
    return total, float(info["objective"])


def _check_agents(
    env_id: str, agent_names: list[str] | None, skip_inapplicable: bool
) -> tuple[list[str], dict[str, str]]:
    """Return the agents to run and the inapplicable ones (name -> reason) to report."""
    if agent_names is None:
        names = agents_for(env_id)
        if not names:
            raise BenchError(f"no registered agent applies to {env_id!r}")
        return names, {}
    names = list(dict.fromkeys(agent_names))  # drop duplicates, keep order
    if not names:
        raise BenchError("no agent given")
    unknown = [n for n in names if parse_spec(n)[0] not in AGENTS]
    if unknown:
        raise BenchError(f"unknown agent(s) {unknown}; known agents: {sorted(AGENTS)}")
    inapplicable = {
        n: f"does not apply to {env_id} (applies to {', '.join(sorted(AGENTS[parse_spec(n)[0]]))})"
        for n in names
        if env_id not in AGENTS[parse_spec(n)[0]]
    }
    if inapplicable and not skip_inapplicable:
        bad = ", ".join(f"{n!r} {why}" for n, why in inapplicable.items())
        raise BenchError(f"agent {bad}; agents for {env_id}: {agents_for(env_id)}")
    return [n for n in names if n not in inapplicable], inapplicable


def _build_env(env_id: str, env_kwargs: dict[str, Any]) -> gym.Env[Any, Any]:
    """The bench's env: selenv's with ``invalid_action="raise"`` unless given otherwise."""
    strict = {"invalid_action": "raise"} if env_id in ENV_IDS else {}
    try:
        return gym.make(env_id, **{**strict, **env_kwargs})
    except (TypeError, ValueError) as exc:
        raise EnvKwargsError(f"cannot build {env_id} with env_kwargs {env_kwargs}: {exc}") from exc


def run_bench(
    env_id: str,
    agent_names: list[str] | None = None,
    *,
    episodes: int = 10,
    seed: int = 0,
    env_kwargs: dict[str, Any] | None = None,
    progress: bool = True,
    skip_inapplicable: bool = False,
) -> EnvBenchResult:
    """Run each agent on ``episodes`` seeded episodes of ``env_id``.

    Args:
        env_id: a registered Gymnasium id.
        agent_names: agents to run, in order; ``None`` runs every agent that applies.
        episodes: episodes per agent (episode ``e`` is seeded with ``seed + e``).
        seed: seed of the first episode.
        env_kwargs: keyword arguments of ``gymnasium.make``.
        progress: show a tqdm bar over (agent, episode) on stderr.
        skip_inapplicable: report a named agent that does not apply to ``env_id`` as skipped
            instead of raising.

    Returns:
        The per-agent results, in the order of ``agent_names``.

    Raises:
        BenchError: unknown env or agent, inapplicable agent (unless ``skip_inapplicable``),
            ``episodes < 1``, negative seed, or env kwargs the env rejects.
    """
    if env_id not in gym.registry:
        raise BenchError(f"unknown env id {env_id!r}; known ids: {', '.join(ENV_IDS)}")
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise BenchError(f"episodes must be an integer >= 1, got {episodes!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise BenchError(f"seed must be an integer >= 0, got {seed!r}")
    kwargs = dict(env_kwargs or {})
    names, inapplicable = _check_agents(env_id, agent_names, skip_inapplicable)
    out = EnvBenchResult(env_id, kwargs, seed, episodes)
    first_env = _build_env(env_id, kwargs) if names else None  # bad kwargs fail before the bar
    bar = tqdm(total=len(names) * episodes, desc=env_id, unit="ep", disable=not progress)
    try:
        for name in names:
            result = out.agents[name] = AgentResult(name)
            bar.set_postfix_str(name)
            env, first_env = first_env or _build_env(env_id, kwargs), None
            done = 0
            try:
                try:
                    agent = make(name, env_id)
                except ValueError as exc:
                    raise AgentRefused(str(exc)) from exc
                for e in range(episodes):
                    ret, obj = run_episode(env, agent, seed + e, result)
                    result.returns.append(ret)
                    result.final_objectives.append(obj)
                    done += 1
                    bar.update(1)
            except AgentRefused as exc:
                out.agents[name] = AgentResult(name, skipped=str(exc) or "raised ValueError")
                bar.update(episodes - done)
            finally:
                env.close()
    finally:
        bar.close()
    for name, why in inapplicable.items():
        out.agents[name] = AgentResult(name, skipped=why)
    out.agents = {n: out.agents[n] for n in (agent_names or names)}
    return out
