"""Reading untrusted torch files: tensors only, refused in one line naming the file and why.

Every ``.pth`` / ``.pt`` / optimizer state selenv reads goes through :func:`load_tensors`, that
is ``torch.load(weights_only=True)``: tensors and plain containers are rebuilt, any other
pickled object (a class, a function such as ``os.system``: the payload of a hostile file) is
refused **without being run**. torch explains such a refusal in a multi-line paragraph and
may warn about the pickle protocol first; here the refusal is one ``ValueError`` line::

    weights runs/m.pth are not a plain tensor file (unsupported GLOBAL posix.system whose
    module posix is blocked); refused, nothing in it was run
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path
from typing import Any

__all__ = ["load_tensors", "unpickling_reason"]

#: lines of torch's weights-only refusal that explain torch, not the file
_BOILERPLATE = (
    "weights only load failed",
    "please file an issue",
    "check the documentation",
    "re-running `torch.load`",
    "in pytorch 2.6",
)


def unpickling_reason(exc: BaseException) -> str:
    """The one clause of torch's refusal ``exc`` that names what the file holds.

    ``"unsupported GLOBAL posix.system whose module posix is blocked"`` out of torch's
    paragraph; the first line of any other message, or the exception's type name.
    """
    lines = [" ".join(line.split()) for line in str(exc).splitlines()]
    lines = [line for line in lines if line]
    useful = [
        line.removeprefix("WeightsUnpickler error:").strip()
        for line in lines
        if not any(line.lower().startswith(b) for b in _BOILERPLATE)
    ]
    useful = [line for line in useful if line]
    text = useful[0] if useful else (lines[0] if lines else type(exc).__name__)
    text = text.removeprefix("Trying to load ").rstrip(".")
    text = text[:1].lower() + text[1:]
    return text if len(text) <= 200 else text[:197] + "..."


def load_tensors(
    source: bytes | str | Path,
    what: str,
    *,
    verb: str = "is",
    kind: str = "a plain tensor file",
    junk: str = "a readable tensor file",
) -> Any:
    """``torch.load(source, weights_only=True)`` on CPU, every failure one ``ValueError`` line.

    Args:
        source: the file's bytes, or its path.
        what: how the message names the file (``"weights runs/m.pth"``).
        verb: ``"is"`` or ``"are"`` (``"weights ... are"``).
        kind: what a file holding other pickled objects is not (``"a plain tensor file"``).
        junk: what an empty, truncated or junk file is not (``"a readable tensor file"``).

    Raises:
        ValueError: ``"{what} is not a plain tensor file (unsupported GLOBAL posix.system
            ...); refused, nothing in it was run"`` for a file with other objects (a hostile
            pickle), ``"{what} is not a readable tensor file (...)"`` for a junk one.
    """
    import pickle

    import torch as th

    handle: Any = io.BytesIO(source) if isinstance(source, bytes) else source
    try:
        with warnings.catch_warnings():  # torch warns about the pickle protocol of odd files
            warnings.simplefilter("ignore")
            return th.load(handle, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise ValueError(
            f"{what} {verb} not {kind} ({unpickling_reason(exc)}); refused, nothing in it was run"
        ) from None
    except Exception as exc:  # empty, truncated or junk files: refuse, never fall back
        raise ValueError(f"{what} {verb} not {junk} ({unpickling_reason(exc)})") from None
