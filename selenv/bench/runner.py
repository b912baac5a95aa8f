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
not among the agents or was skipped) raise :class:`BenchError`, and so does an ``episodes``
above ``max_episodes`` (:data:`MAX_EPISODES` by default), checked before anything runs.

Stopping early: an interruption (``KeyboardInterrupt``, a SIGTERM exception) or a dead worker
(:class:`~selenv.parallel.WorkerDiedError`) propagates out of :func:`run_bench`, but the
:class:`EnvBenchResult` given to ``collect`` keeps every episode that finished (the current
one is abandoned), with ``complete=False``; with a process pool the workers return the
episodes of their current blocks too (:func:`selenv.parallel.stoppable`).

Test hooks (environment variables read after each finished episode, for the fault-injection
tests; counted per process): ``SELENV_TEST_SIGNAL_AFTER_EPISODES=N`` sends
``SELENV_TEST_SIGNAL`` (``INT``, the default, or ``TERM``) to the bench's main process after
the N-th episode; ``SELENV_TEST_PAUSE_AFTER_EPISODES=N`` prints
``selenv: test hook: paused after N episodes (PID <pid>)`` on stderr after the N-th episode
and waits until the process is signalled.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
from tqdm import tqdm

from selenv.agents import AGENTS, Agent, agents_for, default_agents, make, parse_spec
from selenv.agents.base import unknown_agent_message
from selenv.bench.bounds import return_bounds
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
from selenv.parallel import (
    Executor,
    LocalExecutor,
    TaskStopped,
    WorkerDiedError,
    stop_requested,
    stoppable,
)
from selenv.parallel.executors import in_pool_worker
from selenv.suggest import with_suggestion
from selenv.threads import limit_threads

__all__ = [
    "EPISODE_RESULT_BYTES",
    "MAX_EPISODES",
    "AgentRefused",
    "AgentResult",
    "BenchError",
    "BlockResult",
    "EnvBenchResult",
    "EnvKwargsError",
    "EpisodeBlock",
    "check_env_id",
    "check_env_kwargs",
    "episodes_problem",
    "play_block",
    "run_bench",
    "run_episode",
]


#: default ceiling on the episodes per agent (``selenv bench --max-episodes`` raises it)
MAX_EPISODES = 100_000
#: estimated memory of one finished episode's results (return, objective and seed as Python
#: floats and ints in lists, the seed list, the bootstrap's share), for the memory estimate
EPISODE_RESULT_BYTES = 200


def _memory_bytes() -> int | None:
    """Physical memory of this machine (``None`` if unknown)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def _gib(n: float) -> str:
    return f"{n / 2**30:,.1f} GiB" if n >= 2**30 else f"{n / 2**20:,.1f} MiB"


def episodes_problem(
    episodes: int,
    max_episodes: int = MAX_EPISODES,
    *,
    runs: int = 1,
    option: str = "--episodes",
    raise_option: str = "--max-episodes",
) -> str | None:
    """Why ``episodes`` per agent is too much work (``None`` if it is fine), in O(1).

    Refused: more than ``max_episodes``, or results that would need more than half of this
    machine's memory (``runs`` = agents x envs, ``EPISODE_RESULT_BYTES`` per episode).
    """
    estimate = float(episodes) * max(1, runs) * EPISODE_RESULT_BYTES
    if episodes > max_episodes:
        return (
            f"{option} {episodes:,} exceeds the ceiling of {max_episodes:,} episodes per agent "
            f"({max(1, runs) * episodes:,} episodes to play, about {_gib(estimate)} of results); "
            f"raise it with {raise_option} N if you mean it"
        )
    memory = _memory_bytes()
    if memory is not None and estimate > memory / 2:
        return (
            f"{option} {episodes:,}: the results of {max(1, runs) * episodes:,} episodes need "
            f"about {_gib(estimate)}, more than half of this machine's {_gib(memory)}"
        )
    return None


_test_episodes = 0  # episodes finished in this process (test hooks)


def _after_episode() -> None:
    """The test hooks of the module docstring (no-ops unless their variables are set)."""
    global _test_episodes
    _test_episodes += 1
    after = os.environ.get("SELENV_TEST_SIGNAL_AFTER_EPISODES")
    if after and _test_episodes == int(after):
        name = os.environ.get("SELENV_TEST_SIGNAL", "INT").upper().removeprefix("SIG")
        os.kill(os.getppid() if in_pool_worker() else os.getpid(), signal.Signals[f"SIG{name}"])
    pause = os.environ.get("SELENV_TEST_PAUSE_AFTER_EPISODES")
    if pause and _test_episodes == int(pause):
        # one write of the whole line (atomic on a pipe): print() writes the text and the
        # newline separately, so two workers pausing together could interleave their lines
        sys.stderr.write(f"selenv: test hook: paused after {pause} episodes (PID {os.getpid()})\n")
        sys.stderr.flush()
        while True:
            time.sleep(0.05)


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
    known = [*gym.registry, *multiagent_modules()]
    listing = (
        f"Gymnasium ids: {', '.join(ALL_ENV_IDS)}; "
        f"PettingZoo modules: {', '.join(multiagent_modules())}"
    )
    raise BenchError(with_suggestion(f"unknown {kind} {env_id!r}", env_id, known, listing))


def _check_agents(
    env_id: str, agent_names: list[str] | None, skip_inapplicable: bool
) -> tuple[list[str], dict[str, str]]:
    """Return the agents to run and the inapplicable ones (name -> reason) to report."""
    if agent_names is None:
        names = default_agents(env_id)
        if not names:
            raise BenchError(f"no registered agent applies to {env_id!r}")
        return names, {}
    names = list(dict.fromkeys(agent_names))  # drop duplicates, keep order
    if not names:
        raise BenchError("no agent given")
    for n in names:
        try:
            parse_spec(n)
        except ValueError as exc:
            raise BenchError(str(exc)) from None
    unknown = [n for n in names if parse_spec(n)[0] not in AGENTS]
    if unknown:
        raise BenchError(unknown_agent_message([parse_spec(n)[0] for n in unknown], [env_id]))
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
        # CPython's wording for the keyword a signature does not take (not the user's keywords)
        missing = "keyword argument 'invalid_action'" in str(exc)
        if strict and "invalid_action" not in env_kwargs and missing:
            raise BenchError(  # not the user's keywords: a family's env must take it
                f"cannot build {env_id}: selenv bench plays a family's env with "
                f"invalid_action='raise' (a masked action fails loudly) and its env does not "
                f"take that keyword ({exc}); see the guide 'adding an env family'"
            ) from exc
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
    stopped: bool = False  # a pool worker was asked to stop: ``result`` has the episodes done


def _play_one(
    play: Callable[[Any, Any, int, AgentResult], tuple[float, float]],
    env: Any,
    agent: Any,
    seed: int,
    result: AgentResult,
) -> None:
    """Play one episode into ``result``; an abandoned episode leaves ``result`` as it was."""
    saved = (result.decision_seconds, result.decisions, result.cost_evaluations)
    try:
        ret, obj = play(env, agent, seed, result)
    except BaseException:
        result.decision_seconds, result.decisions, result.cost_evaluations = saved
        raise
    result.returns.append(ret)
    result.final_objectives.append(obj)
    result.seeds.append(seed)


def _trim(result: AgentResult) -> AgentResult:
    """Make the per-episode lists equally long (an interruption may fall between appends)."""
    n = min(len(result.returns), len(result.final_objectives), len(result.seeds))
    del result.returns[n:], result.final_objectives[n:], result.seeds[n:]
    return result


def play_block(
    block: EpisodeBlock,
    env: Any = None,
    on_episode: Callable[[int], object] | None = None,
    into: AgentResult | None = None,
) -> BlockResult:
    """Play ``block``: build the env (unless given) and the agent, then each seeded episode.

    In a pool worker asked to stop (:func:`selenv.parallel.stoppable`), the current episode is
    abandoned and the block returns the episodes it finished with ``stopped=True``.

    Args:
        block: the task.
        env: an already built env to use (closed afterwards); ``None`` builds one.
        on_episode: called with 1 after each episode (progress in this process).
        into: the result to add the episodes to as they finish (kept by the caller if the
            block is interrupted); ``None``: a new one.
    """
    result = AgentResult(block.agent) if into is None else into
    build, play = _env_factory(block.env_id, block.kind, block.env_kwargs)
    if stop_requested():
        if env is not None:
            env.close()
        return BlockResult(result, stopped=True)
    env = build() if env is None else env
    try:
        try:
            agent = make(block.agent, block.env_id)
        except ValueError as exc:
            if block.named:  # named explicitly: bad options or file
                return BlockResult(result, build_error=str(exc))
            return BlockResult(result, refused=str(exc) or "raised ValueError")
        # after make: the ppo agent imports torch
        with limit_threads(*block.threads), stoppable():
            for seed in block.seeds:
                if stop_requested():
                    return BlockResult(_trim(result), stopped=True)
                _play_one(play, env, agent, seed, result)
                if on_episode is not None:
                    on_episode(1)
                _after_episode()
    except AgentRefused as exc:
        return BlockResult(result, refused=str(exc) or "raised ValueError")
    except TaskStopped:
        return BlockResult(_trim(result), stopped=True)
    finally:
        env.close()
    return BlockResult(result)


def check_env_kwargs(env_id: str, env_kwargs: dict[str, Any]) -> None:
    """Build (and close) the bench's env once: bad keywords fail before anything runs.

    Raises:
        BenchError: unknown env or module, or a family's env without ``invalid_action``.
        EnvKwargsError: the constructor rejected ``env_kwargs``.
    """
    build, _ = _env_factory(env_id, check_env_id(env_id), dict(env_kwargs))
    build().close()


#: most episodes in one Ray block: an interrupted Ray run loses the episodes of the blocks in
#: flight (a pool's workers hand theirs back), so at most this many per worker
RAY_BLOCK_EPISODES = 50


def _blocks_per_agent(episodes: int, workers: int, max_block: int | None = None) -> int:
    """Blocks each agent's episodes are cut into: two per worker (at most one per episode).

    Per agent, not per bench: agents differ by orders of magnitude in cost (a ``rollout``
    reference against a random pick), so the expensive agent's episodes must spread over every
    worker by themselves; each block pays one env and agent construction. With ``max_block``
    more blocks are made so that none has more than ``max_block`` episodes.
    """
    parts = max(1, min(episodes, 2 * workers))
    if max_block is not None:
        parts = max(parts, -(-episodes // max_block))
    return parts


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
        out.seeds += r.seeds
        out.decision_seconds += r.decision_seconds
        out.decisions += r.decisions
        if r.cost_evaluations is not None:
            out.cost_evaluations = (out.cost_evaluations or 0) + r.cost_evaluations
    return out


def _merge_partial(name: str, parts: list[BlockResult]) -> AgentResult:
    """:func:`_merge` of the blocks that finished before a run stopped (never raises)."""
    for part in parts:
        if part.build_error is not None:
            return AgentResult(name, skipped=f"cannot build agent {name!r}: {part.build_error}")
    return _merge(name, [BlockResult(_trim(p.result), p.refused) for p in parts])


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
    max_episodes: int = MAX_EPISODES,
    collect: list[EnvBenchResult] | None = None,
    bounds: bool = True,
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
        max_episodes: ceiling on ``episodes`` (:func:`episodes_problem`), checked first.
        collect: a list the result is appended to before any episode runs; if the run is
            interrupted or a worker dies, the result there holds the finished episodes and
            ``complete=False`` (module docstring) while the exception propagates.
        bounds: after the episodes, compute the family's certified bound on each seed's
            return (``FamilySpec.return_bound``, :mod:`selenv.bench.bounds`) so every agent
            gets its gap to it; ``False`` skips it.

    Returns:
        The per-agent results, in the order of ``agent_names``.

    Raises:
        BenchError: unknown env, module or agent, inapplicable agent (unless
            ``skip_inapplicable``), ``episodes < 1``, negative seed, env kwargs the env
            rejects, or a ``baseline`` that is not among the agents (checked before running)
            or was skipped (checked after); ``episodes`` above ``max_episodes``.
        WorkerDiedError: a pool or Ray worker died (or a pool worker was stopped).
    """
    kind = check_env_id(env_id)
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise BenchError(f"episodes must be an integer >= 1, got {episodes!r}")
    why = episodes_problem(episodes, max_episodes, option="episodes", raise_option="max_episodes=")
    if why is not None:
        raise BenchError(why)
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
    if collect is not None:
        collect.append(out)
    try:
        if executor is None or isinstance(executor, LocalExecutor):
            _run_local(out, names, seeds, named, threads, first_env, progress)
        else:
            if first_env is not None:
                first_env.close()
            _run_pooled(out, names, seeds, named, threads, executor, progress)
    except BaseException:
        out.complete = False
        for name in names:  # an agent that had not started: 0 episodes
            out.agents.setdefault(name, AgentResult(name))
        for name, why in inapplicable.items():
            out.agents[name] = AgentResult(name, skipped=why)
        out.agents = {n: out.agents[n] for n in (agent_names or names) if n in out.agents}
        raise
    for name, why in inapplicable.items():
        out.agents[name] = AgentResult(name, skipped=why)
    out.agents = {n: out.agents[n] for n in (agent_names or names) if n in out.agents}
    out.check_baseline()
    if bounds and kind == "gymnasium" and names:
        got = return_bounds(env_id, kwargs, seeds)
        if got is not None:
            out.bound_kind, out.bound_method, out.bounds = got
    return out


def _run_local(
    out: EnvBenchResult,
    names: list[str],
    seeds: list[int],
    named: bool,
    threads: tuple[int | None, int | None],
    first_env: Any,
    progress: bool,
) -> None:
    """Play every agent's episodes in this process, filling ``out`` as episodes finish."""
    episodes = len(seeds)
    bar = tqdm(total=len(names) * episodes, desc=out.env_id, unit="ep", disable=not progress)
    try:
        for name in names:
            bar.set_postfix_str(name)
            block = EpisodeBlock(
                out.env_id, out.kind, out.env_kwargs, name, tuple(seeds), named, threads
            )
            into = AgentResult(name)
            out.agents[name] = into  # the finished episodes stay if the run is interrupted
            try:
                part = play_block(block, first_env, bar.update, into=into)
            except BaseException:
                _trim(into)
                raise
            finally:
                first_env = None
            out.agents[name] = _merge(name, [part])
            bar.update(episodes - len(part.result.returns) if part.refused else 0)
    finally:
        bar.close()
        if first_env is not None:
            first_env.close()


def _run_pooled(
    out: EnvBenchResult,
    names: list[str],
    seeds: list[int],
    named: bool,
    threads: tuple[int | None, int | None],
    executor: Executor,
    progress: bool,
) -> None:
    """Play the agents' episodes as blocks on ``executor``, filling ``out`` with what finished."""
    cap = RAY_BLOCK_EPISODES if executor.name == "ray" else None
    parts = _blocks_per_agent(len(seeds), executor.num_workers, cap)
    blocks = [
        EpisodeBlock(out.env_id, out.kind, out.env_kwargs, name, chunk, named, threads)
        for name in names
        for chunk in _split(seeds, parts)
    ]
    finished: dict[int, BlockResult] = {}
    try:
        executor.map(
            play_block,
            blocks,
            desc=out.env_id,
            unit="ep",
            weights=[len(b.seeds) for b in blocks],
            progress=progress,
            on_result=finished.__setitem__,
        )
    except BaseException:
        for i, name in enumerate(names):
            got = [finished[j] for j in range(i * parts, (i + 1) * parts) if j in finished]
            out.agents[name] = _merge_partial(name, got)
        raise
    stopped = any(b.stopped for b in finished.values())
    for i, name in enumerate(names):
        got = [finished[j] for j in range(i * parts, (i + 1) * parts)]
        out.agents[name] = _merge_partial(name, got) if stopped else _merge(name, got)
    if stopped:
        raise WorkerDiedError(
            "a process-pool worker was stopped (SIGINT or SIGUSR1) before finishing its episodes"
        )
