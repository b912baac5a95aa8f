"""Where the shipped checkpoints are on disk, for every layer (no torch, no numpy).

In a clone the files live in the top-level ``checkpoints/`` folder, which setuptools installs
as ``selenv.checkpoints`` (``setup.py``); :mod:`importlib.resources` finds them in an editable
install, a wheel install, and from any working directory. The learned side's loaders
(:mod:`selenv.learned.resources`) and the policy records' standings
(:mod:`selenv.families.policy`) both read them from here.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["CHECKPOINT_PACKAGE", "checkpoint_dir"]

CHECKPOINT_PACKAGE = "selenv.checkpoints"


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
