"""SIGINT and SIGTERM handling that never raises into native code; importable before the rest.

This module uses the standard library only, so that ``selenv/__init__`` can import it first:
a ``selenv`` command-line process installs its handlers here, a few milliseconds after exec,
before gymnasium, scipy, torch or the agents are imported (:func:`start_cli`).

:func:`on_signal` is the handler the commands install: in the main thread it raises
``KeyboardInterrupt`` for SIGINT (as Python's own handler does) and :class:`Terminated` for
SIGTERM, except inside a :func:`hold_signals` region, where it only records the signal; the
region raises the first recorded signal when it ends. Regions surround the work during which
native code runs Python code: importing torch or Ray (module initialisers of C++ extensions
call back into Python, and an exception raised there can abort the process with C++'s
``terminate``), loading agents and checkpoints, and a command's start-up.

A process started with SIGINT ignored (``nohup``, a background job of a non-interactive shell)
keeps it ignored, as shells and Python itself do: nothing here installs a SIGINT handler over
``SIG_IGN``. SIGTERM is always handled.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

__all__ = [
    "Terminated",
    "end_startup",
    "held",
    "hold_signals",
    "is_cli_process",
    "on_signal",
    "signal_exception",
    "start_cli",
]

#: the ``-m`` modules and console-script names that are the ``selenv`` command line
CLI_MODULES = frozenset({"selenv", "selenv.cli", "selenv.__main__"})
CLI_SCRIPTS = frozenset({"selenv", "selenv.exe", "selenv-script.py"})


class Terminated(BaseException):
    """SIGTERM, raised in the main thread like ``KeyboardInterrupt`` for SIGINT."""


_held = 0  # depth of hold_signals() regions (main thread)
_pending: list[int] = []  # signals received while held, in order
_startup = False  # the start-up hold of start_cli() is still open


def signal_exception(signum: int) -> BaseException:
    """The exception a signal stands for: ``KeyboardInterrupt`` or :class:`Terminated`."""
    return KeyboardInterrupt() if signum == signal.SIGINT else Terminated()


def held() -> bool:
    """Whether a :func:`hold_signals` region is active (signals are recorded, not raised)."""
    return _held > 0


def defer(signum: int) -> None:
    """Record ``signum`` to be raised when the outermost :func:`hold_signals` region ends."""
    _pending.append(signum)


def on_signal(signum: int, frame: FrameType | None) -> None:
    """Handler of SIGINT / SIGTERM: raise its exception, or record it inside a held region."""
    if _held:
        defer(signum)
        return
    raise signal_exception(signum)


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _release() -> None:
    """Leave one level of hold; at the outermost, raise the first signal received meanwhile."""
    global _held
    _held -= 1
    if _held == 0 and _pending:
        signum = _pending[0]
        _pending.clear()
        raise signal_exception(signum)


@contextmanager
def hold_signals() -> Iterator[None]:
    """While active, SIGINT and SIGTERM are recorded; the first is raised when it ends.

    For regions where native code may call Python code (imports of torch or Ray, building an
    agent, loading a checkpoint): a signal's exception raised there could abort the process.
    Regions nest (the outermost raises). Python's own SIGINT handler is replaced by
    :func:`on_signal` for the region; selenv's handlers (:func:`on_signal`,
    :class:`selenv.exits.DeferredSignals`) honour it; ignored signals stay ignored and other
    handlers are left alone. Outside the main thread this does nothing.

    Raises:
        KeyboardInterrupt | Terminated: on exit, if SIGINT / SIGTERM arrived meanwhile.
    """
    if not _main_thread():
        yield
        return
    global _held
    swapped = None
    if _held == 0 and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        swapped = signal.signal(signal.SIGINT, on_signal)
    _held += 1
    try:
        yield
    finally:
        if swapped is not None:
            signal.signal(signal.SIGINT, swapped)
        _release()


def is_cli_process() -> bool:
    """Whether this process is the ``selenv`` command (``python -m selenv`` or the script).

    Asked while ``selenv`` is first imported: ``sys.argv[0]`` is then still ``"-m"`` for
    ``python -m`` (the module is in ``sys.orig_argv``), or the console script's path.
    """
    argv0 = sys.argv[0] if sys.argv else ""
    if argv0 == "-m":
        args = list(getattr(sys, "orig_argv", []))
        for i, arg in enumerate(args):
            if arg == "-m" and i + 1 < len(args):
                return args[i + 1] in CLI_MODULES
            if arg.startswith("-m") and len(arg) > 2:
                return arg[2:] in CLI_MODULES
        return False
    return os.path.basename(argv0) in CLI_SCRIPTS


def start_cli() -> None:
    """In the ``selenv`` command's process: install the handlers now and hold the signals.

    Called first thing by ``selenv/__init__``; does nothing in any other process (a program
    importing selenv keeps its own handlers). SIGTERM gets :func:`on_signal`, and SIGINT too
    unless it was ignored on entry. The signals are held until the command's entry point
    calls :func:`end_startup`, which raises one received meanwhile.
    """
    global _held, _startup
    if _startup or not _main_thread() or not is_cli_process():
        return
    # hold first: a SIGTERM that arrives between the two installations is recorded, not raised
    # inside signal.signal() (seen: a Terminated traceback from the SIGINT installation)
    _held += 1
    _startup = True
    signal.signal(signal.SIGTERM, on_signal)
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        signal.signal(signal.SIGINT, on_signal)


def end_startup() -> None:
    """End the start-up hold of :func:`start_cli` (no-op if none is open).

    Raises:
        KeyboardInterrupt | Terminated: a signal received since the process started.
    """
    global _startup
    if _startup and _main_thread():
        _startup = False
        _release()
