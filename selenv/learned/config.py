"""Dataclass configs as command lines: each field is a ``--kebab-case`` option (CleanRL style)."""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any, TypeVar

__all__ = ["parse_config"]

C = TypeVar("C")


def parse_config(cls: type[C], argv: list[str] | None, description: str) -> C:
    """Build a ``cls`` instance (a dataclass of int / float / str / bool fields) from ``argv``.

    ``bool`` fields become ``--flag / --no-flag``; every other field ``--field-name VALUE``
    with the field's type and default. ``argv=None`` reads ``sys.argv``.
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"cls must be a dataclass, got {cls!r}")
    parser = argparse.ArgumentParser(description=description)
    for f in dataclasses.fields(cls):
        flag = "--" + f.name.replace("_", "-")
        if f.type in ("bool", bool):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=f.default)
        else:
            typ: Any = {"int": int, "float": float, "str": str}[str(f.type)]
            parser.add_argument(flag, type=typ, default=f.default)
    return cls(**vars(parser.parse_args(argv)))
