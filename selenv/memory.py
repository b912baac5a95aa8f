"""How much memory is available now, for checks made before a large allocation.

:func:`available_memory` is what the native vector envs (:mod:`selenv.envs.vector_memory`) and
the raw-array FIM solvers (:mod:`selenv.agents.fim_solvers`) compare their estimates with, so
that a request that cannot fit is a ``ValueError`` up front, not a ``MemoryError`` (or the
out-of-memory killer) after seconds of work.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["available_memory", "human_bytes", "refuse_if_larger"]


def human_bytes(n: float) -> str:
    """``1.5 GB``-style size (powers of 1024, one decimal)."""
    for unit in ("B", "KB", "MB", "GB"):
        if abs(n) < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GB"  # pragma: no cover


def _meminfo_available() -> int | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def _cgroup_room() -> int | None:
    """What the cgroup v2 memory limit of this process still allows (``None``: no limit)."""
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit == "max":
            return None
        used = int(Path("/sys/fs/cgroup/memory.current").read_text().strip())
        return max(int(limit) - used, 0)
    except (OSError, ValueError):
        return None


def available_memory() -> tuple[int | None, str]:
    """``(bytes available now, where that number comes from)``; ``None`` when unknown."""
    free, room = _meminfo_available(), _cgroup_room()
    if room is not None and (free is None or room < free):
        return room, "the cgroup's memory.max"
    return free, "MemAvailable"


def refuse_if_larger(estimate: int, what: str) -> None:
    """Raise ``ValueError("{what} need about X, more than the Y of memory available (...)")``.

    Nothing is raised when ``estimate`` fits or the available memory is unknown.
    """
    free, source = available_memory()
    if free is not None and estimate > free:
        raise ValueError(
            f"{what} need about {human_bytes(estimate)}, more than the {human_bytes(free)} "
            f"of memory available ({source})"
        )
