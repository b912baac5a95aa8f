"""The exception types of :mod:`selenv.parallel`."""

from __future__ import annotations

__all__ = ["ExecutorError", "WorkerDiedError"]


class ExecutorError(ValueError):
    """A bad executor choice: unknown name, Ray not installed, unreachable ``--address``.

    A :class:`ValueError`, so the command-line tools report it as a usage error (exit code 2);
    the message names the option and what to do (what to install, how to start a cluster).
    """


class WorkerDiedError(RuntimeError):
    """A worker (a pool process, a Ray worker or node) died while the executor ran tasks.

    Raised by :meth:`~selenv.parallel.Executor.map` in place of ``BrokenProcessPool`` or Ray's
    ``WorkerCrashedError`` / ``NodeDiedError`` / ...; the message is one line naming what died
    (the worker's PID and signal when known). The results of the tasks that finished before
    were already passed to ``on_result``. A command reports it with exit code 1.
    """
