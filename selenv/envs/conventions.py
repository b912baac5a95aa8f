"""Constructor conventions shared by every env: keywords, ``render_mode``, ``spec``.

* an unknown keyword is a ``TypeError`` with a "did you mean" for a close one
  (:func:`check_known_keywords`, :class:`KnownKeywords`; Python's convention,
  which ``gymnasium.make``, SB3's ``make_vec_env`` and TorchRL rely on), a bad value a
  ``ValueError`` naming the argument;
* ``render_mode`` is one of ``metadata["render_modes"]`` or ``None`` (:func:`check_render_mode`);
* ``env.spec.max_episode_steps`` is the episode length the keywords imply
  (:class:`EpisodeLengthSpec`).
"""

from __future__ import annotations

import dataclasses
import inspect
from typing import Any, cast

from gymnasium.envs.registration import EnvSpec

from selenv.scenarios.validation import ArgumentTypeError, describe
from selenv.suggest import with_suggestion

__all__ = [
    "EpisodeLengthSpec",
    "KnownKeywords",
    "check_known_keywords",
    "check_render_mode",
    "named_parameters",
]


def named_parameters(cls: type) -> list[str]:
    """The named keyword parameters of ``cls.__init__`` (not ``self`` nor ``**kwargs``)."""
    params = inspect.signature(cast(Any, cls).__init__).parameters.values()
    return [p.name for p in params if p.name != "self" and p.kind != p.VAR_KEYWORD]


def check_known_keywords(given: dict[str, Any], known: Any, env_name: str, named: Any = ()) -> None:
    """Raise ``TypeError`` for keywords of ``given`` (the ``**config`` of an env) not in ``known``.

    The message has Python's own form (``got an unexpected keyword argument 'x'``, which
    wrappers such as TorchRL's ``GymEnv`` recognise to drop an optional keyword like
    ``frameskip``), names every unknown keyword and lists every keyword the constructor
    accepts: ``known`` and its ``named`` parameters, after a "did you mean" for a close one.
    """
    unknown = sorted(set(given) - set(known))
    if unknown:
        accepted = sorted(set(known) | set(named))
        more = f" (and {unknown[1:]})" if len(unknown) > 1 else ""
        message = f"{env_name} got an unexpected keyword argument {unknown[0]!r}{more}"
        raise TypeError(with_suggestion(message, unknown, accepted, f"known: {accepted}"))


def check_render_mode(render_mode: Any, metadata: dict[str, Any]) -> str | None:
    """Return ``render_mode`` if it is ``None`` or in ``metadata["render_modes"]``.

    Raises:
        TypeError: neither ``None`` nor a str.
        ValueError: any other str, naming the supported modes.
    """
    modes = metadata["render_modes"]
    if render_mode is not None and not isinstance(render_mode, str):
        raise ArgumentTypeError(
            f"render_mode must be None or one of {modes}, got {describe(render_mode)}"
        )
    if render_mode is not None and render_mode not in modes:
        raise ValueError(f"render_mode must be None or one of {modes}, got {render_mode!r}")
    return render_mode


class KnownKeywords:
    """Mixin (put it first among the bases): unknown keywords are refused with a "did you mean".

    For a constructor with a fixed signature, whose unknown keywords Python itself would
    refuse; one that takes ``**config`` checks them itself with :func:`check_known_keywords`.
    The check runs in ``__new__``, before ``__init__``: the ``TypeError`` keeps Python's
    wording (``Env.__init__() got an unexpected keyword argument 'x'``), then suggests the
    close keywords and lists the known ones.
    """

    def __new__(cls, *args: Any, **kwargs: Any) -> Any:
        """Check ``kwargs`` against the keywords of ``cls.__init__``, then create the object."""
        params = inspect.signature(cls.__init__).parameters.values()
        if not any(p.kind is p.VAR_KEYWORD for p in params):
            check_known_keywords(kwargs, named_parameters(cls), f"{cls.__name__}.__init__()")
        return super().__new__(cls)


class EpisodeLengthSpec(KnownKeywords):
    """Mixin (put it before ``gymnasium.Env``): the spec reports the episode length.

    ``gymnasium.make`` stores a spec with ``max_episode_steps=None`` on the unwrapped env; the
    length of a selenv episode is known from the constructor keywords (``budget``, ``k *
    horizon``, ...), so the spec is completed with :attr:`max_episode_steps` when it is set.
    No ``TimeLimit`` is added by the registration: episodes end by termination. A
    ``max_episode_steps`` given to ``gymnasium.make`` is kept as given.
    """

    #: the longest possible episode, in ``step`` calls (set by the env's ``__init__``)
    max_episode_steps: int
    _spec: EnvSpec | None = None

    @property
    def spec(self) -> EnvSpec | None:
        """The env's spec, with ``max_episode_steps`` filled in."""
        return self._spec

    @spec.setter
    def spec(self, value: Any) -> None:
        if isinstance(value, EnvSpec) and value.max_episode_steps is None:
            value = dataclasses.replace(value, max_episode_steps=int(self.max_episode_steps))
        self._spec = value
