"""Gymnasium's ``call`` / ``get_attr`` / ``set_attr`` on a batched vector env.

:class:`gymnasium.vector.SyncVectorEnv` answers them by visiting its ``B`` sub-env objects
(``env.get_wrapper_attr(name)``, called when callable). A native batched vector env
(:class:`~selenv.envs.vector.BatchedVectorEnv`) has no sub-env objects: its sub-envs are rows
of shared arrays. :class:`SubEnvAttributes` answers the same calls, with the same return
shapes (a ``B``-tuple) and the same rules, for what a sub-env exposes:

* ``np_random`` (sub-env ``b``'s generator, created on first use as
  :attr:`gymnasium.Env.np_random` does) and ``np_random_seed`` (the seed it was made from;
  ``-1`` once a generator was assigned);
* ``spec``, ``render_mode``, ``metadata`` (the single env's), ``observation_space`` and
  ``action_space`` (the single spaces);
* the batched methods a single env has, one row per sub-env: ``action_masks`` and ``render``
  (``call("render")`` is ``render()``'s frames);
* the family's per-sub-env attributes (:attr:`SubEnvAttributes.sub_env_attributes`: name ->
  the vector env's attribute holding the ``B`` values, e.g. ``budget_left``);
* attributes a user sets with ``set_attr`` under a new name (stored per sub-env, read back by
  ``get_attr``), as on any Python object.

``set_attr("np_random", ...)`` replaces the sub-envs' generators (as assigning
``env.np_random`` does); setting any other attribute the env itself defines is refused with an
``AttributeError`` naming it (the state lives in shared arrays: it cannot be rebound per
sub-env). An unknown name is an ``AttributeError`` listing what the sub-envs expose.
"""

from __future__ import annotations

import difflib
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np
from gymnasium.utils import seeding

__all__ = ["SubEnvAttributes"]

#: the single-env methods a batched env answers row by row (from its batched method)
_BATCHED_METHODS = ("action_masks", "render")
#: names ``call`` refuses: a sub-env is reset or stepped through the vector env
_VECTOR_ONLY = ("reset", "step", "close")


class SubEnvAttributes:
    """``call`` / ``get_attr`` / ``set_attr`` for :class:`~selenv.envs.vector.BatchedVectorEnv`.

    Subclasses set :attr:`sub_env_metadata` (the single env's ``metadata``) and may declare
    :attr:`sub_env_attributes`.
    """

    #: the single env class's ``metadata`` (``get_attr("metadata")``)
    sub_env_metadata: ClassVar[dict[str, Any]] = {}
    #: family attributes of a sub-env: name -> the vector env's attribute (or method) holding
    #: the ``B`` values, e.g. ``{"budget_left": "budget_left"}`` for a ``(B,)`` array
    sub_env_attributes: ClassVar[dict[str, str]] = {}

    num_envs: int
    np_randoms: list[np.random.Generator | None]
    np_random_seeds: list[int | None]
    render_mode: str | None
    spec: Any
    single_observation_space: Any
    single_action_space: Any

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """Every sub-env's ``name``: called with ``args`` / ``kwargs`` if callable (a ``B``-tuple).

        Raises:
            AttributeError: ``name`` is not something a sub-env exposes (the known names are
                listed), or is ``reset`` / ``step`` / ``close`` (use the vector env's).
            TypeError: ``name`` is not a str.
        """
        if name in _VECTOR_ONLY:
            raise AttributeError(
                f"call({name!r}): a sub-env of {type(self).__name__} is {name} through the "
                f"vector env (reset(options={{'reset_mask': mask}}) resets some sub-envs)"
            )
        if name in _BATCHED_METHODS:
            if args or kwargs:
                raise TypeError(f"call({name!r}) takes no arguments (the single env's takes none)")
            if name == "render":
                frames = self.render()  # type: ignore[attr-defined]
                return tuple(frames) if frames is not None else (None,) * self.num_envs
            return tuple(np.asarray(self.action_masks()))  # type: ignore[attr-defined]
        values = self._sub_env_values(name)
        return tuple(v(*args, **kwargs) if callable(v) else v for v in values)

    def get_attr(self, name: str) -> tuple[Any, ...]:
        """Every sub-env's ``name`` (a ``B``-tuple); as ``SyncVectorEnv``: ``call(name)``."""
        return self.call(name)

    def set_attr(self, name: str, values: Any) -> None:
        """Set ``name`` on every sub-env: ``values`` one per sub-env (list / tuple) or shared.

        Raises:
            ValueError: a list / tuple of another length than ``num_envs``.
            AttributeError: ``name`` is an attribute of the env other than ``np_random``
                (its state is shared arrays, not per-sub-env objects).
            TypeError: ``name`` not a str; ``np_random`` values not numpy Generators.
        """
        _check_name(name)
        if not isinstance(values, list | tuple):
            values = [values] * self.num_envs
        if len(values) != self.num_envs:
            raise ValueError(
                f"set_attr({name!r}): values must be a list or tuple of {self.num_envs} (one per "
                f"sub-env) or a single value, got {len(values)}"
            )
        if name == "np_random":
            for v in values:
                if not isinstance(v, np.random.Generator):
                    raise TypeError(
                        f"set_attr('np_random'): values must be numpy Generators, got {type(v)}"
                    )
            self.np_randoms[:] = list(values)
            self.np_random_seeds[:] = [-1] * self.num_envs  # as gymnasium.Env's setter
            return
        if name in self._env_names():
            raise AttributeError(
                f"set_attr({name!r}): {type(self).__name__} keeps its sub-envs' state in shared "
                "arrays; only np_random and attributes of your own can be set per sub-env"
            )
        self._user_attrs()[name] = list(values)

    # -- helpers -----------------------------------------------------------------------------
    def _user_attrs(self) -> dict[str, list[Any]]:
        attrs: dict[str, list[Any]] | None = self.__dict__.get("_sub_env_user_attrs")
        if attrs is None:
            attrs = {}
            self.__dict__["_sub_env_user_attrs"] = attrs
        return attrs

    def _env_names(self) -> list[str]:
        """Every name a sub-env exposes besides the user's own."""
        base = ["np_random", "np_random_seed", "spec", "render_mode", "metadata"]
        base += ["observation_space", "action_space", *_BATCHED_METHODS]
        return base + sorted(self.sub_env_attributes)

    def _sub_env_values(self, name: str) -> tuple[Any, ...]:
        _check_name(name)
        n = self.num_envs
        getters: dict[str, Callable[[], Any]] = {
            "np_random": self._generators,
            "np_random_seed": self._generator_seeds,
            "spec": lambda: (self.spec,) * n,
            "render_mode": lambda: (self.render_mode,) * n,
            "metadata": lambda: tuple(dict(self.sub_env_metadata) for _ in range(n)),
            "observation_space": lambda: (self.single_observation_space,) * n,
            "action_space": lambda: (self.single_action_space,) * n,
        }
        if name in getters:
            return tuple(getters[name]())
        if name in self.sub_env_attributes:
            batched = getattr(self, self.sub_env_attributes[name])
            batched = batched() if callable(batched) else batched
            arr = np.asarray(batched)
            if arr.ndim == 1 and arr.dtype != object:  # Python scalars, as the single env's
                return tuple(arr.tolist())
            return tuple(batched)
        user = self._user_attrs()
        if name in user:
            return tuple(user[name])
        known = self._env_names() + sorted(user)
        close = difflib.get_close_matches(name, known, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise AttributeError(
            f"the sub-envs of {type(self).__name__} have no attribute {name!r}{hint} (they "
            f"expose {', '.join(known)})"
        )

    def _generators(self) -> list[np.random.Generator]:
        """Each sub-env's generator; one made from fresh entropy where none exists yet."""
        for i, rng in enumerate(self.np_randoms):
            if rng is None:
                self.np_randoms[i], self.np_random_seeds[i] = seeding.np_random()
        return [rng for rng in self.np_randoms if rng is not None]

    def _generator_seeds(self) -> list[int | None]:
        self._generators()
        return list(self.np_random_seeds)


def _check_name(name: Any) -> None:
    if not isinstance(name, str):
        raise TypeError(f"the attribute name must be a str, got {type(name).__name__}")
