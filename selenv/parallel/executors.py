"""Executors: run independent, self-seeded tasks in this process, a local pool or on Ray.

Every executor has one method that matters, :meth:`Executor.map`: ``map(fn, tasks)`` returns
``[fn(t) for t in tasks]`` **in task order**, whatever order the workers finish in, with a
tqdm bar over the tasks (optionally weighted, e.g. by the episodes a task plays). The contract
that makes results bit-identical across executors is on the caller's side: each task carries
its own seed, derived from the master seed and the task's index (``seed + e`` for episode
``e``, ``SeedSequence(seed).spawn(n)[i]`` for sample block ``i``), never from the worker that
runs it or the order in which tasks complete. ``fn`` must be a module-level function and the
tasks picklable (they travel to other processes).

* :class:`LocalExecutor` (``"local"``, the default): a plain loop in this process.
* :class:`ProcessExecutor` (``"process"``): a :class:`~concurrent.futures.ProcessPoolExecutor`
  of ``num_workers`` *spawned* processes (no fork of a process that may hold threads), each
  with one BLAS / OpenMP thread.
* :class:`RayExecutor` (``"ray"``): Ray tasks of one CPU each, at most ``num_workers`` in
  flight (default: every CPU of the Ray instance); an embedded local Ray instance is started
  when no ``address`` is given and joined otherwise (:func:`~selenv.parallel.ray_session`).

An exception raised by ``fn`` in a worker is re-raised in the caller as itself (Ray's wrapper
is removed), after the outstanding tasks are cancelled. Executors are context managers; the
pool or the Ray instance they started is shut down on exit.
"""

from __future__ import annotations

import contextlib
import os
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from multiprocessing import get_context
from types import TracebackType
from typing import Any, TypeVar

from tqdm import tqdm

from selenv.parallel.errors import ExecutorError
from selenv.parallel.ray_session import ray_session

__all__ = [
    "EXECUTORS",
    "Executor",
    "LocalExecutor",
    "ProcessExecutor",
    "RayExecutor",
    "make_executor",
]

T = TypeVar("T")
R = TypeVar("R")

#: environment variables that cap the BLAS / OpenMP threads of a worker process
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _check_workers(num_workers: int | None) -> int | None:
    if num_workers is None:
        return None
    if isinstance(num_workers, bool) or not isinstance(num_workers, int) or num_workers < 1:
        raise ExecutorError(f"--num-workers must be an integer >= 1, got {num_workers!r}")
    return num_workers


def _weights(tasks: Sequence[Any], weights: Sequence[int] | None) -> list[int]:
    if weights is None:
        return [1] * len(tasks)
    if len(weights) != len(tasks):
        raise ValueError(f"weights has {len(weights)} entries for {len(tasks)} tasks")
    return [int(w) for w in weights]


class Executor(ABC):
    """Runs ``fn`` over tasks and returns the results in task order (see the module doc)."""

    #: the name under which :func:`make_executor` builds it
    name: str = ""

    def __init__(self, num_workers: int | None = None) -> None:
        self._num_workers = _check_workers(num_workers)

    @property
    def num_workers(self) -> int:
        """Tasks that may run at once (1 for :class:`LocalExecutor`)."""
        return self._num_workers or os.cpu_count() or 1

    def map(
        self,
        fn: Callable[[T], R],
        tasks: Sequence[T],
        *,
        desc: str | None = None,
        unit: str = "task",
        weights: Sequence[int] | None = None,
        progress: bool = True,
    ) -> list[R]:
        """``[fn(t) for t in tasks]``, computed by this executor's workers.

        Args:
            fn: a module-level function of one task (picklable for the pool and Ray).
            tasks: the tasks, each carrying its own seed.
            desc: label of the progress bar.
            unit: unit of the progress bar (``"ep"``, ``"sample"``, ...).
            weights: how far each finished task advances the bar (default 1 each).
            progress: show the bar (on stderr).

        Returns:
            The results, in the order of ``tasks``.
        """
        tasks = list(tasks)
        w = _weights(tasks, weights)
        with tqdm(total=sum(w), desc=desc, unit=unit, disable=not progress) as bar:
            return self._map(fn, tasks, w, bar)

    @abstractmethod
    def _map(self, fn: Callable[[T], R], tasks: list[T], weights: list[int], bar: tqdm) -> list[R]:
        """Run the tasks, advance ``bar`` by each finished task's weight, return in order."""

    def close(self) -> None:  # noqa: B027  (optional hook: only pools and Ray hold workers)
        """Release the workers (no-op for the local executor)."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def describe(self) -> dict[str, Any]:
        """Provenance: ``{"executor": name, "num_workers": n}`` (plus the Ray address)."""
        return {"executor": self.name, "num_workers": self.num_workers}


class LocalExecutor(Executor):
    """A loop in this process: the reference every other executor must reproduce."""

    name = "local"

    @property
    def num_workers(self) -> int:  # noqa: D102
        return 1

    def _map(self, fn: Callable[[T], R], tasks: list[T], weights: list[int], bar: tqdm) -> list[R]:
        out = []
        for task, w in zip(tasks, weights, strict=True):
            out.append(fn(task))
            bar.update(w)
        return out


@contextlib.contextmanager
def _single_threaded_children() -> Iterator[None]:
    """Set :data:`THREAD_VARS` to 1 while spawning (children read them before numpy loads)."""
    saved = {v: os.environ.get(v) for v in THREAD_VARS}
    os.environ.update(dict.fromkeys(THREAD_VARS, "1"))
    try:
        yield
    finally:
        for var, old in saved.items():
            if old is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = old


class ProcessExecutor(Executor):
    """A pool of ``num_workers`` spawned processes on this machine (default: every CPU).

    Args:
        num_workers: processes (default ``os.cpu_count()``).
        initializer: called once in each worker before its first task.
        initargs: arguments of ``initializer``.
    """

    name = "process"

    def __init__(
        self,
        num_workers: int | None = None,
        initializer: Callable[..., None] | None = None,
        initargs: tuple[Any, ...] = (),
    ) -> None:
        super().__init__(num_workers)
        self._initializer, self._initargs = initializer, initargs
        self._pool: ProcessPoolExecutor | None = None

    def _get_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            with _single_threaded_children():
                self._pool = ProcessPoolExecutor(
                    self.num_workers,
                    mp_context=get_context("spawn"),
                    initializer=self._initializer,
                    initargs=self._initargs,
                )
        return self._pool

    def _map(self, fn: Callable[[T], R], tasks: list[T], weights: list[int], bar: tqdm) -> list[R]:
        pool = self._get_pool()
        with _single_threaded_children():  # the pool spawns its workers lazily, on submit
            futures: dict[Future[R], int] = {pool.submit(fn, t): i for i, t in enumerate(tasks)}
        out: list[Any] = [None] * len(tasks)
        pending = set(futures)
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    i = futures[fut]
                    out[i] = fut.result()  # re-raises the worker's exception
                    bar.update(weights[i])
        except BaseException:
            for fut in pending:
                fut.cancel()
            raise
        return out

    def close(self) -> None:  # noqa: D102
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


def _ray_call(fn: Callable[[T], R], task: T) -> R:
    """Body of every Ray task (module-level so Ray pickles it by reference)."""
    return fn(task)


class RayExecutor(Executor):
    """Ray tasks of one CPU each, at most ``num_workers`` in flight.

    Args:
        num_workers: tasks in flight, and the CPUs of an embedded instance (default: every
            CPU Ray reports).
        address: ``None`` starts an embedded local Ray instance for the executor's lifetime;
            ``"HOST:PORT"`` / ``"ray://HOST:PORT"`` / ``"auto"`` joins a running cluster
            (whose nodes must have selenv installed).

    Raises:
        ExecutorError: Ray not installed, or ``address`` malformed or unreachable (checked when
            the executor starts, i.e. on ``__enter__`` or the first :meth:`map`).
    """

    name = "ray"

    def __init__(self, num_workers: int | None = None, address: str | None = None) -> None:
        super().__init__(num_workers)
        self.address = address
        self._session: contextlib.AbstractContextManager[Any] | None = None
        self._ray: Any = None

    def start(self) -> None:
        """Start or join Ray now (idempotent)."""
        if self._ray is None:
            session = ray_session(self.address, None if self.address else self._num_workers)
            self._ray = session.__enter__()
            self._session = session

    def __enter__(self) -> RayExecutor:
        self.start()
        return self

    @property
    def num_workers(self) -> int:  # noqa: D102
        if self._num_workers is not None:
            return self._num_workers
        if self._ray is not None:
            return max(1, int(self._ray.cluster_resources().get("CPU", 1)))
        return os.cpu_count() or 1

    def _map(self, fn: Callable[[T], R], tasks: list[T], weights: list[int], bar: tqdm) -> list[R]:
        self.start()
        ray = self._ray
        remote = ray.remote(num_cpus=1, max_retries=0)(_ray_call)
        fn_ref = ray.put(fn)
        out: list[Any] = [None] * len(tasks)
        index: dict[Any, int] = {}
        todo = iter(enumerate(tasks))
        limit = self.num_workers
        try:
            for i, task in todo:
                index[remote.remote(fn_ref, task)] = i
                if len(index) >= limit:
                    break
            while index:
                (ref,), _ = ray.wait(list(index), num_returns=1)
                i = index.pop(ref)
                try:
                    out[i] = ray.get(ref)
                except ray.exceptions.RayTaskError as err:
                    cause = getattr(err, "cause", None)
                    if isinstance(cause, BaseException):
                        raise cause from None
                    raise
                bar.update(weights[i])
                nxt = next(todo, None)
                if nxt is not None:
                    index[remote.remote(fn_ref, nxt[1])] = nxt[0]
        except BaseException:
            for ref in index:
                with contextlib.suppress(Exception):
                    ray.cancel(ref, force=True)
            raise
        return out

    def close(self) -> None:  # noqa: D102
        if self._session is not None:
            session, self._session, self._ray = self._session, None, None
            session.__exit__(None, None, None)

    def describe(self) -> dict[str, Any]:  # noqa: D102
        return {**super().describe(), "address": self.address}


#: executor name -> class
EXECUTORS: dict[str, type[Executor]] = {
    "local": LocalExecutor,
    "process": ProcessExecutor,
    "ray": RayExecutor,
}


def make_executor(
    name: str = "local",
    *,
    num_workers: int | None = None,
    address: str | None = None,
    initializer: Callable[..., None] | None = None,
    initargs: tuple[Any, ...] = (),
) -> Executor:
    """Build the executor ``name`` (``"local"``, ``"process"`` or ``"ray"``).

    Args:
        name: which executor.
        num_workers: parallel tasks (ignored by ``"local"``; default every CPU).
        address: Ray cluster to join (``"ray"`` only).
        initializer: called once per worker process before its tasks (``"process"`` only;
            Ray workers get one BLAS thread from Ray itself).
        initargs: arguments of ``initializer``.

    Raises:
        ExecutorError: unknown ``name``, ``address`` given for a non-Ray executor, bad
            ``num_workers``, or Ray not installed for ``"ray"``.
    """
    if name not in EXECUTORS:
        raise ExecutorError(
            f"--executor {name!r} is not one of: {', '.join(EXECUTORS)} (local = this "
            "process, process = a local pool, ray = Ray tasks)"
        )
    _check_workers(num_workers)
    if address is not None and name != "ray":
        raise ExecutorError(f"--address only applies to --executor ray (got --executor {name})")
    if name == "ray":
        from selenv.parallel.ray_session import require_ray

        require_ray()
        return RayExecutor(num_workers, address)
    if name == "process":
        return ProcessExecutor(num_workers, initializer, initargs)
    return LocalExecutor(num_workers)
