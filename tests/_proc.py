"""Every child process the tests start: default signal dispositions and a deadline on every wait.

A test suite launched as a background job of a non-interactive shell (``nohup make test &``,
some CI runners) starts with SIGINT and SIGQUIT ignored, and an ignored disposition survives
``fork`` and ``exec``: a child ``selenv bench`` would then never see the Ctrl-C a test sends
it, and a test reading its stderr would wait forever. So every child started here gets the
default disposition of SIGINT and SIGQUIT (a Python child then installs its
``KeyboardInterrupt`` handler as it does in a terminal); SIGHUP stays as inherited (``nohup``
ignores it on purpose). Every wait and read has a deadline: past it the child is killed and
the test fails naming the command.

Use :func:`popen` / :func:`run` instead of :mod:`subprocess`'s (a test in ``test_proc.py``
checks that no test file calls :mod:`subprocess` directly), and :func:`communicate`,
:func:`wait`, :func:`readline` and :func:`stop` on what :func:`popen` returns.
"""

from __future__ import annotations

import os
import selectors
import signal
import subprocess
import time
from collections.abc import Callable, Sequence
from typing import Any

import pytest

#: the signals a child always starts with at their default disposition
DEFAULT_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGQUIT)
#: a generous deadline for a child's whole run (a hang guard, not a timing)
TIMEOUT = 120.0


def _child_defaults(then: Callable[[], object] | None) -> Callable[[], None]:
    """A ``preexec_fn``: default SIGINT / SIGQUIT in the child, then ``then`` (the caller's)."""

    def reset() -> None:
        for signum in DEFAULT_SIGNALS:
            signal.signal(signum, signal.SIG_DFL)
        if then is not None:
            then()

    return reset


def _name(args: Any) -> str:
    """The command for a failure message (its first words)."""
    words = [args] if isinstance(args, (str, bytes, os.PathLike)) else list(args)
    text = " ".join(os.fsdecode(w) if not isinstance(w, str) else w for w in words)
    return text if len(text) <= 160 else text[:157] + "..."


def popen(args: Sequence[Any] | str, **kwargs: Any) -> subprocess.Popen[Any]:
    """:class:`subprocess.Popen` with SIGINT and SIGQUIT at their defaults in the child.

    A ``preexec_fn`` of the caller runs after the reset; every other keyword is Popen's.
    """
    kwargs["preexec_fn"] = _child_defaults(kwargs.get("preexec_fn"))
    return subprocess.Popen(args, **kwargs)


def stop(proc: subprocess.Popen[Any], timeout: float = 30.0) -> None:
    """Kill ``proc`` if it still runs and reap it (for ``finally`` blocks); never blocks long."""
    if proc.poll() is None:
        proc.kill()
    try:
        proc.communicate(timeout=timeout)
    except (subprocess.TimeoutExpired, ValueError):  # ValueError: its pipes already closed
        proc.wait(timeout=timeout)


def _timed_out(proc: subprocess.Popen[Any], what: str, timeout: float) -> None:
    stop(proc)
    pytest.fail(f"{_name(proc.args)}: {what} took longer than {timeout:g} s (killed)")


def communicate(
    proc: subprocess.Popen[Any], timeout: float = TIMEOUT, input: Any = None
) -> tuple[Any, Any]:
    """``proc.communicate`` with a deadline: past it, the child is killed and the test fails."""
    try:
        return proc.communicate(input, timeout=timeout)
    except subprocess.TimeoutExpired:
        _timed_out(proc, "the run", timeout)
        raise AssertionError("unreachable") from None


def wait(proc: subprocess.Popen[Any], timeout: float = TIMEOUT) -> int:
    """``proc.wait`` with a deadline: past it, the child is killed and the test fails."""
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        _timed_out(proc, "the exit", timeout)
        raise AssertionError("unreachable") from None


def readline(proc: subprocess.Popen[Any], timeout: float = TIMEOUT, stream: Any = None) -> Any:
    """One line of the child's ``stream`` (default: its stderr) within ``timeout`` seconds.

    Reads the pipe itself, a byte at a time after a ``select`` (POSIX), so a child that never
    writes its line fails the test instead of blocking it, and a later :func:`communicate`
    (which reads the pipe's descriptor too) gets everything after the line. Returns ``""``
    (``b""`` for a binary pipe) at end of file.
    """
    stream = proc.stderr if stream is None else stream
    if stream is None:
        raise ValueError("readline: the child has no such pipe (pass stderr=subprocess.PIPE)")
    fd = stream.fileno()
    deadline = time.monotonic() + timeout
    data = bytearray()
    with selectors.DefaultSelector() as sel:
        sel.register(fd, selectors.EVENT_READ)
        while not data.endswith(b"\n"):
            left = deadline - time.monotonic()
            if left <= 0 or not sel.select(left):
                _timed_out(proc, "waiting for a line of output", timeout)
            byte = os.read(fd, 1)
            if not byte:
                break
            data += byte
    return data.decode(errors="replace") if proc.text_mode else bytes(data)


def run(
    args: Sequence[Any] | str, *, timeout: float = TIMEOUT, **kwargs: Any
) -> subprocess.CompletedProcess[Any]:
    """:func:`subprocess.run` through :func:`popen`, with a deadline on the whole run.

    ``check`` is honoured; ``capture_output`` is Popen's ``stdout=stderr=PIPE``.
    """
    check = kwargs.pop("check", False)
    if kwargs.pop("capture_output", False):
        kwargs["stdout"] = kwargs["stderr"] = subprocess.PIPE
    input_ = kwargs.pop("input", None)
    if input_ is not None:
        kwargs["stdin"] = subprocess.PIPE
    proc = popen(args, **kwargs)
    try:
        out, err = communicate(proc, timeout, input_)
    finally:
        if proc.poll() is None:
            stop(proc)
    done = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    if check:
        done.check_returncode()
    return done
