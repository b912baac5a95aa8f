"""The learned agents, registered from the families' policy records.

Every :class:`~selenv.families.policy.PolicySpec` record becomes an agent of its name on the
envs it plays (its loader is imported only when the agent is built); its deprecated names stay
for one release; and ``learned`` names, per env and PettingZoo module, the record with the best
held-out standing (:func:`resolve_learned`). Agents built from a record check, at each
episode, that the env's configuration is one the record was trained and verified on, and warn
in one line when it is not (:class:`OutsideValidityWarning`), unless they play the user's own
``checkpoint=``.

``learned`` chooses among the records whose standing beats their baseline (95 % CI above 0)
within the record's decision budget (``max_decision_ratio``) the one with the largest mean
paired difference, preferring standings measured at the env's
own values of the keywords they were measured with (a PettingZoo ``mode``, say) over those
measured at the defaults. Standings of one env are measured on the same seeds, so their mean
differences are comparable (``scripts/record_standings.py``).
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from collections.abc import Mapping
from typing import Any

from selenv.agents.base import AGENTS, Agent, AgentSpec, _check_options, register_agent
from selenv.families import ADAPTED, FAMILIES
from selenv.families.policy import PolicySpec, Standing
from selenv.families.spec import load_attr

__all__ = [
    "OutsideValidityWarning",
    "PolicyAgent",
    "all_policies",
    "learned_choice",
    "list_note",
    "policy",
    "register_policies",
    "resolve_learned",
]


class OutsideValidityWarning(UserWarning):
    """A shipped policy plays an env configuration it was not trained and verified on."""


@functools.cache
def all_policies() -> tuple[PolicySpec, ...]:
    """Every family's records, in family order."""
    out: list[PolicySpec] = []
    for family in FAMILIES:
        if family.policies is not None:
            out.extend(load_attr(family.policies))
    return tuple(out)


def policy(name: str, env_id: str) -> PolicySpec:
    """The record named ``name`` that plays ``env_id``.

    Raises:
        KeyError: no such record.
    """
    for record in all_policies():
        if record.name == name and env_id in record.plays:
            return record
    raise KeyError(f"no learned policy {name!r} plays {env_id!r}")


def _matches(standing: Standing, parameters: Mapping[str, Any] | None) -> int | None:
    """How many keywords of ``standing`` the env's ``parameters`` match (``None``: one differs).

    ``parameters is None`` stands for the env's defaults: only standings measured at the
    defaults (no keywords) match them.
    """
    if parameters is None:
        return 0 if not standing.env_kwargs else None
    for key, value in standing.env_kwargs.items():
        if key not in parameters or parameters[key] != value:
            return None
    return len(standing.env_kwargs)


def resolve_learned(
    env_id: str, parameters: Mapping[str, Any] | None = None
) -> tuple[PolicySpec, Standing] | None:
    """The record ``learned`` plays on ``env_id`` (at ``parameters``; ``None``: the defaults).

    Returns ``None`` when no current record's standing beats its baseline there.
    """
    best: tuple[int, float, PolicySpec, Standing] | None = None
    for record in all_policies():
        if env_id not in record.plays or record.retired:
            continue
        for standing in record.standings():
            if standing.env_id != env_id or not standing.beats_baseline:
                continue
            if not record.within_budget(standing):
                continue
            level = _matches(standing, parameters)
            if level is None:
                continue
            key = (level, standing.mean_difference)
            if best is None or key > best[:2]:
                best = (level, standing.mean_difference, record, standing)
    return None if best is None else (best[2], best[3])


def list_note(name: str, env_id: str) -> str:
    """What ``selenv list`` adds to a learned agent's line: its standing, or why it is retired.

    On a version that plays an older one's agents (:data:`~selenv.families.ADAPTED`), the
    older version's standings: the agent plays the same episodes there.
    """
    if env_id in ADAPTED:
        source = ADAPTED[env_id][0]
        note = list_note(name, source)
        return f"{note} (on {source}: the same episodes)" if note else note
    if name == "learned":
        return learned_choice(env_id)
    try:
        record = policy(name, env_id)
    except KeyError:
        return ""
    if record.retired:
        return f"retired: {record.retired}"
    measured = [s for s in record.standings() if s.env_id == env_id]
    if not measured:
        return "no held-out standing recorded"
    return "; ".join(s.summary() for s in measured)


def learned_choice(env_id: str) -> str:
    """One line for ``selenv list``: what ``learned`` plays on ``env_id`` at its defaults."""
    found = resolve_learned(env_id)
    if found is None:
        return "no shipped learned policy beats its baseline here yet"
    record, standing = found
    return f"plays {record.name}: {standing.summary()}"


class PolicyAgent(Agent):
    """An agent built from a record: the loader's agent, with the validity check at each reset.

    Attributes the loader's agent has (``checkpoint``, ``logits``, ...) are reached through this
    one.
    """

    def __init__(self, record: PolicySpec, inner: Agent, *, shipped: bool) -> None:
        self.record = record
        self.inner = inner
        self.shipped = shipped
        self.name = record.name  # type: ignore[misc]

    def __getattr__(self, attr: str) -> Any:
        if attr == "inner":  # not set yet (copy, unpickling): no recursion
            raise AttributeError(attr)
        return getattr(self.inner, attr)

    def reset(self, env: Any, seed: int | None = None) -> None:  # noqa: D102
        if self.shipped and self.record.valid:
            check_validity(self.record, env)
        self.inner.reset(env, seed)

    def act(self, obs: Any, info: dict[str, Any]) -> Any:  # noqa: D102
        return self.inner.act(obs, info)


def env_parameters(env: Any) -> dict[str, Any]:
    """The constructor parameters of a built env (Gymnasium or PettingZoo) as it holds them."""
    from selenv.envs.resolved import resolved_env_config

    return dict(resolved_env_config(env)["parameters"])


def check_validity(record: PolicySpec, env: Any) -> None:
    """Warn (:class:`OutsideValidityWarning`, one line) if ``env`` is outside ``record.valid``."""
    outside = record.outside(env_parameters(env))
    if not outside:
        return
    got = ", ".join(f"{k}={v!r}" for k, v in sorted(outside.items()))
    verified = "; ".join(f"{k} in {list(record.valid[k])}" for k in sorted(outside))
    warnings.warn(
        f"{record.name}: this env has {got}, outside what the shipped policy was trained and "
        f"verified on ({verified}); it may play worse than {record.baseline} there",
        OutsideValidityWarning,
        stacklevel=3,
    )


def _build(record: PolicySpec, **options: Any) -> PolicyAgent:
    """``record``'s agent with ``options`` (a user ``checkpoint=`` replaces the shipped one)."""
    factory = load_attr(record.factory)
    kwargs = dict(record.kwargs)
    own = options.get("checkpoint") is not None
    if own:
        kwargs.pop("shipped", None)
    elif record.retired:
        warnings.warn(
            f"agent {record.name!r} on {', '.join(record.plays)} is retired: "
            f"{record.retired}; it is removed in the next release",
            DeprecationWarning,
            stacklevel=4,
        )
    kwargs.update(options)
    _check_options(record.name, factory, kwargs)
    return PolicyAgent(record, factory(**kwargs), shipped=not own)


def _build_alias(record: PolicySpec, alias: str, **options: Any) -> PolicyAgent:
    """A deprecated name: warn, naming the new spelling, then build ``record`` with its options."""
    fixed = dict(record.aliases[alias])
    spelling = ":".join([record.name, *(f"{k}={v}" for k, v in fixed.items())])
    warnings.warn(
        f"agent {alias!r} is deprecated and removed in the next release: use {spelling!r}",
        DeprecationWarning,
        stacklevel=4,
    )
    return _build(record, **{**fixed, **options})


class LearnedAgent(Agent):
    """``learned``: at each episode, the record :func:`resolve_learned` picks for the env.

    The record for the defaults is built at once (so a bad option fails early); another is
    built the first time an env's configuration selects it (a PettingZoo ``mode``, say).
    """

    name = "learned"

    def __init__(self, env_id: str, options: Mapping[str, Any]) -> None:
        self.env_id = env_id
        self.options = dict(options)
        self._built: dict[str, PolicyAgent] = {}
        found = resolve_learned(env_id)
        if found is None:
            raise ValueError(f"no shipped learned policy beats its baseline on {env_id} yet")
        self.current = self._agent(found[0])

    def _agent(self, record: PolicySpec) -> PolicyAgent:
        if record.name not in self._built:
            self._built[record.name] = _build(record, **self.options)
        return self._built[record.name]

    def __getattr__(self, attr: str) -> Any:
        if attr == "current":
            raise AttributeError(attr)
        return getattr(self.current, attr)

    def reset(self, env: Any, seed: int | None = None) -> None:
        found = resolve_learned(self.env_id, env_parameters(env))
        if found is not None:
            self.current = self._agent(found[0])
        self.current.reset(env, seed)

    def act(self, obs: Any, info: dict[str, Any]) -> Any:
        return self.current.act(obs, info)


def register_policies() -> None:
    """Register every record, its deprecated names and ``learned`` (called by ``selenv.agents``)."""
    envs: dict[str, None] = {}
    for record in all_policies():
        register_agent(
            AgentSpec(
                record.name,
                record.plays,
                functools.partial(_build, record),
                record.description + (" (shipped weights retired)" if record.retired else ""),
                all_versions=False,  # a shipped policy was trained on the current version
                learned=True,
                default=not record.retired,
            )
        )
        for alias in record.aliases:
            options = "".join(f":{k}={v}" for k, v in record.aliases[alias].items())
            register_agent(
                AgentSpec(
                    alias,
                    record.plays,
                    functools.partial(_build_alias, record, alias),
                    f"deprecated: use {record.name}{options}",
                    all_versions=False,
                    learned=True,
                    default=False,
                    deprecated=True,
                )
            )
        envs.update(dict.fromkeys(record.plays))
    for env_id in envs:
        target = learned_target(env_id)
        if target is None:
            continue
        # `learned` plays that record: the bench runs it once, under `learned`
        register_agent(
            dataclasses.replace(AGENTS[target][env_id], env_ids=(env_id,), default=False)
        )
        register_agent(
            AgentSpec(
                "learned",
                (env_id,),
                functools.partial(_learned_factory, env_id),
                "the recommended learned agent (the record with the best held-out standing)",
                all_versions=False,
                learned=True,
            )
        )


def _learned_factory(env_id: str, **options: Any) -> LearnedAgent:
    return LearnedAgent(env_id, options)


def learned_target(env_id: str) -> str | None:
    """The record ``learned`` plays on ``env_id`` at its defaults (``None``: no ``learned``).

    On a version that plays an older one's agents (:data:`~selenv.families.ADAPTED`), the
    older version's record (``learned`` there is wrapped by the adapter).
    """
    found = resolve_learned(ADAPTED.get(env_id, (env_id,))[0])
    return None if found is None else found[0].name
