"""Where the shipped checkpoints are, and how untrusted checkpoint metadata is read.

In a clone the files live in the top-level ``checkpoints/`` folder, which setuptools installs
as ``selenv.checkpoints`` (``setup.py``); :mod:`importlib.resources` finds them in an editable
install, a wheel install, and from any working directory.

A checkpoint's JSON metadata decides what a loader builds (layer widths, pool sizes, ...), so
it is treated as untrusted input and bounded **before anything is allocated**:

* :func:`read_metadata` refuses a file larger than ``max_metadata_bytes`` and JSON nested
  deeper than ``max_metadata_depth`` (found by :func:`selenv.untrusted.json_depth`, a linear,
  non-recursive scan before parsing, so a file nested 10^5 deep is a ``ValueError``, never a
  ``RecursionError``);
* :func:`bounded_int`, :func:`bounded_widths` and :func:`check_parameter_count` hold every
  size against :data:`CHECKPOINT_LIMITS`, with a ``ValueError`` naming the file, the field, the
  value and the ceiling.

The ceilings are far above every shipped checkpoint (widths <= 128, pools <= 1,336 candidates,
<= 60,000 parameters). To load a larger trusted checkpoint, raise the entry in
:data:`CHECKPOINT_LIMITS` before loading it, e.g.
``selenv.learned.resources.CHECKPOINT_LIMITS["max_parameters"] = 50_000_000`` (together with
the weights-file limit ``MAX_WEIGHTS_BYTES`` of the loader if the file is larger).
"""

from __future__ import annotations

import json
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

from selenv.shipped import CHECKPOINT_PACKAGE, checkpoint_dir
from selenv.untrusted import json_depth, read_text

__all__ = [
    "CHECKPOINT_LIMITS",
    "CHECKPOINT_PACKAGE",
    "bounded_int",
    "bounded_widths",
    "check_parameter_count",
    "checkpoint_dir",
    "checkpoint_path",
    "current_class_name",
    "json_depth",
    "limit_hint",
    "mlp_parameters",
    "read_metadata",
]


#: Ceilings on what checkpoint metadata may ask a loader to build (read at call time, so a
#: caller that trusts a larger file can raise an entry first):
#:
#: ``max_metadata_bytes``
#:     size of a metadata JSON file (shipped ones: 3-17 KB);
#: ``max_metadata_depth``
#:     nesting depth of its JSON (shipped ones: <= 8);
#: ``max_width``
#:     any layer width (``hidden``, ``vf``) and the edit scorer's ``rank``;
#: ``max_layers``
#:     the number of layers of ``hidden`` and of ``vf``;
#: ``max_parameters``
#:     the parameter count the architecture implies (16 Mi float32 = the 64 MiB weights-file
#:     limit of the loaders);
#: ``max_candidates``
#:     ``obs_layout.n_candidates_trained``, the pool the policy is built for;
#: ``max_candidate_width``
#:     ``obs_layout.whitened_dim``, ``m``, ``d`` and ``n_features``;
#: ``max_observation_entries``
#:     ``n_candidates_trained * whitened_dim``, the size of the largest observation array.
CHECKPOINT_LIMITS: dict[str, int] = {
    "max_metadata_bytes": 4 * 2**20,
    "max_metadata_depth": 64,
    "max_width": 4096,
    "max_layers": 16,
    "max_parameters": 16 * 2**20,
    "max_candidates": 100_000,
    "max_candidate_width": 4096,
    "max_observation_entries": 2**24,
}


#: modules whose classes checkpoints recorded before the module moved: old prefix -> new prefix
MOVED_CLASS_MODULES = {
    "selenv.learned.rl.edit_policy.": "selenv.learned.families.clustering_edits.",
}


def current_class_name(name: object) -> object:
    """A class path recorded by an earlier selenv under today's name.

    Checkpoint metadata names its classes (``"learned.rl.candidate_policy.CandidateScorer"``
    before the packages moved under ``selenv``; ``"selenv.learned.rl.edit_policy.*"`` before
    the module moved, ``MOVED_CLASS_MODULES``); such names are compared as today's.
    Anything else is returned unchanged.
    """
    if not isinstance(name, str):
        return name
    if name.startswith("learned."):
        name = f"selenv.{name}"
    for old, new in MOVED_CLASS_MODULES.items():
        if name.startswith(old):
            return new + name[len(old) :]
    return name


def checkpoint_path(name: str) -> Path:
    """Path of the shipped checkpoint file ``name`` (e.g. ``"ldmv.pt"``); it may not exist."""
    return checkpoint_dir() / name


def shipped_checkpoint(name: object) -> Path:
    """Path of the shipped checkpoint ``name``, a plain file name in ``checkpoints/``.

    Raises:
        ValueError: ``name`` is not a non-empty file name without a folder.
    """
    if not isinstance(name, str) or not name or Path(name).name != name:
        raise ValueError(f"shipped must be a file name in checkpoints/, got {name!r}")
    return checkpoint_path(name)


def with_shipped(shipped: object, kwargs: dict[str, Any]) -> dict[str, Any]:
    """``kwargs`` of a learned agent with ``checkpoint`` set from ``shipped`` (if given).

    Raises:
        ValueError: ``shipped`` is not a plain file name, or ``checkpoint`` is given too.
    """
    if shipped is None:
        return kwargs
    path = shipped_checkpoint(shipped)
    if kwargs.get("checkpoint") is not None:
        raise ValueError("give checkpoint= or shipped=, not both")
    return {**kwargs, "checkpoint": path}


def limit_hint(key: str) -> str:
    """``"the ceiling N (selenv.learned.resources.CHECKPOINT_LIMITS['key'])"`` for messages."""
    return f"the ceiling {CHECKPOINT_LIMITS[key]:,} ({__name__}.CHECKPOINT_LIMITS[{key!r}])"


def read_metadata(path: str | Path, what: str = "checkpoint metadata") -> Any:
    """The parsed JSON of the untrusted metadata file ``path``, size and depth bounded.

    Args:
        path: the JSON file.
        what: how messages name the file (``"checkpoint metadata"``).

    Raises:
        FileNotFoundError: ``path`` does not exist (the message names it).
        ValueError: not a regular file, larger than ``max_metadata_bytes``, not UTF-8, nested
            deeper than ``max_metadata_depth`` ("metadata nested deeper than N"), or not valid
            JSON; each message names the file.
    """
    path = Path(path)
    text = read_text(
        path,
        what,
        max_bytes=CHECKPOINT_LIMITS["max_metadata_bytes"],
        ceiling=f"{__name__}.CHECKPOINT_LIMITS['max_metadata_bytes']",
    )
    limit = CHECKPOINT_LIMITS["max_metadata_depth"]
    if json_depth(text) > limit:
        raise ValueError(
            f"{what} {path}: metadata nested deeper than {limit} levels "
            f"({__name__}.CHECKPOINT_LIMITS['max_metadata_depth'])"
        )
    try:
        return json.loads(text)
    except RecursionError:  # unreachable after the scan; kept so no loader ever sees it
        raise ValueError(f"{what} {path}: metadata nested deeper than {limit} levels") from None
    except ValueError as exc:  # JSONDecodeError, and ints beyond the digit limit
        raise ValueError(f"{what} {path} is not valid JSON: {exc}") from None


def _is_int(value: object) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def bounded_int(value: object, field: str, key: str, source: str = "checkpoint") -> int:
    """``value`` as an int in ``1 .. CHECKPOINT_LIMITS[key]``.

    Raises:
        ValueError: not an integer, below 1 or above the ceiling; names ``source``, the
            ``field``, the value and the ceiling.
    """
    if not _is_int(value):
        raise ValueError(f"{source}: {field} must be a positive integer, got {value!r:.80}")
    number = int(value)  # type: ignore[call-overload]
    if number < 1:
        raise ValueError(f"{source}: {field} must be a positive integer, got {number}")
    if number > CHECKPOINT_LIMITS[key]:
        raise ValueError(f"{source}: {field}={number:,} exceeds {limit_hint(key)}")
    return number


def bounded_widths(
    value: object, field: str, source: str = "checkpoint", *, allow_empty: bool = False
) -> list[int]:
    """``value`` as a list of layer widths, each and their count within the ceilings.

    Raises:
        ValueError: not a list (or tuple), empty (unless ``allow_empty``), more than
            ``max_layers`` entries or a width outside ``1 .. max_width``; names the field.
    """
    if not isinstance(value, list | tuple):
        raise ValueError(f"{source}: {field} must be a list of layer widths, got {value!r:.80}")
    if not value and not allow_empty:
        raise ValueError(f"{source}: {field} must hold at least one layer width")
    if len(value) > CHECKPOINT_LIMITS["max_layers"]:
        raise ValueError(
            f"{source}: {field} has {len(value):,} layers, more than {limit_hint('max_layers')}"
        )
    return [bounded_int(w, f"{field}[{k}]", "max_width", source) for k, w in enumerate(value)]


def mlp_parameters(widths: list[int]) -> int:
    """Weights and biases of the dense chain ``widths[0] -> widths[1] -> ...``."""
    return sum((a + 1) * b for a, b in pairwise(widths))


def check_parameter_count(count: int, source: str = "checkpoint") -> None:
    """Refuse an architecture of more than ``max_parameters`` parameters (before building it).

    Raises:
        ValueError: naming the estimate and the ceiling.
    """
    if count > CHECKPOINT_LIMITS["max_parameters"]:
        raise ValueError(
            f"{source}: the architecture in its metadata has about {count:,} parameters, "
            f"more than {limit_hint('max_parameters')}"
        )
