"""Bounded reading of untrusted JSON and TOML: size and nesting checked before parsing.

Every JSON or TOML text a command reads from its user or from a file (``--env-kwargs``, an
agent option ``name:key=json``, a ``--config`` TOML file, checkpoint metadata, a resume state)
goes through this module, so that a hostile or mistaken input is one ``ValueError`` naming
the option or the file, never a ``RecursionError`` traceback or an allocation of gigabytes:

* the text is refused when it is larger than :data:`LIMITS` ``["max_bytes"]`` (command-line
  texts: ``["max_argument_bytes"]``);
* its nesting depth is measured by a linear, non-recursive scan (string literals and TOML
  comments removed first) and refused above ``["max_depth"]`` before the parser runs; the
  depth of the parsed value is checked again (TOML dotted keys and table headers nest
  without brackets).

:class:`UntrustedInputError` is a ``ValueError``; its message starts with the name given as
``what`` (``"--env-kwargs"``, ``"--config runs/a.toml"``, ...). The ceilings are far above
any real input (selenv's own files nest <= 8 deep); a caller that trusts a larger input can
raise an entry of :data:`LIMITS` first.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "LIMITS",
    "NotParsedError",
    "UntrustedInputError",
    "json_depth",
    "json_object",
    "loads_json",
    "loads_toml",
    "read_json_file",
    "read_text",
    "read_toml_file",
    "toml_depth",
    "value_depth",
]

#: ceilings of :func:`loads_json` / :func:`loads_toml` (read at call time):
#:
#: ``max_bytes``
#:     size of a file's text (4 MiB);
#: ``max_argument_bytes``
#:     size of a text given on the command line (1 MiB);
#: ``max_depth``
#:     nesting depth of arrays and objects / tables (64).
LIMITS: dict[str, int] = {"max_bytes": 4 * 2**20, "max_argument_bytes": 2**20, "max_depth": 64}

#: a JSON string literal (escapes included), matched without backtracking blow-up
_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"', re.DOTALL)
#: TOML strings (multi-line first) and comments, leftmost first
_TOML_SKIP = re.compile(
    r'"""[\s\S]*?"""|\'\'\'[\s\S]*?\'\'\'|"[^"\\\n]*(?:\\.[^"\\\n]*)*"|\'[^\'\n]*\'|#[^\n]*'
)


class UntrustedInputError(ValueError):
    """A JSON / TOML input refused: too large, nested too deeply, or not parseable."""


class NotParsedError(UntrustedInputError):
    """The input is within the bounds but is not valid JSON / TOML."""


def _bracket_depth(bare: str) -> int:
    """Deepest running count of ``[``/``{`` minus ``]``/``}`` in ``bare`` (one numpy pass)."""
    codes = np.frombuffer(bare.encode("ascii", "ignore"), dtype=np.uint8)
    if codes.size == 0:
        return 0
    step = np.isin(codes, (0x5B, 0x7B)).astype(np.int64) - np.isin(codes, (0x5D, 0x7D))
    return int(max(np.cumsum(step).max(), 0))


def json_depth(text: str) -> int:
    """The deepest nesting of arrays and objects in the JSON ``text``, without parsing it.

    String literals are removed first (their brackets do not count): linear time, no
    recursion, so a document nested 10^5 deep costs milliseconds. Malformed JSON gives some
    number; parsing it afterwards reports the error.
    """
    return _bracket_depth(_JSON_STRING.sub("", text))


def toml_depth(text: str) -> int:
    """The deepest bracket nesting of arrays and inline tables in the TOML ``text``.

    Strings and comments are removed first. Dotted keys and ``[a.b.c]`` headers are not
    counted here (they do not recurse in the parser); :func:`value_depth` measures them.
    """
    return _bracket_depth(_TOML_SKIP.sub("", text))


def value_depth(value: Any) -> int:
    """Nesting depth of a parsed value (a scalar is 0, ``[]`` is 1), found without recursion."""
    deepest = 0
    stack: list[tuple[Any, int]] = [(value, 0)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, dict):
            children: Any = item.values()
        elif isinstance(item, list | tuple):
            children = item
        else:
            continue
        deepest = max(deepest, depth + 1)
        stack.extend((child, depth + 1) for child in children)
    return deepest


def _check_text(text: str, what: str, limit_key: str, depth: int) -> None:
    size = len(text.encode("utf-8", "surrogatepass"))
    if size > LIMITS[limit_key]:
        raise UntrustedInputError(
            f"{what}: {size:,} bytes, more than the ceiling of {LIMITS[limit_key]:,} "
            f"(selenv.untrusted.LIMITS[{limit_key!r}])"
        )
    _check_depth(depth, what)


def _too_deep(what: str) -> UntrustedInputError:
    return UntrustedInputError(
        f"{what}: nested deeper than {LIMITS['max_depth']} levels "
        "(selenv.untrusted.LIMITS['max_depth'])"
    )


def _check_depth(depth: int, what: str) -> None:
    if depth > LIMITS["max_depth"]:
        raise _too_deep(what)


def loads_json(text: str, what: str, *, argument: bool = True) -> Any:
    """``json.loads(text)``, its size and nesting bounded first.

    Args:
        text: the JSON text.
        what: how messages name the input (``"--env-kwargs"``, a file name).
        argument: a command-line text (ceiling ``max_argument_bytes``) rather than a file's
            (``max_bytes``).

    Raises:
        UntrustedInputError: too large, nested deeper than ``max_depth``, or not valid JSON
            (``"{what}: not valid JSON (...)"``, a :class:`NotParsedError`).
    """
    _check_text(text, what, "max_argument_bytes" if argument else "max_bytes", json_depth(text))
    try:
        return json.loads(text)
    except RecursionError:  # unreachable after the scan; kept so no caller ever sees one
        raise _too_deep(what) from None
    except ValueError as exc:  # JSONDecodeError, and ints beyond the digit limit
        raise NotParsedError(f"{what}: not valid JSON ({exc})") from None


def json_object(text: str, what: str = "--env-kwargs") -> dict[str, Any]:
    """The JSON object ``text`` (e.g. ``--env-kwargs``), bounded as :func:`loads_json`.

    Raises:
        UntrustedInputError: too large, too deep, not valid JSON, or not an object
            (``"{what} must be a JSON object, got ..."``).
    """
    value = loads_json(text, what)
    if not isinstance(value, dict):
        raise UntrustedInputError(f"{what} must be a JSON object, got {text!r:.120}")
    return value


def read_text(
    path: str | Path, what: str, *, max_bytes: int | None = None, ceiling: str | None = None
) -> str:
    """The UTF-8 text of the regular file ``path``, its size checked before it is read.

    Args:
        path: the file.
        what: how messages name it (``"checkpoint metadata"``, ``"--config"``).
        max_bytes: the largest size read (default ``LIMITS["max_bytes"]``).
        ceiling: how messages name that limit (default ``"selenv.untrusted.LIMITS['max_bytes']"``).

    Raises:
        FileNotFoundError: ``path`` does not exist (the message names it).
        UntrustedInputError: unreadable, not a regular file, larger than ``max_bytes`` or not
            UTF-8; the message starts with ``"{what} {path}: "``.
    """
    path = Path(path)
    limit = LIMITS["max_bytes"] if max_bytes is None else max_bytes
    where = ceiling or "selenv.untrusted.LIMITS['max_bytes']"
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} {path} not found") from None
    except OSError as exc:
        raise UntrustedInputError(f"{what} {path}: cannot read it ({exc.strerror})") from None
    if not path.is_file():
        raise UntrustedInputError(f"{what} {path}: not a regular file")
    if size > limit:
        raise UntrustedInputError(
            f"{what} {path}: {size:,} bytes, more than the ceiling of {limit:,} ({where})"
        )
    try:
        return path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise UntrustedInputError(f"{what} {path}: cannot read it ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise UntrustedInputError(f"{what} {path}: not UTF-8 text ({exc})") from None


def read_json_file(path: str | Path, what: str) -> Any:
    """The parsed JSON file ``path``, bounded as :func:`loads_json` (messages ``"{what} {path}"``).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        UntrustedInputError: not a readable regular UTF-8 file, too large, too deep, not JSON.
    """
    return loads_json(read_text(path, what), f"{what} {path}", argument=False)


def _tomllib() -> Any:
    """``tomllib`` (Python >= 3.11) or its backport ``tomli`` (Python 3.10)."""
    try:
        import tomllib
    except ModuleNotFoundError:  # pragma: no cover - Python 3.10
        try:
            import tomli as tomllib  # type: ignore[no-redef]
        except ModuleNotFoundError:
            raise UntrustedInputError(
                "reading TOML needs Python >= 3.11 or the tomli package (pip install tomli)"
            ) from None
    return tomllib


def loads_toml(text: str, what: str) -> dict[str, Any]:
    """``tomllib.loads(text)``, size and nesting bounded (before and after parsing).

    Raises:
        UntrustedInputError: too large, nested deeper than ``max_depth`` (brackets, dotted
            keys or table headers), or not valid TOML (``"{what}: not a valid TOML file"``).
    """
    toml = _tomllib()
    _check_text(text, what, "max_bytes", toml_depth(text))
    try:
        data: dict[str, Any] = toml.loads(text)
    except RecursionError:  # brackets hidden from the scan by an odd string: still refused
        raise _too_deep(what) from None
    except toml.TOMLDecodeError as exc:
        raise NotParsedError(f"{what}: not a valid TOML file ({exc})") from None
    _check_depth(value_depth(data), what)
    return data


def read_toml_file(path: str | Path, what: str) -> dict[str, Any]:
    """The parsed TOML file ``path``, bounded as :func:`loads_toml`.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        UntrustedInputError: not a readable regular UTF-8 file, too large, too deep, not TOML.
    """
    return loads_toml(read_text(path, what), f"{what} {path}")
