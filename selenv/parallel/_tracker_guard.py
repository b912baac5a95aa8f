"""A process pool that outlives its resource tracker ends quietly (one warning line).

:mod:`multiprocessing` starts a *resource tracker* process the first time a pool creates its
named semaphores, and tells it when each is released (``UNREGISTER``). If that tracker dies
during a run (killed by hand, by an out-of-memory killer, by a process-group ``kill``), the
next release relaunches a fresh tracker, which never saw those names: it prints one stdlib
``KeyError`` traceback per semaphore, after a ``UserWarning`` about the relaunch, although
nothing is wrong (the semaphores themselves are unlinked by this process as usual).

:func:`install` wraps :func:`multiprocessing.resource_tracker.register` / ``unregister``:
registrations are remembered with the tracker they were sent to, and an ``UNREGISTER`` for a
tracker that is no longer running is dropped, with one line on stderr the first time
(``selenv: warning: ...``). Everything else goes to the stdlib functions unchanged.
"""

from __future__ import annotations

import sys
import threading
from multiprocessing import resource_tracker
from typing import Any

__all__ = ["install"]

_lock = threading.Lock()
_sent: dict[tuple[str, str], int | None] = {}  # (name, rtype) -> tracker pid it was sent to
_warned = False
_originals: tuple[Any, Any] | None = None


def _tracker() -> Any:
    return resource_tracker._resource_tracker


def _alive(pid: int | None) -> bool:
    """Whether the tracker that got a registration (``pid``) is the one still running."""
    tracker = _tracker()
    if pid is None or tracker._pid != pid:
        return False
    check = getattr(tracker, "_check_alive", None)
    return bool(check()) if callable(check) else True


def _register(name: str, rtype: str) -> None:
    assert _originals is not None  # internal invariant: set by install()
    _originals[0](name, rtype)
    with _lock:
        _sent[(name, rtype)] = _tracker()._pid


def _unregister(name: str, rtype: str) -> None:
    global _warned
    assert _originals is not None  # internal invariant: set by install()
    with _lock:
        pid = _sent.pop((name, rtype), -1)
    if pid == -1 or _alive(pid):  # not ours, or its tracker still runs: the stdlib's way
        _originals[1](name, rtype)
        return
    if not _warned:
        _warned = True
        print(
            "selenv: warning: the multiprocessing resource tracker of the process pool died "
            "during the run; its bookkeeping is skipped (the pool's semaphores are released "
            "as usual)",
            file=sys.stderr,
        )


def install() -> None:
    """Wrap the resource tracker's ``register`` / ``unregister`` (idempotent; POSIX only)."""
    global _originals
    if _originals is not None or sys.platform == "win32":
        return
    with _lock:
        if _originals is None:
            _originals = (resource_tracker.register, resource_tracker.unregister)
            resource_tracker.register = _register  # type: ignore[assignment]
            resource_tracker.unregister = _unregister  # type: ignore[assignment]
