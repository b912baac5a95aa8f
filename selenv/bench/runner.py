"""Run agents on one env over identical seeded episodes and collect their results.

``env_id`` is a Gymnasium id or a PettingZoo module of :mod:`selenv.multiagent` (e.g.
``selenv.multiagent.fim_selection_v0``, see :mod:`selenv.bench.multiagent`). Every agent gets
its own env (``gymnasium.make(env_id, **env_kwargs)`` or ``module.parallel_env(**env_kwargs)``,
built once per agent; selenv's own envs with ``invalid_action="raise"`` unless ``env_kwargs``
says otherwise, so an agent that picks a masked action fails loudly) and plays the same
episodes: episode ``e`` starts with ``env.reset(seed=seed + e)`` and
``agent.reset(env, seed=seed + e)``. The wall time of each ``agent.act`` call is measured
with :func:`time.perf_counter`; the episode return is the sum of the rewards (of the shared
team reward for a PettingZoo env) and the final objective is ``info["objective"]`` after the
last step. The statistics (paired differences against a baseline, CIs, normalised scores) are
derived from the returns by :class:`~selenv.bench.results.EnvBenchResult`.

An agent that raises :class:`ValueError` while being built, reset or asked to act (for
instance brute force's size guard) is recorded as skipped with the message and the run goes
on; any other exception propagates. Usage errors (unknown env, module or agent, an agent that
does not apply to the env, ``episodes < 1``, env kwargs the env rejects, a baseline that is
not among the agents or was skipped) raise :class:`BenchError`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
from tqdm import tqdm

from selenv.agents import AGENTS, Agent, agents_for, make, parse_spec
from selenv.bench.multiagent import (
    build_parallel_env,
    is_multiagent_module,
    load_multiagent_module,
    multiagent_modules,
    run_parallel_episode,
)
from selenv.bench.results import (
    AgentRefused,
    AgentResult,
    BenchError,
    EnvBenchResult,
    EnvKwargsError,
)
from selenv.envs.resolved import resolved_env_config
from selenv.families import ALL_ENV_IDS
from selenv.parallel import Executor, LocalExecutor
from selenv.threads import limit_threads

__all__ = [
    "AgentRefused",
    "AgentResult",
    "BenchError",
    "BlockResult",
    "EnvBenchResult",
    "EnvKwargsError",
    "EpisodeBlock",
    "check_env_id",
    "check_env_kwargs",
    "play_block",
    "run_bench",
    "run_episode",
]


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


def check_env_id(env_id: str) -> str:
    """``"gymnasium"`` for a registered Gymnasium id, ``"pettingzoo"`` for a selenv module.

    Raises:
        BenchError: neither; the message names ``env_id`` and lists the known ones.
    """
    if env_id in gym.registry:
        return "gymnasium"
    if is_multiagent_module(env_id):
        return "pettingzoo"
    kind = "PettingZoo module" if "." in env_id and "/" not in env_id else "env id"
    raise BenchError(
        f"unknown {kind} {env_id!r}; Gymnasium ids: {', '.join(ALL_ENV_IDS)}; "
        f"PettingZoo modules: {', '.join(multiagent_modules())}"
    )


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
    strict = {"invalid_action": "raise"} if env_id in ALL_ENV_IDS else {}
    try:
        return gym.make(env_id, **{**strict, **env_kwargs})
    except (TypeError, ValueError) as exc:
        raise EnvKwargsError(f"cannot build {env_id} with env_kwargs {env_kwargs}: {exc}") from exc


def _env_factory(
    env_id: str, kind: str, kwargs: dict[str, Any]
) -> tuple[Callable[[], Any], Callable[[Any, Any, int, AgentResult], tuple[float, float]]]:
    """How to build the env and play one episode of it, for either kind of env."""
    if kind == "pettingzoo":
        module = load_multiagent_module(env_id)
        return (lambda: build_parallel_env(module, kwargs)), run_parallel_episode
    return (lambda: _build_env(env_id, kwargs)), run_episode


@dataclass(frozen=True)
class EpisodeBlock:
    """One task of the bench: ``agent`` plays the episodes seeded ``seeds`` on a fresh env.

    Self-contained and picklable, so any executor can run it; its result depends only on its
    fields (the env and the agent are reset with each episode's seed), never on the worker.
    """

    env_id: str
    kind: str
    env_kwargs: dict[str, Any]
    agent: str
    seeds: tuple[int, ...]
    named: bool  # the agent was named explicitly: a ValueError while building it is a usage error
    #: BLAS and torch threads while the episodes play (``None``: leave the library's setting);
    #: small problems: one thread is fastest (:mod:`selenv.threads`)
    threads: tuple[int | None, int | None] = (1, 1)


@dataclass
class BlockResult:
    """What :func:`play_block` returns: the episodes played, or why the agent could not play."""

    result: AgentResult
    refused: str | None = None  # AgentRefused message (the agent is reported as skipped)
    build_error: str | None = None  # ValueError building a named agent (a usage error)


def play_block(
    block: EpisodeBlock, env: Any = None, on_episode: Callable[[int], object] | None = None
) -> BlockResult:
    """Play ``block``: build the env (unless given) and the agent, then each seeded episode.

    Args:
        block: the task.
        env: an already built env to use (closed afterwards); ``None`` builds one.
        on_episode: called with 1 after each episode (progress in this process).
    """
    build, play = _env_factory(block.env_id, block.kind, block.env_kwargs)
    env = build() if env is None else env
    result = AgentResult(block.agent)
    try:
        try:
            agent = make(block.agent, block.env_id)
        except ValueError as exc:
            if block.named:  # named explicitly: bad options or file
                return BlockResult(result, build_error=str(exc))
            return BlockResult(result, refused=str(exc) or "raised ValueError")
        with limit_threads(*block.threads):  # after make: the ppo agent imports torch
            for seed in block.seeds:
                ret, obj = play(env, agent, seed, result)
                result.returns.append(ret)
                result.final_objectives.append(obj)
                if on_episode is not None:
                    on_episode(1)
    except AgentRefused as exc:
        return BlockResult(result, refused=str(exc) or "raised ValueError")
    finally:
        env.close()
    return BlockResult(result)


def check_env_kwargs(env_id: str, env_kwargs: dict[str, Any]) -> None:
    """Build (and close) the bench's env once: bad keywords fail before anything runs.

    Raises:
        BenchError: unknown env or module.
        EnvKwargsError: the constructor rejected ``env_kwargs``.
    """
    build, _ = _env_factory(env_id, check_env_id(env_id), dict(env_kwargs))
    build().close()


def _blocks_per_agent(episodes: int, workers: int) -> int:
    """Blocks each agent's episodes are cut into: two per worker (at most one per episode).

    Per agent, not per bench: agents differ by orders of magnitude in cost (a ``rollout``
    reference against a random pick), so the expensive agent's episodes must spread over every
    worker by themselves; each block pays one env and agent construction.
    """
    return max(1, min(episodes, 2 * workers))


def _split(seeds: list[int], parts: int) -> list[tuple[int, ...]]:
    """``seeds`` in ``parts`` contiguous runs of near-equal length (in order)."""
    q, r = divmod(len(seeds), parts)
    out, start = [], 0
    for i in range(parts):
        stop = start + q + (i < r)
        out.append(tuple(seeds[start:stop]))
        start = stop
    return out


def _merge(name: str, parts: list[BlockResult]) -> AgentResult:
    """One agent's result from its blocks, in seed order; the first refusal skips the agent."""
    for part in parts:
        if part.build_error is not None:
            raise BenchError(f"cannot build agent {name!r}: {part.build_error}")
    for part in parts:
        if part.refused is not None:
            return AgentResult(name, skipped=part.refused)
    out = AgentResult(name)
    for part in parts:
        r = part.result
        out.returns += r.returns
        out.final_objectives += r.final_objectives
        out.decision_seconds += r.decision_seconds
        out.decisions += r.decisions
        if r.cost_evaluations is not None:
            out.cost_evaluations = (out.cost_evaluations or 0) + r.cost_evaluations
    return out


def run_bench(
    env_id: str,
    agent_names: list[str] | None = None,
    *,
    episodes: int = 10,
    seed: int = 0,
    env_kwargs: dict[str, Any] | None = None,
    progress: bool = True,
    skip_inapplicable: bool = False,
    baseline: str | None = None,
    executor: Executor | None = None,
    threads: tuple[int | None, int | None] = (1, 1),
) -> EnvBenchResult:
    """Run each agent on ``episodes`` seeded episodes of ``env_id``.

    Args:
        env_id: a registered Gymnasium id or a PettingZoo module of :mod:`selenv.multiagent`
            (``"selenv.multiagent.fim_selection_v0"``).
        agent_names: agent specs to run, in order; ``None`` runs every agent that applies.
        episodes: episodes per agent (episode ``e`` is seeded with ``seed + e``).
        seed: seed of the first episode.
        env_kwargs: keyword arguments of the env constructor.
        progress: show a tqdm bar over (agent, episode) on stderr.
        skip_inapplicable: report a named agent that does not apply to ``env_id`` as skipped
            instead of raising.
        baseline: the agent every other is compared with on the same seeds; ``None``: the one
            with the best mean return.
        executor: where the episodes run (:mod:`selenv.parallel`); ``None`` or a
            :class:`~selenv.parallel.LocalExecutor`: in this process, one env per agent. A
            pool or Ray executor gets each agent's episodes as contiguous blocks of seeds
            (:class:`EpisodeBlock`, a fresh env and agent per block); returns and objectives
            are identical to the local run, only the decision times differ.
        threads: ``(blas, torch)`` thread counts while episodes play, in every worker
            (:func:`selenv.threads.limit_threads`; ``None`` leaves a library's own setting).
            Decisions do not depend on them; decision times do.

    Returns:
        The per-agent results, in the order of ``agent_names``.

    Raises:
        BenchError: unknown env, module or agent, inapplicable agent (unless
            ``skip_inapplicable``), ``episodes < 1``, negative seed, env kwargs the env
            rejects, or a ``baseline`` that is not among the agents (checked before running)
            or was skipped (checked after).
    """
    kind = check_env_id(env_id)
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise BenchError(f"episodes must be an integer >= 1, got {episodes!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise BenchError(f"seed must be an integer >= 0, got {seed!r}")
    kwargs = dict(env_kwargs or {})
    names, inapplicable = _check_agents(env_id, agent_names, skip_inapplicable)
    out = EnvBenchResult(env_id, kwargs, seed, episodes, baseline=baseline, kind=kind)
    if baseline is not None and baseline not in (agent_names or names):
        raise BenchError(
            f"baseline {baseline!r} is not among the agents run on {env_id}: "
            f"{list(agent_names or names)}"
        )
    build, _ = _env_factory(env_id, kind, kwargs)
    first_env = build() if names else None  # bad kwargs fail before the bar
    if first_env is not None:
        out.env_config = resolved_env_config(first_env)
    seeds = [seed + e for e in range(episodes)]
    named = agent_names is not None
    if executor is None or isinstance(executor, LocalExecutor):
        bar = tqdm(total=len(names) * episodes, desc=env_id, unit="ep", disable=not progress)
        try:
            for name in names:
                bar.set_postfix_str(name)
                block = EpisodeBlock(env_id, kind, kwargs, name, tuple(seeds), named, threads)
                part = play_block(block, first_env, bar.update)
                first_env = None
                out.agents[name] = _merge(name, [part])
                bar.update(episodes - len(part.result.returns) if part.refused else 0)
        finally:
            bar.close()
    else:
        if first_env is not None:
            first_env.close()
        parts = _blocks_per_agent(episodes, executor.num_workers)
        blocks = [
            EpisodeBlock(env_id, kind, kwargs, name, chunk, named, threads)
            for name in names
            for chunk in _split(seeds, parts)
        ]
        done = executor.map(
            play_block,
            blocks,
            desc=env_id,
            unit="ep",
            weights=[len(b.seeds) for b in blocks],
            progress=progress,
        )
        for i, name in enumerate(names):
            out.agents[name] = _merge(name, done[i * parts : (i + 1) * parts])
    for name, why in inapplicable.items():
        out.agents[name] = AgentResult(name, skipped=why)
    out.agents = {n: out.agents[n] for n in (agent_names or names) if n in out.agents}
    out.check_baseline()
    return out
