"""The resolved configuration of a built env: every constructor keyword with the value it took.

``env_kwargs: {}`` in a result says only that the defaults were used, and defaults change
between versions and presets. :func:`resolved_env_config` records what the env actually runs:
its id, the keywords ``gymnasium.make`` passed (the version's registered defaults included),
and every constructor parameter with its resolved value (a preset's values filled in), so two
results can be compared without the code that made them.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
from typing import Any

import numpy as np

__all__ = ["jsonable", "resolved_env_config"]

_MISSING = object()


def jsonable(value: Any) -> Any:
    """``value`` as JSON types; other objects as their ``repr``.

    numpy scalars and arrays become numbers and lists, tuples lists, dataclasses dicts, and
    non-finite floats strings.
    """
    if isinstance(value, bool | int | str) or value is None:
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if isinstance(value, np.generic):
        return jsonable(value.item())
    if isinstance(value, np.ndarray):
        return [jsonable(v) for v in value.tolist()]
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    return repr(value)


def _resolved(name: str, base: Any, given: dict[str, Any], default: Any) -> Any:
    """The value parameter ``name`` took: the env's attribute, its config's, else as given."""
    for holder in (base, getattr(base, "config", None)):
        if holder is not None and name != "render_mode":
            value = getattr(holder, name, _MISSING)
            if value is not _MISSING and not callable(value):
                return value
    return given.get(name, default)


def resolved_env_config(env: Any) -> dict[str, Any]:
    """``{"env_id", "make_kwargs", "parameters", "config"}`` of a built env (JSON types).

    ``make_kwargs``: what ``gymnasium.make`` passed (``env.spec.kwargs``: the version's
    registered defaults and the user's keywords); ``parameters``: every constructor parameter
    of the env class with the value the env holds (its attribute, or its ``config``'s),
    falling back to the keyword given or the signature default; ``config``: the env's
    ``config`` dataclass, if it has one, field by field.
    """
    base = getattr(env, "unwrapped", env)
    spec = getattr(env, "spec", None)
    given = dict(getattr(spec, "kwargs", None) or {})
    params: dict[str, Any] = {}
    for p in inspect.signature(type(base).__init__).parameters.values():
        if p.name == "self" or p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            continue
        default = None if p.default is inspect.Parameter.empty else p.default
        params[p.name] = _resolved(p.name, base, given, default)
    for name, value in given.items():  # **config keywords the signature does not name
        params.setdefault(name, _resolved(name, base, given, value))
    config = getattr(base, "config", None)
    return {
        "env_id": getattr(spec, "id", None),
        "make_kwargs": jsonable(given),
        "parameters": jsonable(params),
        "config": jsonable(config) if dataclasses.is_dataclass(config) else None,
    }
