"""Where a benchmark result came from: versions, commit, platform, command line, time.

:func:`provenance` never fails: anything it cannot find (not a git checkout, no ``git``, a
package that is not installed) is ``None``.
"""

from __future__ import annotations

import platform
import subprocess
import sys
from collections.abc import Sequence
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

import selenv

__all__ = ["PACKAGES", "git_commit", "provenance"]

#: distributions whose installed version is recorded
PACKAGES = (
    "numpy",
    "scipy",
    "gymnasium",
    "pettingzoo",
    "stable_baselines3",
    "sb3_contrib",
    "torch",
)


def _git(args: list[str], cwd: Path) -> str | None:
    try:
        proc = subprocess.run(
            ["git", *args], cwd=cwd, capture_output=True, text=True, timeout=10, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return proc.stdout.strip() if proc.returncode == 0 else None


def git_commit() -> tuple[str | None, bool | None]:
    """``(HEAD commit, dirty)`` of the git checkout selenv is imported from, else ``(None, None)``.

    Only the repository whose top level holds the imported ``selenv`` package counts (an
    installed copy inside some other repository gives ``None``). ``dirty``: tracked files
    differ from ``HEAD``.
    """
    root = Path(selenv.__file__).resolve().parent.parent
    top = _git(["rev-parse", "--show-toplevel"], root)
    if top is None or Path(top).resolve() != root:
        return None, None
    commit = _git(["rev-parse", "HEAD"], root)
    status = _git(["status", "--porcelain", "--untracked-files=no"], root)
    return commit, (None if status is None else bool(status))


def _version(dist: str) -> str | None:
    for name in (dist, dist.replace("_", "-")):
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return None


def provenance(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """The provenance block of the bench JSON.

    Args:
        argv: the command line (default ``sys.argv``).

    Returns:
        ``{"selenv_version", "git_commit", "git_dirty", "python", "platform", "packages":
        {name: version or None}, "argv", "timestamp"}``.
    """
    commit, dirty = git_commit()
    return {
        "selenv_version": selenv.__version__,
        "git_commit": commit,
        "git_dirty": dirty,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "packages": {name: _version(name) for name in PACKAGES},
        "argv": list(sys.argv if argv is None else argv),
        "timestamp": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
