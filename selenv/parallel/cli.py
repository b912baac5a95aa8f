"""The ``--executor`` / ``--address`` / ``--num-workers`` options, shared by every command."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from selenv.parallel.executors import EXECUTORS, Executor, make_executor

__all__ = ["add_executor_arguments", "executor_from_args"]


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {value}")
    return value


def add_executor_arguments(
    parser: argparse.ArgumentParser, *, default: str = "local", workers_alias: bool = False
) -> None:
    """Add ``--executor``, ``--address`` and ``--num-workers`` to ``parser``.

    Args:
        parser: the parser (or argument group) to extend.
        default: the default executor.
        workers_alias: also accept ``--workers`` for ``--num-workers`` (older scripts).
    """
    group = parser.add_argument_group("parallel execution")
    group.add_argument(
        "--executor",
        choices=list(EXECUTORS),
        default=default,
        help=f"where tasks run: local = this process, process = a pool of local processes, "
        f"ray = Ray tasks (a local Ray instance, or the cluster at --address); results are "
        f"identical for the same seeds (default: {default})",
    )
    group.add_argument(
        "--address",
        metavar="ADDR",
        help="join the Ray cluster at ADDR (HOST:PORT printed by `ray start --head`, "
        "ray://HOST:PORT or auto); only with --executor ray (default: start a local instance)",
    )
    flags = ["--num-workers", "--workers"] if workers_alias else ["--num-workers"]
    group.add_argument(
        *flags,
        dest="num_workers",
        type=_positive,
        metavar="N",
        help="tasks run at once (default: every CPU; ignored by --executor local)",
    )


def executor_from_args(
    args: argparse.Namespace,
    initializer: Callable[..., None] | None = None,
    initargs: tuple[Any, ...] = (),
) -> Executor:
    """The executor that ``args`` (from :func:`add_executor_arguments`) describe.

    ``--executor process --num-workers 1`` runs in this process (same results, no spawn).

    Raises:
        ExecutorError: ``--address`` without ``--executor ray``, or Ray not installed.
    """
    name = args.executor
    if name == "process" and args.num_workers == 1:
        name = "local"  # a pool of one process computes the same results, in this process
    return make_executor(
        name,
        num_workers=args.num_workers,
        address=args.address,
        initializer=initializer,
        initargs=initargs,
    )
