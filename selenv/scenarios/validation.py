"""Argument checks shared by the scenario configs, the envs and the agents.

Every check names the argument, states what is expected (the type and the valid range) and
shows the value received; none repairs its input silently. A value of the wrong type raises
:class:`ArgumentTypeError`, a ``TypeError`` that is also a ``ValueError`` (the configs
documented ``ValueError`` for every bad field before these checks existed, and ``except
ValueError`` keeps working); a value of the right type outside its range raises
``ValueError``.

Numbers: Python and numpy ints and floats are accepted where a real number is expected; bools,
strings, complex numbers, arrays and ``None`` are not. Where an int is expected a float is
refused even when integral (``2.0``): nothing is truncated.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = [
    "ArgumentTypeError",
    "as_generator",
    "check_bool",
    "check_choice",
    "check_generator",
    "check_integer",
    "check_real",
    "check_reals",
    "describe",
    "interval",
]


class ArgumentTypeError(TypeError, ValueError):
    """An argument of the wrong type (a ``TypeError``; a ``ValueError`` for compatibility)."""


def describe(value: Any, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters, with the type name for non-builtins."""
    text = repr(value)
    if len(text) > limit:
        text = text[: limit - 3] + "..."
    builtin = isinstance(value, int | float | str | bool | tuple | list | dict | type(None))
    return text if builtin else f"{type(value).__name__} {text}"


def interval(low: float, high: float, low_open: bool = False, high_open: bool = False) -> str:
    """``[low, high]`` with ``(`` / ``)`` for open ends and ``inf`` for an absent bound."""
    left = "(" if low_open or low == -math.inf else "["
    right = ")" if high_open or high == math.inf else "]"
    return f"{left}{low:g}, {high:g}{right}"


def _is_real(value: Any) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(
        value, bool | np.bool_
    )


def check_real(
    value: Any,
    name: str,
    low: float = -math.inf,
    high: float = math.inf,
    *,
    low_open: bool = False,
    high_open: bool = False,
    unit: str = "",
) -> float:
    """``value`` as a finite float in the interval (``low_open`` / ``high_open``: open ends).

    Raises:
        ArgumentTypeError: not a real number (bool, str, complex, array, None, ...).
        ValueError: NaN, infinite or outside the interval (the message gives the interval).
    """
    where = interval(low, high, low_open, high_open) + (f" {unit}" if unit else "")
    if not _is_real(value):
        raise ArgumentTypeError(f"{name} must be a real number in {where}, got {describe(value)}")
    try:
        v = float(value)
    except OverflowError:  # an int beyond the float range
        v = math.inf if value > 0 else -math.inf
    ok = math.isfinite(v) and (low < v if low_open else low <= v)
    if not (ok and (v < high if high_open else v <= high)):
        raise ValueError(f"{name} must be a finite number in {where}, got {describe(value)}")
    return v


def check_integer(value: Any, name: str, low: int, high: float = math.inf) -> int:
    """``value`` as an int in ``[low, high]`` (Python or numpy ints; floats and bools refused).

    Raises:
        ArgumentTypeError: not an int (``2.0``, ``True``, ``"2"``, ``None``, ...).
        ValueError: outside ``[low, high]``.
    """
    where = f"in [{low}, {high:g}]" if high != math.inf else f">= {low}"
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer):
        raise ArgumentTypeError(f"{name} must be an int {where}, got {describe(value)}")
    if not low <= value <= high:
        raise ValueError(f"{name} must be an int {where}, got {describe(value)}")
    return int(value)


def check_choice(value: Any, name: str, choices: Sequence[str]) -> str:
    """``value`` if it is one of the strings ``choices``.

    Raises:
        ArgumentTypeError: not a str.
        ValueError: a str that is not one of ``choices``.
    """
    if not isinstance(value, str):
        raise ArgumentTypeError(f"{name} must be one of {tuple(choices)}, got {describe(value)}")
    if value not in choices:
        raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}")
    return value


def check_bool(value: Any, name: str) -> bool:
    """``value`` as a bool (Python or numpy bools only: ``1`` and ``"yes"`` are refused)."""
    if not isinstance(value, bool | np.bool_):
        raise ArgumentTypeError(f"{name} must be a bool, got {describe(value)}")
    return bool(value)


def check_reals(
    value: Any,
    name: str,
    size: int,
    low: float = -math.inf,
    high: float = math.inf,
    *,
    low_open: bool = False,
    unit: str = "",
    labels: Sequence[str] | None = None,
) -> tuple[float, ...]:
    """A sequence (tuple, list or 1-D array) of exactly ``size`` real numbers in the interval.

    Each entry is checked by :func:`check_real` under the name ``name[i]`` (or ``labels[i]``).

    Raises:
        ArgumentTypeError: not a sequence of reals.
        ValueError: the wrong length, or an entry outside the interval.
    """
    seq = _sequence(value, name, f"{size} numbers")
    if len(seq) != size:
        raise ValueError(f"{name} must hold {size} numbers, got {describe(value)}")
    return tuple(
        check_real(v, f"{name}[{i}]" if labels is None else f"{name}[{i}] ({labels[i]})", low,
                   high, low_open=low_open, unit=unit)
        for i, v in enumerate(seq)
    )  # fmt: skip


def _sequence(value: Any, name: str, what: str) -> Sequence[Any]:
    """``value`` as a list if it is a tuple, a list or a 1-D array, else ArgumentTypeError."""
    if isinstance(value, np.ndarray) and value.ndim == 1:
        return list(value)
    if not isinstance(value, tuple | list):
        raise ArgumentTypeError(f"{name} must be a sequence of {what}, got {describe(value)}")
    return list(value)


def check_generator(rng: Any, name: str = "rng") -> np.random.Generator:
    """``rng`` if it is a ``numpy.random.Generator`` (operators that take a generator as is).

    Raises:
        ArgumentTypeError: anything else (seeds are not accepted here; pass
            ``numpy.random.default_rng(seed)``).
    """
    if not isinstance(rng, np.random.Generator):
        raise ArgumentTypeError(
            f"{name} must be a numpy.random.Generator (numpy.random.default_rng(seed)), "
            f"got {describe(rng)}"
        )
    return rng


def as_generator(rng: Any, name: str = "rng") -> np.random.Generator:
    """A generator from ``rng``: a ``Generator`` as is, an int seed >= 0, or ``None`` (fresh).

    Raises:
        ArgumentTypeError: any other type (a float seed, a string, ...).
        ValueError: a negative seed.
    """
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None:
        return np.random.default_rng()
    seed = check_integer(rng, f"{name} (a seed)", 0)
    return np.random.default_rng(seed)
