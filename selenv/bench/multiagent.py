"""PettingZoo modules in the benchmark: resolving ``selenv.multiagent.*`` names, playing episodes.

A PettingZoo "env id" of the bench is the module name, e.g.
``selenv.multiagent.fim_selection_v0``; it must be one of :func:`multiagent_modules` (the
``*_v<N>`` modules of :mod:`selenv.multiagent` that expose ``parallel_env``). The bench builds
``module.parallel_env(invalid_action="raise", **env_kwargs)`` once per agent (strict, like the
Gymnasium bench; ``env_kwargs`` may override it) and plays every episode with a
:class:`~selenv.agents.multiagent.MultiAgentPolicy`:

* ``observations, infos = env.reset(seed=seed + e)`` and ``policy.reset(env, seed=seed + e)``;
* each step, one joint decision ``policy.act(observations, infos)`` (timed) gives the action of
  every live agent;
* the episode return is the sum over steps of the **team reward**, the mean over agents of the
  step's rewards (the rewards of both modules are shared, so this is the shared reward itself:
  the fusion centre's log-det gain, or ``-J``);
* the final objective is ``infos[agent]["objective"]`` after the last step (the same for every
  agent: the centre's ``f`` or the clustering cost ``J``).
"""

from __future__ import annotations

import importlib
import time
from types import ModuleType
from typing import Any

import numpy as np

from selenv.bench.results import AgentRefused, AgentResult, BenchError, EnvKwargsError
from selenv.families import FAMILIES

__all__ = [
    "MULTIAGENT_PACKAGE",
    "build_parallel_env",
    "is_multiagent_module",
    "load_multiagent_module",
    "multiagent_modules",
    "run_parallel_episode",
]

MULTIAGENT_PACKAGE = "selenv.multiagent"


def multiagent_modules() -> list[str]:
    """Full names of selenv's PettingZoo modules (``selenv.multiagent.<name>_v<N>``).

    The current modules (sorted), then the older versions kept to reproduce release 0.1.

    Read from the family records (:data:`selenv.families.FAMILIES`, ``multiagent_module``).
    """
    current = sorted(f.multiagent_module for f in FAMILIES if f.multiagent_module is not None)
    return current + sorted(f.multiagent_v0 for f in FAMILIES if f.multiagent_v0 is not None)


def is_multiagent_module(env_id: str) -> bool:
    """Whether ``env_id`` names one of :func:`multiagent_modules`."""
    return env_id in multiagent_modules()


def load_multiagent_module(env_id: str) -> ModuleType:
    """Import the PettingZoo module ``env_id``.

    Raises:
        BenchError: ``env_id`` is not one of :func:`multiagent_modules`, or has no
            ``parallel_env``.
    """
    known = multiagent_modules()
    if env_id not in known:
        raise BenchError(
            f"{env_id!r} is not a PettingZoo module of selenv; modules: {', '.join(known)}"
        )
    module = importlib.import_module(env_id)
    if not callable(getattr(module, "parallel_env", None)):
        raise BenchError(f"{env_id!r} has no parallel_env(): not a PettingZoo module of selenv")
    return module


def build_parallel_env(module: ModuleType, env_kwargs: dict[str, Any]) -> Any:
    """``module.parallel_env(invalid_action="raise", **env_kwargs)``.

    Raises:
        EnvKwargsError: the constructor rejected the keyword arguments.
    """
    try:
        return module.parallel_env(**{"invalid_action": "raise", **env_kwargs})
    except (TypeError, ValueError) as exc:
        raise EnvKwargsError(
            f"cannot build {module.__name__} with env_kwargs {env_kwargs}: {exc}"
        ) from exc


def run_parallel_episode(
    env: Any, agent: Any, seed: int, result: AgentResult
) -> tuple[float, float]:
    """Play one episode of a ``ParallelEnv`` with a multi-agent policy (module docstring).

    The decision time and count are added to ``result`` as they happen.

    Returns:
        The episode return (sum of the team reward) and the final ``objective``.

    Raises:
        AgentRefused: the policy raised ``ValueError`` in ``reset`` or ``act``.
        RuntimeError: the env does not report ``infos[agent]["objective"]``.
    """
    observations, infos = env.reset(seed=seed)
    try:
        agent.reset(env, seed=seed)
    except ValueError as exc:
        raise AgentRefused(str(exc)) from exc
    total = 0.0
    last: dict[str, Any] = next(iter(infos.values()), {})
    while env.agents:
        t0 = time.perf_counter()
        try:
            actions = agent.act(observations, infos)
        except ValueError as exc:
            raise AgentRefused(str(exc)) from exc
        result.decision_seconds += time.perf_counter() - t0
        result.decisions += 1
        observations, rewards, _terms, _truncs, infos = env.step(actions)
        total += float(np.mean([float(r) for r in rewards.values()]))  # shared team reward
        last = next(iter(infos.values()), last)
    if "objective" not in last:
        name = env.metadata.get("name", type(env).__name__)
        raise RuntimeError(f"{name} does not report infos[agent]['objective'] (see DESIGN.md)")
    if "cost_evaluations" in last:
        result.cost_evaluations = (result.cost_evaluations or 0) + int(last["cost_evaluations"])
    return total, float(last["objective"])
