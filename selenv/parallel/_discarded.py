"""A process pool that selenv kills on purpose ends without a thread traceback.

When a map is stopped (SIGINT / SIGTERM) or a worker dies, :class:`selenv.parallel.ProcessExecutor`
kills the pool's workers (SIGKILL) and shuts the pool down. The pool's manager thread
(``concurrent.futures``' executor manager thread) can then find the workers' queues and pipes
gone under it and raise; Python prints that as ``Exception in thread ...`` and a traceback
(seen once in about 3,500 tests on a loaded machine, in a SIGTERM test of ``selenv bench
--executor process``), although the pool was discarded deliberately and nothing is lost: the
finished episodes were collected before the kill.

:func:`discard` records the manager thread of a pool that is being discarded; the
``threading.excepthook`` it installs (once) drops the uncaught exception of such a thread and
hands every other thread's to the hook that was in place before. Nothing else changes: a pool
that breaks on its own is still reported as a :class:`~selenv.parallel.WorkerDiedError` line.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable
from typing import Any

__all__ = ["discard", "install"]

_lock = threading.Lock()
_discarded: weakref.WeakSet[threading.Thread] = weakref.WeakSet()
_previous: Callable[[threading.ExceptHookArgs], Any] | None = None


def _hook(args: threading.ExceptHookArgs) -> None:
    """``threading.excepthook``: silent for a discarded pool's manager thread, else the previous."""
    if args.thread is not None and args.thread in _discarded:
        return
    (_previous or threading.__excepthook__)(args)


def install() -> None:
    """Put :func:`_hook` in front of the current ``threading.excepthook`` (idempotent)."""
    global _previous
    with _lock:
        if threading.excepthook is not _hook:
            _previous = threading.excepthook
            threading.excepthook = _hook


def discard(pool: object) -> None:
    """Record ``pool``'s manager thread as discarded before its workers are killed.

    ``pool`` is a :class:`concurrent.futures.ProcessPoolExecutor`; its manager thread is
    CPython's ``_executor_manager_thread`` attribute. Where a Python has no such attribute
    (or the pool never started one) nothing is recorded and a traceback may still be printed.
    """
    thread = getattr(pool, "_executor_manager_thread", None)
    if isinstance(thread, threading.Thread):
        install()
        with _lock:
            _discarded.add(thread)
