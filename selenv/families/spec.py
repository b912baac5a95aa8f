"""The record of an env family, from which its ids, entry points, views and agents are built.

A family is one folder under ``selenv/families/``: ``scenario`` (frozen config, seeded generator;
with ``models`` and the like), ``env`` (the Gymnasium env), ``rendering``, ``agents``
(heuristics; with ``rollout``, ``forecast``, ``multiagent_agents`` where the family has them),
``view`` (the candidate view of the learned policies) and ``multiagent`` (its PettingZoo
module). Its ``__init__`` holds one :class:`FamilySpec` and the two entry points
:func:`env_factories` makes from it. :mod:`selenv.families` lists the
records (one line per family) and registers their Gymnasium ids; ``selenv list``, the agent
registry, the candidate views of the learned policies and the ``ppo`` agent read the records,
so no table elsewhere names a family.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import gymnasium as gym
from gymnasium.wrappers import RenderCollection

from selenv.envs.versions import EnvVersion

__all__ = [
    "FamilySpec",
    "FrozenVersion",
    "ReturnBound",
    "build_env",
    "build_vector_env",
    "env_factories",
    "frozen_factories",
    "load_attr",
    "vector_factories",
]


def load_attr(path: str) -> Any:
    """The object ``"package.module:attr"`` names (imported on use)."""
    module, _, attr = path.partition(":")
    if not attr:
        raise ValueError(f"expected 'module:attr', got {path!r}")
    return getattr(importlib.import_module(module), attr)


@dataclass(frozen=True, kw_only=True)
class FrozenVersion:
    """A version between ``-v0`` and the current one, still registered, never changed again.

    Gymnasium's rule: a change that alters results gets a new id and the old id keeps its
    behaviour, so results published against it stay reproducible from the id alone.

    Args:
        env_class: ``"module:Class"`` of that version's Gymnasium env.
        vector_class: ``"module:Class"`` of its native vector env (``None``: none).
        change: one line: what the next version changed (the docs' version table).
    """

    env_class: str
    vector_class: str | None = None
    change: str = ""


@dataclass(frozen=True)
class ReturnBound:
    """A certified upper bound on the return of one episode (what ``selenv bench`` reports).

    Attributes:
        value: no policy's return on the episode exceeds it.
        kind: ``"optimum"`` (the best return, attained) or ``"bound"`` (certified, maybe not
            attained).
        method: how it was computed, one line (e.g. ``"continuous relaxation"``).
    """

    value: float
    kind: str
    method: str

    def __post_init__(self) -> None:
        if self.kind not in ("optimum", "bound"):
            raise ValueError(f"kind must be 'optimum' or 'bound', got {self.kind!r}")


@dataclass(frozen=True, kw_only=True)
class FamilySpec:
    """Everything the package needs to know of one env family.

    Args:
        name: folder name under ``selenv/families`` (``"fim"``).
        env_name: the Gymnasium name; ids are ``selenv/<env_name>-v<N>``.
        title: one line: the decision problem and its paper.
        env_class: ``"module:Class"`` of the current version's Gymnasium env.
        v0_kwargs: keyword defaults registered with ``-v0`` (release 0.1's configuration).
        v0_presets: preset names that meant another preset in release 0.1 (``-v0`` maps them).
        views: ``"module:attr"`` of the family's candidate views, ``{name: factory(env)}``; the
            first is the default (the learned policies read the env through it).
        checkpoint: file name in ``checkpoints/`` of the default weights of the family's
            ``ppo`` loader (:class:`selenv.learned.rl.agent.SB3PolicyAgent` without
            ``checkpoint=``) and the starting point of its expert-iteration trainers
            (``None``: none).
        policies: ``"module:attr"`` of the family's shipped learned policies, a tuple of
            :class:`~selenv.families.policy.PolicySpec` records (torch-free; their loaders are
            imported only when an agent is built). The agent registry, ``selenv list``, the
            bench's defaults, ``learned`` and the docs' tables read them; no other place
            declares a learned agent.
        agent_modules: modules whose import registers the family's agents.
        multiagent_module: the public PettingZoo module of the family (its current version),
            if any.
        multiagent_v0: the module name that reproduces release 0.1's PettingZoo env, if the
            current one changed behaviour since (``None``: the current module is it).
        has_v0: whether the family has a ``-v0`` id (it existed in release 0.1); a family
            added later starts at ``-v1``.
        vector_class: ``"module:Class"`` of the family's native batched vector env (a
            :class:`~selenv.envs.vector.BatchedVectorEnv`), registered as the ids'
            ``vector_entry_point``; ``None``: ``gymnasium.make_vec`` loops over single envs.
        frozen: the superseded versions ``-v1`` ... ``-vK`` (oldest first), still registered;
            the current version is ``-v(K+1)``. ``-v0`` builds the oldest class (release
            0.1's), ``frozen[0].env_class`` when there is one.
        agent_adapter: ``"module:attr"`` of ``adapter(agent)``, which makes an agent of the
            newest frozen version play the current one (``None``: an agent plays every version
            as it is). The agent registry registers every agent of ``-vK`` on the current id
            through it, so heuristics and shipped policies keep working when the action space
            changes.
        return_bound: ``"module:attr"`` of ``bound(env) -> ReturnBound | None``, called on the
            unwrapped env right after ``reset(seed=s)``: a certified upper bound on the return
            of that episode, or ``None`` where the configuration has none. ``selenv bench``
            reports each agent's gap to it (``None``: the family has no bound).
    """

    name: str
    env_name: str
    title: str
    env_class: str
    v0_kwargs: Mapping[str, Any] = field(default_factory=dict)
    v0_presets: Mapping[str, str] = field(default_factory=dict)
    views: str = "selenv.envs.views:IDENTITY_VIEWS"
    checkpoint: str | None = None
    policies: str | None = None
    agent_modules: tuple[str, ...] = ()
    multiagent_module: str | None = None
    multiagent_v0: str | None = None
    has_v0: bool = True
    vector_class: str | None = None
    frozen: tuple[FrozenVersion, ...] = ()
    agent_adapter: str | None = None
    return_bound: str | None = None

    def __post_init__(self) -> None:
        if not self.name.isidentifier() or not self.env_name.isidentifier():
            raise ValueError(f"name and env_name must be identifiers, got {self!r}")
        if self.agent_adapter is not None and not self.frozen:
            raise ValueError(f"{self.name}: agent_adapter needs a frozen version to adapt")
        for attr in ("v0_kwargs", "v0_presets"):
            object.__setattr__(self, attr, MappingProxyType(dict(getattr(self, attr))))

    @property
    def version(self) -> int:
        """The current version number (``1 + len(frozen)``)."""
        return 1 + len(self.frozen)

    @property
    def current_id(self) -> str:
        """The current id, ``selenv/<env_name>-v<version>``."""
        return self.version_id(self.version)

    def version_id(self, version: int) -> str:
        """``selenv/<env_name>-v<version>``."""
        return f"selenv/{self.env_name}-v{version}"

    @property
    def agents_id(self) -> str:
        """The id the family's agents and shipped policies are written for (and trained on).

        The current id, or :attr:`adapted_from` when the current version plays them through
        :attr:`agent_adapter`.
        """
        return self.adapted_from or self.current_id

    @property
    def adapted_from(self) -> str | None:
        """The id whose agents play the current one through :attr:`agent_adapter` (or ``None``)."""
        return None if self.agent_adapter is None else self.version_id(len(self.frozen))

    def classes(self, version: int) -> tuple[str, str | None]:
        """``(env_class, vector_class)`` of ``-v<version>`` (``0``: release 0.1's classes)."""
        if version == self.version or not self.frozen:
            return self.env_class, self.vector_class
        old = self.frozen[max(version, 1) - 1]
        return old.env_class, old.vector_class

    @property
    def multiagent_modules(self) -> tuple[str, ...]:
        """Every PettingZoo module name of the family, oldest first."""
        names = (self.multiagent_v0, self.multiagent_module)
        return tuple(n for n in names if n is not None)

    @property
    def versions(self) -> tuple[EnvVersion, ...]:
        """``-v0`` (release 0.1, if :attr:`has_v0`), the frozen versions and the current one.

        Entry points: ``make_env`` / ``make_vector_env`` (current), ``make_env_v<N>`` /
        ``make_vector_env_v<N>`` (older) in the family's package.
        """
        package = f"selenv.families.{self.name}"
        out = []
        for version in range(0 if self.has_v0 else 1, self.version + 1):
            suffix = "" if version == self.version else f"_v{version}"
            vector = self.classes(version)[1] is not None
            out.append(
                EnvVersion(
                    env_id=self.version_id(version),
                    entry_point=f"{package}:make_env{suffix}",
                    vector_entry_point=f"{package}:make_vector_env{suffix}" if vector else None,
                    kwargs=self.v0_kwargs if version == 0 else {},
                    superseded_by=None if version == self.version else self.current_id,
                )
            )
        return tuple(out)


def build_env(entry: str, render_mode: Any = None, **kwargs: Any) -> gym.Env[Any, Any]:
    """``Class(render_mode=..., **kwargs)`` for ``entry = "module:Class"``.

    ``gymnasium.make`` inspects ``entry_point.metadata`` when the entry point is a class and
    then handles ``render_mode`` itself before the env sees it: a non-str ``render_mode``
    (``1``, ``True``) fails there with an ``AttributeError``. The ids are therefore registered
    with plain functions, so every keyword, ``render_mode`` included, is validated by the env
    (a ``TypeError`` / ``ValueError`` naming it). What ``gymnasium.make`` would have added is
    kept: ``render_mode="rgb_array_list"`` wraps the ``"rgb_array"`` env in
    :class:`gymnasium.wrappers.RenderCollection`.
    """
    cls = load_attr(entry)
    modes = cls.metadata["render_modes"]
    if isinstance(render_mode, str) and render_mode.endswith("_list"):
        base = render_mode[: -len("_list")]
        if base in modes and base != "human":
            return RenderCollection(cls(render_mode=base, **kwargs))
    env: gym.Env[Any, Any] = cls(render_mode=render_mode, **kwargs)
    return env


EnvFactory = Callable[..., gym.Env[Any, Any]]


def env_factories(spec: FamilySpec) -> tuple[EnvFactory, EnvFactory]:
    """The entry points ``(make_env, make_env_v0)`` of a family's ``-v1`` and ``-v0`` ids.

    ``make_env_v0`` emits the ``DeprecationWarning`` pointing to ``-v1`` and maps the preset
    names of :attr:`FamilySpec.v0_presets` (the registered ``v0_kwargs`` arrive as keywords).
    """
    from selenv.envs.versions import warn_deprecated

    def make_env(**kwargs: Any) -> gym.Env[Any, Any]:
        return build_env(spec.env_class, **kwargs)

    def make_env_v0(**kwargs: Any) -> gym.Env[Any, Any]:
        warn_deprecated(f"selenv/{spec.env_name}-v0", spec.current_id)
        preset = kwargs.get("preset")
        if isinstance(preset, str) and preset in spec.v0_presets:
            kwargs["preset"] = spec.v0_presets[preset]
        return build_env(spec.classes(0)[0], **kwargs)

    make_env.__doc__ = f"``{spec.current_id}``: a ``{spec.env_class.split(':')[1]}``."
    make_env_v0.__doc__ = f"``selenv/{spec.env_name}-v0`` (release 0.1; deprecated)."
    return make_env, make_env_v0


VectorFactory = Callable[..., Any]


def vector_factories(spec: FamilySpec) -> tuple[VectorFactory, VectorFactory]:
    """The vector entry points ``(make_vector_env, make_vector_env_v0)`` of a family.

    ``gymnasium.make_vec(id, num_envs=B, **kwargs)`` calls them with ``num_envs`` and the id's
    keywords (``autoreset_mode``, if given, selects Gymnasium's autoreset mode);
    ``make_vector_env_v0`` warns and maps the ``-v0`` presets as :func:`env_factories` does. A
    family without :attr:`FamilySpec.vector_class` refuses.
    """
    from selenv.envs.versions import warn_deprecated

    def make_vector_env(num_envs: int = 1, **kwargs: Any) -> Any:
        return build_vector_env(spec.vector_class, spec.current_id, num_envs, **kwargs)

    def make_vector_env_v0(num_envs: int = 1, **kwargs: Any) -> Any:
        warn_deprecated(f"selenv/{spec.env_name}-v0", spec.current_id)
        preset = kwargs.get("preset")
        if isinstance(preset, str) and preset in spec.v0_presets:
            kwargs["preset"] = spec.v0_presets[preset]
        return build_vector_env(spec.classes(0)[1], spec.version_id(0), num_envs, **kwargs)

    make_vector_env.__doc__ = f"``gymnasium.make_vec('{spec.current_id}', num_envs=B)``."
    make_vector_env_v0.__doc__ = f"``selenv/{spec.env_name}-v0``'s vector env (deprecated)."
    return make_vector_env, make_vector_env_v0


def build_vector_env(entry: str | None, env_id: str, num_envs: int, **kwargs: Any) -> Any:
    """``Class(num_envs=num_envs, **kwargs)``; ``autoreset_mode``, if given, selects the mode.

    Raises:
        ValueError: ``entry`` is ``None`` (``env_id`` has no native vector env).
    """
    if entry is None:
        raise ValueError(f"{env_id} has no native vector env")
    mode = kwargs.pop("autoreset_mode", None)
    venv = load_attr(entry)(num_envs=num_envs, **kwargs)
    if mode is not None:
        venv.set_autoreset_mode(mode)
    return venv


def frozen_factories(spec: FamilySpec, version: int) -> tuple[EnvFactory, VectorFactory]:
    """The entry points ``(make_env_vN, make_vector_env_vN)`` of the frozen ``-v<version>``.

    They build that version's classes (:attr:`FamilySpec.frozen`) with the user's keywords;
    Gymnasium's ``make`` itself warns that a newer version exists.
    """
    if not 1 <= version < spec.version:
        raise ValueError(f"{spec.name}: -v{version} is not a frozen version")
    env_class, vector_class = spec.classes(version)
    env_id = spec.version_id(version)

    def make_env_frozen(**kwargs: Any) -> gym.Env[Any, Any]:
        return build_env(env_class, **kwargs)

    def make_vector_env_frozen(num_envs: int = 1, **kwargs: Any) -> Any:
        return build_vector_env(vector_class, env_id, num_envs, **kwargs)

    make_env_frozen.__doc__ = f"``{env_id}`` (frozen; {spec.current_id} is current)."
    make_vector_env_frozen.__doc__ = f"``gymnasium.make_vec('{env_id}', num_envs=B)`` (frozen)."
    return make_env_frozen, make_vector_env_frozen
