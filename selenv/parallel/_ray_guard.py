"""Guard of an embedded Ray instance: its processes die with the selenv process that started it.

Ray ties most of an embedded instance's processes to the process that started it (the kernel
kills the GCS server, the raylet and the monitors when it dies, the workers follow the
raylet), but not the raylet's agents (dashboard agent, runtime-env agent): after a SIGKILL of
the starting process they wait about a minute for a GCS server that is gone. This script,
started by :func:`selenv.parallel.ray_session` right after the instance, closes that gap.

It reads ``PID START`` lines on stdin (``START``: the process's start time, field 22 of
``/proc/PID/stat``, so that a reused PID is never touched), then waits for the end of its input:
the pipe closes when the starting process ends the session or dies, however it dies. It then
SIGKILLs every listed process still running and exits. It runs in a session of its own, so a
Ctrl-C or a closed terminal that reaches the starting process's group does not end it first.
Linux only (``/proc``); run as a script (standard library only, nothing of selenv is
imported).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys


def start_time(pid: int) -> str | None:
    """Start time of the running process ``pid`` (``None``: gone, a zombie or unreadable)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    if len(fields) < 20 or fields[0] in ("Z", "X"):
        return None
    return fields[19]


def main() -> int:
    """Read the processes to guard, wait for the end of input, kill those still running."""
    targets: list[tuple[int, str]] = []
    for line in sys.stdin:
        parts = line.split()
        if len(parts) == 2 and parts[0].isdigit():
            targets.append((int(parts[0]), parts[1]))
    for pid, start in targets:
        if pid > 1 and pid != os.getpid() and start_time(pid) == start:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
    return 0


if __name__ == "__main__":
    sys.exit(main())
