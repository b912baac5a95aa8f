"""The agent protocol shared by classic heuristics and learned policies, and the agent registry.

An agent acts in a Gymnasium env exactly like a policy would::

    agent = selenv.agents.make("greedy", "selenv/FIMSelection-v1")
    obs, info = env.reset(seed=0)
    agent.reset(env, seed=0)
    while not done:
        obs, r, terminated, truncated, info = env.step(agent.act(obs, info))

Heuristics may read the scenario's oracle view (``env.unwrapped``) in :meth:`Agent.reset` or
:meth:`Agent.act`; learned policies use only ``obs`` and ``info``. Agents never re-implement
the objective: they call the solvers and the scenario.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import inspect
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from selenv._signals import hold_signals
from selenv.families import ADAPTED, version_ids
from selenv.suggest import with_suggestion

__all__ = [
    "AGENTS",
    "Agent",
    "AgentSpec",
    "PlanAgent",
    "agents_for",
    "default_agents",
    "make",
    "parse_spec",
    "register_adapted",
    "register_agent",
    "unknown_agent_message",
]


class Agent(ABC):
    """Base class of every agent: ``reset`` once per episode, then ``act`` each step."""

    #: registry name (as used by ``selenv bench --agents``)
    name: ClassVar[str] = "agent"

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:
        """Start an episode in ``env`` (already reset); ``seed`` seeds any internal randomness."""
        self.env = env
        self.rng = np.random.default_rng(seed)

    @abstractmethod
    def act(self, obs: Any, info: dict[str, Any]) -> Any:
        """Return the action for the current observation."""


class PlanAgent(Agent):
    """An agent that computes a plan (a sequence of actions) and then plays it.

    Subclasses implement :meth:`plan`, which is called lazily at the first :meth:`act` of an
    episode (so the plan's compute time is counted as decision time) and again whenever the
    plan runs out before the episode ends.
    """

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:  # noqa: D102
        super().reset(env, seed)
        self._plan: list[Any] = []

    @abstractmethod
    def plan(self, obs: Any, info: dict[str, Any]) -> list[Any]:
        """Return the actions to play from the current state on."""

    def act(self, obs: Any, info: dict[str, Any]) -> Any:  # noqa: D102
        if not self._plan:
            self._plan = list(self.plan(obs, info))
            if not self._plan:
                raise RuntimeError(f"agent {self.name!r} produced an empty plan")
        return self._plan.pop(0)


@dataclass(frozen=True)
class AgentSpec:
    """Registry entry: ``factory(**kwargs)`` builds the agent for the env ids in ``env_ids``.

    ``factory`` may be a callable or an ``"module:attr"`` string imported lazily (so that the
    learned agents living above this layer can register without an upward import).
    """

    name: str
    env_ids: tuple[str, ...]
    factory: Callable[..., Agent] | str
    description: str = ""
    kwargs: dict[str, Any] = field(default_factory=dict)
    #: apply to every version of each env id's family (``-v0``, ``-v1``, ...); ``False`` for
    #: agents tied to one version, e.g. a policy trained on it
    all_versions: bool = True
    #: a trained policy (it loads weights: a shipped checkpoint or a ``checkpoint=`` file),
    #: not a heuristic or a search; ``scripts/bench_tables.py`` picks each env's best learned
    #: agent by it
    learned: bool = False
    #: among the agents ``selenv bench`` runs when ``--agents`` is not given (``False``: a
    #: deprecated name, a retired policy, or the record ``learned`` already plays)
    default: bool = True
    #: an old name kept for one release (it warns when built; ``selenv list`` says what
    #: replaces it; the env pages leave it out)
    deprecated: bool = False

    def build(self, **kwargs: Any) -> Agent:
        """Instantiate the agent.

        Raises:
            ValueError: an option the agent does not have (the factory's ``TypeError`` for an
                unexpected keyword, named after the agent), or a bad option value.
        """
        fac = self.factory
        if isinstance(fac, str):
            module, attr = fac.split(":")
            fac = getattr(importlib.import_module(module), attr)
        options = {**self.kwargs, **kwargs}
        _check_options(self.name, fac, options)
        try:
            return fac(**options)
        except TypeError as exc:  # a factory that forwards **kwargs (CPython's wording)
            if "unexpected keyword argument" in str(exc):
                raise ValueError(f"agent {self.name!r} has no such option: {exc}") from None
            raise


def _check_options(name: str, factory: Callable[..., Agent], options: dict[str, Any]) -> None:
    """``ValueError`` naming the options ``factory``'s signature does not take (if it is fixed)."""
    try:
        params = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):  # no signature to check against: the call decides
        return
    if any(p.kind is p.VAR_KEYWORD for p in params):
        return
    accepted = [p.name for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        message = f"agent {name!r} has no option(s) {unknown}"
        listing = f"its options: {', '.join(accepted) or 'none'}"
        raise ValueError(with_suggestion(message, unknown, accepted, listing))


#: name -> env id -> spec
AGENTS: dict[str, dict[str, AgentSpec]] = {}
#: env id -> agent names in the order they were registered for it
_ORDER: dict[str, list[str]] = {}


def register_agent(spec: AgentSpec) -> None:
    """Register ``spec`` under its name for each of its env ids (re-registering replaces).

    With ``spec.all_versions`` an id stands for every registered version of its family
    (:func:`~selenv.families.version_ids`) whose action space it shares: a version with
    another action space (:data:`~selenv.families.ADAPTED`) gets the agent through
    :func:`register_adapted`, unless ``spec.env_ids`` names it.
    """
    ids = spec.env_ids
    if spec.all_versions:
        ids = tuple(
            dict.fromkeys(
                v for env_id in ids for v in version_ids(env_id) if v == env_id or v not in ADAPTED
            )
        )
    for env_id in ids:
        AGENTS.setdefault(spec.name, {})[env_id] = spec
        names = _ORDER.setdefault(env_id, [])
        if spec.name not in names:
            names.append(spec.name)


def register_adapted() -> None:
    """Register every agent of an adapted version's source on it, through the adapter.

    For each ``target -> (source, adapter)`` of :data:`~selenv.families.ADAPTED` (e.g.
    ``ReceiverClustering-v2 -> (-v1, SequentialAgent)``), an agent of ``source`` not
    registered on ``target`` itself is registered there as ``adapter(agent)``, with its
    description and flags; it plays the same episodes as on ``source``.
    """
    for target, (source, adapter) in ADAPTED.items():
        for name in agents_for(source):
            if target in AGENTS[name]:
                continue
            spec = AGENTS[name][source]
            factory = functools.partial(_build_adapted, spec, adapter)
            register_agent(
                dataclasses.replace(
                    spec, env_ids=(target,), factory=factory, kwargs={}, all_versions=False
                )
            )


def _build_adapted(spec: AgentSpec, adapter: str, **options: Any) -> Agent:
    module, _, attr = adapter.partition(":")
    wrap: Callable[[Agent], Agent] = getattr(importlib.import_module(module), attr)
    return wrap(spec.build(**options))


def agents_for(env_id: str) -> list[str]:
    """Names of the agents that apply to ``env_id``, in registration order."""
    ordered = [name for name in _ORDER.get(env_id, []) if env_id in AGENTS.get(name, {})]
    others = [n for n, by_env in AGENTS.items() if env_id in by_env and n not in ordered]
    return ordered + others


def default_agents(env_id: str) -> list[str]:
    """The agents ``selenv bench`` runs on ``env_id`` by default (:attr:`AgentSpec.default`)."""
    return [n for n in agents_for(env_id) if AGENTS[n][env_id].default]


def unknown_agent_message(names: str | list[str], env_ids: list[str] | tuple[str, ...]) -> str:
    """The one-line message for agent name(s) ``names`` that are not registered, for ``env_ids``.

    Close names are suggested among the agents that apply to those envs, which the message
    then lists (every registered agent when none applies, e.g. an env of no selenv family)::

        unknown agent 'gredy' for selenv/FIMSelection-v1; did you mean 'greedy'? agents for
        this env: random, greedy, ...
    """
    names = [names] if isinstance(names, str) else list(names)
    applicable = list(dict.fromkeys(a for env_id in env_ids for a in agents_for(env_id)))
    where = f" for {', '.join(env_ids)}" if env_ids else ""
    which = ", ".join(map(repr, names))
    message = f"unknown agent{'s' if len(names) > 1 else ''} {which}{where}"
    if not applicable:
        listing = f"known agents: {', '.join(sorted(AGENTS))}"
        return with_suggestion(message, names, AGENTS, listing)
    these = "this env" if len(env_ids) == 1 else "these envs"
    listing = f"agents for {these}: {', '.join(applicable)}"
    return with_suggestion(message, names, applicable, listing)


def parse_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """Split an agent spec ``NAME[:ARG]...`` into the name and the factory's keywords.

    Each ``ARG`` is either ``key=value`` (an option; ``value`` is read as JSON when it parses,
    e.g. ``5``, ``0.5``, ``true``, else kept as a string) or a path, passed as ``checkpoint``
    (learned agents load that file instead of the shipped checkpoint)::

        "ppo:runs/my.zip"            -> ("ppo", {"checkpoint": "runs/my.zip"})
        "rollout:top_k=5:horizon=3"  -> ("rollout", {"top_k": 5, "horizon": 3})

    Raises:
        ValueError: an empty option name, two checkpoints, or a value nested deeper or larger
            than :data:`selenv.untrusted.LIMITS` allows.
    """
    from selenv.untrusted import NotParsedError, loads_json  # (light: numpy only)

    name, *args = spec.split(":")
    kwargs: dict[str, Any] = {}
    for arg in args:
        if not arg:
            continue
        key, eq, text = arg.partition("=")
        if not eq:
            if "checkpoint" in kwargs:
                raise ValueError(f"agent spec {spec!r} names two checkpoints")
            kwargs["checkpoint"] = arg
            continue
        if not key.isidentifier():
            raise ValueError(f"agent spec {spec!r}: {key!r} is not an option name")
        try:  # bounded: a value nested deeper than the ceiling is refused, not parsed
            kwargs[key] = loads_json(text, f"agent spec {name!r}: option {key}")
        except NotParsedError:
            kwargs[key] = text
    return name, kwargs


def make(name: str, env_id: str, **kwargs: Any) -> Agent:
    """Build agent ``name`` (or a ``"name:checkpoint"`` spec, see :func:`parse_spec`).

    Raises:
        ValueError: unknown agent, or an agent that does not apply to ``env_id``.
    """
    name, extra = parse_spec(name)
    kwargs = {**extra, **kwargs}
    if name not in AGENTS:
        raise ValueError(unknown_agent_message(name, [env_id]))
    if env_id not in AGENTS[name]:
        raise ValueError(
            f"agent {name!r} does not apply to {env_id!r}; it applies to {sorted(AGENTS[name])}"
        )
    with hold_signals():  # torch imports, checkpoint loads: a signal waits until they end
        return AGENTS[name][env_id].build(**kwargs)
