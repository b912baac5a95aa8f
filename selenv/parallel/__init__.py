"""Parallel execution: the same seeded tasks in this process, a local pool or on Ray.

>>> from selenv.parallel import make_executor
>>> with make_executor("local") as ex:
...     ex.map(abs, [-1, 2, -3], progress=False)
[1, 2, 3]

See :mod:`selenv.parallel.executors` for the determinism contract and
:mod:`selenv.parallel.ray_session` for how Ray is started, joined and stopped.
"""

from selenv.parallel.cli import add_executor_arguments, executor_from_args
from selenv.parallel.errors import ExecutorError, WorkerDiedError
from selenv.parallel.executors import (
    EXECUTORS,
    Executor,
    LocalExecutor,
    ProcessExecutor,
    RayExecutor,
    TaskStopped,
    make_executor,
    max_pool_workers,
    stop_requested,
    stoppable,
)
from selenv.parallel.ray_session import INSTALL_HINT, check_address, ray_session, require_ray

__all__ = [
    "EXECUTORS",
    "INSTALL_HINT",
    "Executor",
    "ExecutorError",
    "LocalExecutor",
    "ProcessExecutor",
    "RayExecutor",
    "TaskStopped",
    "WorkerDiedError",
    "add_executor_arguments",
    "check_address",
    "executor_from_args",
    "make_executor",
    "max_pool_workers",
    "ray_session",
    "require_ray",
    "stop_requested",
    "stoppable",
]
