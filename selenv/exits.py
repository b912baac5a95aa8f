"""How a selenv command ends: one line and a conventional exit code, never a traceback.

:func:`guarded_main` runs a command's ``main`` and maps what can end it to the shell's
conventions:

==================================  =====  ==================================================
what happened                        exit   printed (stderr, one line)
==================================  =====  ==================================================
finished                             0      (the command's own output)
usage error found up front           2      ``prog: error: ...`` (argparse's form)
another run writes the same output   2      ``prog: error: <output> is being written by ...``
I/O failure (ENOSPC, EFBIG, ...)     1      ``prog: cannot write <file>: <cause> (<ERRNO>)``
SIGINT (Ctrl-C)                      130    ``prog: interrupted (SIGINT)``
SIGTERM                              143    ``prog: terminated (SIGTERM)``
==================================  =====  ==================================================

Commands that keep partial work (an interrupted bench, a training run) do so before these
exceptions reach :func:`guarded_main`; the line then says what was kept.

Signals never raise into native code: the handlers installed here raise only outside the
:func:`hold_signals` regions (torch imports, building agents, loading checkpoints, a
command's start-up), which raise a signal received inside them when they end (see
:mod:`selenv._signals`). A process started with SIGINT ignored keeps it ignored.

:func:`check_size` checks a typed size against its valid range and its work ceiling before
any work (the usage error names the option and, for a ceiling, the option that lifts it).
"""

from __future__ import annotations

import math
import signal
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

from selenv._signals import (
    Terminated,
    defer,
    end_startup,
    held,
    hold_signals,
    on_signal,
    signal_exception,
)
from selenv.atomic import OutputBusyError, describe_os_error

__all__ = [
    "DeferredSignals",
    "Terminated",
    "UsageError",
    "check_size",
    "end_startup",
    "guarded_main",
    "hold_signals",
    "sigterm_raises",
]


class UsageError(ValueError):
    """A usage error found before any work: exit 2 with ``prog: error: <message>``."""


def _number(value: float) -> str:
    """``1,000,000`` for ints, ``0.5`` / ``nan`` for floats (for messages)."""
    return f"{value:,}" if isinstance(value, int) else f"{value:,g}"


def check_size(
    option: str,
    value: float,
    *,
    low: float | None = None,
    high: float | None = None,
    ceiling: float | None = None,
    lifted: bool = False,
    lift: str = "--allow-large",
    unit: str = "",
    note: str = "",
) -> None:
    """Check a value the user typed before any work; a :class:`UsageError` naming ``option``.

    ``low`` / ``high`` bound what can run at all (validity: never lifted; NaN and infinities
    are refused whenever a bound is given). ``ceiling`` bounds the work or memory a size
    multiplies: above it the message names the ceiling and ``lift``, the option that lifts it,
    unless ``lifted``. ``unit`` follows every number (e.g. ``" MiB"``), ``note`` ends the
    message (what the number is, why the bound).

    Raises:
        UsageError: ``"<option>: must be in [low, high], got <value>"`` or
            ``"<option>: <value> exceeds the ceiling of <ceiling>; pass <lift> ..."``.
    """
    bounded = low is not None or high is not None
    if bounded and not math.isfinite(value):
        ok = False
    else:
        ok = (low is None or value >= low) and (high is None or value <= high)
    if not ok:
        if low is not None and high is not None:
            where = f"in [{_number(low)}, {_number(high)}]{unit}"
        elif low is not None:
            where = f">= {_number(low)}{unit}"
        else:
            where = f"<= {_number(high)}{unit}"  # type: ignore[arg-type]
        raise UsageError(f"{option}: must be {where}, got {_number(value)}{unit}{note}")
    if ceiling is not None and value > ceiling and not lifted:
        raise UsageError(
            f"{option}: {_number(value)}{unit} exceeds the ceiling of {_number(ceiling)}{unit}"
            f"{note}; pass {lift} to run it anyway"
        )


@contextmanager
def sigterm_raises() -> Iterator[None]:
    """While active, SIGTERM raises :class:`Terminated` in the main thread (restored after).

    Inside a :func:`hold_signals` region the exception waits until the region ends.
    """
    try:
        previous = signal.signal(signal.SIGTERM, on_signal)
    except ValueError:  # not the main thread: leave SIGTERM alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class DeferredSignals:
    """While active (``with``), SIGINT and SIGTERM are recorded instead of raised.

    A long run checks :attr:`signal` at its safe points (after an episode, an update, an
    epoch) and stops there, keeping its completed work; a writer holds the signals until its
    files are in place. With ``second_raises`` (the default) a second signal raises at once
    (``KeyboardInterrupt`` / :class:`Terminated`; at the end of a :func:`hold_signals` region
    inside one), abandoning the run; atomic writes keep the files intact. SIGINT ignored on
    entry stays ignored (a run under ``nohup`` stops on SIGTERM). Outside the main thread
    nothing is installed. The previous handlers are restored on exit.

    Attributes:
        signal: the first signal's name (``"SIGINT"`` / ``"SIGTERM"``), else ``None``.
        received: every signal number received, in order.
    """

    def __init__(self, *, second_raises: bool = True) -> None:
        self.second_raises = second_raises
        self.signal: str | None = None
        self.received: list[int] = []
        self._previous: dict[int, Any] = {}

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.signal is not None and self.second_raises:
            if held():
                defer(signum)
                return
            raise signal_exception(signum)
        self.received.append(signum)
        if self.signal is None:
            self.signal = signal.Signals(signum).name

    def __enter__(self) -> DeferredSignals:
        for signum in (signal.SIGINT, signal.SIGTERM):
            try:
                if signum == signal.SIGINT and signal.getsignal(signum) is signal.SIG_IGN:
                    continue  # ignored on entry (nohup, a background job): stays ignored
                self._previous[signum] = signal.signal(signum, self._handle)
            except ValueError:  # not the main thread: signals unchanged
                break
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous.clear()


def guarded_main(main: Callable[..., Any], prog: str, *args: Any, **kwargs: Any) -> int:
    """Run ``main(*args, **kwargs)``; return the exit code of the table above.

    ``main`` may return an int exit code (``None`` is 0) or raise ``SystemExit`` (argparse's
    usage errors, passed through).
    """
    try:
        with sigterm_raises():
            end_startup()  # a signal received since the process started stops it here
            result = main(*args, **kwargs)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted (SIGINT)", file=sys.stderr)
        return 130
    except Terminated:
        print(f"{prog}: terminated (SIGTERM)", file=sys.stderr)
        return 143
    except (UsageError, OutputBusyError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"{prog}: {describe_os_error(exc)}", file=sys.stderr)
        return 1
    return int(result) if isinstance(result, int) else 0
