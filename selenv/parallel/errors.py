"""The one exception type of :mod:`selenv.parallel`."""

from __future__ import annotations

__all__ = ["ExecutorError"]


class ExecutorError(ValueError):
    """A bad executor choice: unknown name, Ray not installed, unreachable ``--address``.

    A :class:`ValueError`, so the command-line tools report it as a usage error (exit code 2);
    the message names the option and what to do (what to install, how to start a cluster).
    """
