"""Where the shipped checkpoints are: the data package ``selenv.checkpoints``.

In a clone the files live in the top-level ``checkpoints/`` folder, which setuptools installs
as ``selenv.checkpoints`` (``setup.py``); :mod:`importlib.resources` finds them in an editable
install, a wheel install, and from any working directory.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["CHECKPOINT_PACKAGE", "checkpoint_dir", "checkpoint_path", "current_class_name"]

CHECKPOINT_PACKAGE = "selenv.checkpoints"


def current_class_name(name: object) -> object:
    """A class path recorded by selenv 0.1 (top-level ``learned.*``) under today's name.

    Checkpoint metadata names its classes (``"learned.rl.candidate_policy.CandidateScorer"``
    before the packages moved under ``selenv``); such names are compared as
    ``"selenv.learned...."``. Anything else is returned unchanged.
    """
    if isinstance(name, str) and name.startswith("learned."):
        return f"selenv.{name}"
    return name


def checkpoint_dir() -> Path:
    """The folder of the shipped checkpoints (a real directory: selenv is never zipped).

    Raises:
        RuntimeError: the package data is not on the file system (a zipped install).
    """
    root = resources.files(CHECKPOINT_PACKAGE)
    path = Path(str(root))
    if not path.is_dir():
        raise RuntimeError(f"selenv's checkpoints are not a folder on disk: {root!r}")
    return path


def checkpoint_path(name: str) -> Path:
    """Path of the shipped checkpoint file ``name`` (e.g. ``"ldmv.pt"``); it may not exist."""
    return checkpoint_dir() / name
