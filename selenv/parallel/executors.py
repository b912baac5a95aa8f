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

Failures and interruptions (``on_result=`` of :meth:`Executor.map` receives each task's result
as it finishes, so a caller keeps what finished whatever happens next):

* a worker that dies (killed, out of memory) ends :meth:`~Executor.map` with
  :class:`~selenv.parallel.errors.WorkerDiedError`, one line naming what died (for the pool:
  the worker's PID and signal; for Ray: the worker's PID and Ray's exit detail, or the node
  that stopped and why, e.g. a raylet agent it fate-shares with was killed), instead of
  ``BrokenProcessPool`` / ``WorkerCrashedError`` / ``NodeDiedError``. A Ray map never puts
  objects into Ray's object store itself (``fn`` travels with each task), so a Ray node that
  dies ends the map with that error instead of ending this process;
* ``KeyboardInterrupt`` (or another ``BaseException`` such as a SIGTERM exception) in the
  caller during a pool's :meth:`~Executor.map`: the tasks not started are cancelled, the
  workers are asked to stop (SIGUSR1: a task inside :func:`stoppable` gets
  :class:`TaskStopped` and may return what it has; later tasks see :func:`stop_requested`),
  the results that arrive within ``STOP_GRACE_SECONDS`` go to ``on_result``, the workers still
  running are killed, and the exception is re-raised. Ray tasks are cancelled (their workers
  killed); a SIGTERM while Ray waits reaches the caller's SIGTERM handler (Ray itself would
  drop the exception such a handler raises, see :class:`_RaySignals`);
* pool workers never print a ``KeyboardInterrupt`` traceback (a Ctrl-C that reaches the whole
  process group is a stop request to them, ignored if this process ignores SIGINT), and they
  die with their parent (Linux ``PR_SET_PDEATHSIG``; elsewhere a watchdog thread), so none is
  left orphaned;
* ``--num-workers`` of the process pool is bounded by :func:`max_pool_workers`.

Test hook (for the fault-injection tests of ``--executor ray``; no effect unless both
variables are set in the process that calls :meth:`~Executor.map`):
``SELENV_TEST_RAY_HOLD_FROM_TASK=K`` and ``SELENV_TEST_RAY_HOLD_DIR=DIR`` make the Ray tasks
of index ``K`` and above write their worker's PID to ``DIR/task-<index>.pid`` and then wait
until they are killed or cancelled, so a test knows that tasks ``0 .. K-1`` were handed to
``on_result`` (at most ``num_workers`` tasks are in flight) and which processes run the rest.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import importlib
import os
import signal
import sys
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context
from types import FrameType, TracebackType
from typing import Any, TypeVar

from tqdm import tqdm

from selenv.exits import DeferredSignals, hold_signals
from selenv.parallel import _discarded, _tracker_guard
from selenv.parallel.errors import ExecutorError, WorkerDiedError
from selenv.parallel.ray_session import ray_session

__all__ = [
    "EXECUTORS",
    "Executor",
    "LocalExecutor",
    "ProcessExecutor",
    "RayExecutor",
    "TaskStopped",
    "in_pool_worker",
    "make_executor",
    "max_pool_workers",
    "stop_requested",
    "stoppable",
]

T = TypeVar("T")
R = TypeVar("R")

#: environment variables that cap the BLAS / OpenMP threads of a worker process
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


#: seconds a pool's workers get to return what they have after a stop request
STOP_GRACE_SECONDS = 5.0
#: processes per CPU a pool may have (a larger ``--num-workers`` is a usage error)
POOL_WORKERS_PER_CPU = 8


def max_pool_workers() -> int:
    """The largest ``--num-workers`` of ``--executor process``: 8 per CPU (at least 16).

    More processes than that only add memory and start-up time on one machine; a cluster is
    what ``--executor ray`` is for.
    """
    return max(16, POOL_WORKERS_PER_CPU * (os.cpu_count() or 1))


# --- inside a pool worker ---------------------------------------------------------------------

_in_worker = False  # this process is a pool worker (set by _worker_init)
_stop = False  # the parent asked this worker to stop
_stop_raised = False  # TaskStopped was raised once already
_in_task = 0  # depth of stoppable() blocks


class TaskStopped(BaseException):
    """Raised inside a :func:`stoppable` block of a pool worker when its parent asks it to stop.

    A ``BaseException`` (like ``KeyboardInterrupt``), raised at most once per worker; the task
    catches it and returns what it finished. Never raised outside a pool worker.
    """


def in_pool_worker() -> bool:
    """Whether this process is a worker of a :class:`ProcessExecutor` pool."""
    return _in_worker


def stop_requested() -> bool:
    """Whether this process is a pool worker whose parent asked it to stop.

    Check it between units of work; always ``False`` in the main process.
    """
    return _stop


@contextlib.contextmanager
def stoppable() -> Iterator[None]:
    """Mark a task's work as interruptible by its pool's stop request.

    In a pool worker a stop request raises :class:`TaskStopped` inside the block (outside one
    it only sets :func:`stop_requested`). A no-op in the main process (there
    ``KeyboardInterrupt`` propagates as usual).
    """
    global _in_task
    _in_task += 1
    try:
        yield
    finally:
        _in_task -= 1


def _on_stop_signal(signum: int, frame: FrameType | None) -> None:
    global _stop, _stop_raised
    _stop = True
    if _in_task and not _stop_raised:
        _stop_raised = True
        raise TaskStopped()


def _watch_parent(parent: int) -> None:
    while True:
        if os.getppid() != parent:
            os._exit(1)
        time.sleep(0.5)


def _die_with_parent(parent: int) -> None:
    """Make this process die when ``parent`` does (SIGKILL from the kernel on Linux)."""
    armed = False
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            armed = libc.prctl(1, int(signal.SIGKILL), 0, 0, 0) == 0  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            armed = False
    if os.getppid() != parent:  # the parent died before the prctl
        os._exit(1)
    if not armed:
        threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()


def _worker_init(
    parent: int,
    initializer: Callable[..., None] | None,
    initargs: tuple[Any, ...],
    ignore_sigint: bool = False,
) -> None:
    """Set up a pool worker, then run the user's initializer.

    The worker dies with ``parent``; SIGUSR1 (the parent's stop request) and SIGINT (a Ctrl-C
    to the process group; ignored if the parent ignores it) stop its task.
    """
    global _in_worker
    _in_worker = True
    _die_with_parent(parent)
    signal.signal(signal.SIGUSR1, _on_stop_signal)
    signal.signal(signal.SIGINT, signal.SIG_IGN if ignore_sigint else _on_stop_signal)
    if initializer is not None:
        initializer(*initargs)


# --- in the caller ----------------------------------------------------------------------------


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
        on_result: Callable[[int, R], object] | None = None,
    ) -> list[R]:
        """``[fn(t) for t in tasks]``, computed by this executor's workers.

        Args:
            fn: a module-level function of one task (picklable for the pool and Ray).
            tasks: the tasks, each carrying its own seed.
            desc: label of the progress bar.
            unit: unit of the progress bar (``"ep"``, ``"sample"``, ...).
            weights: how far each finished task advances the bar (default 1 each).
            progress: show the bar (on stderr).
            on_result: called with ``(index, result)`` as each task finishes (in completion
                order), so the caller keeps the finished results if the map is interrupted or
                a worker dies.

        Returns:
            The results, in the order of ``tasks``.

        Raises:
            WorkerDiedError: a worker died (module docstring).
        """
        tasks = list(tasks)
        w = _weights(tasks, weights)
        with tqdm(total=sum(w), desc=desc, unit=unit, disable=not progress) as bar:
            return self._map(fn, tasks, w, bar, on_result)

    @abstractmethod
    def _map(
        self,
        fn: Callable[[T], R],
        tasks: list[T],
        weights: list[int],
        bar: tqdm,
        on_result: Callable[[int, R], object] | None,
    ) -> list[R]:
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

    def _map(
        self,
        fn: Callable[[T], R],
        tasks: list[T],
        weights: list[int],
        bar: tqdm,
        on_result: Callable[[int, R], object] | None,
    ) -> list[R]:
        out = []
        for i, (task, w) in enumerate(zip(tasks, weights, strict=True)):
            out.append(fn(task))
            if on_result is not None:
                on_result(i, out[-1])
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

    The workers die with this process, treat SIGINT and SIGUSR1 as a stop request (no
    traceback) and are
    killed when a :meth:`map` is interrupted or one of them dies (module docstring); a later
    :meth:`map` starts a fresh pool.

    Args:
        num_workers: processes (default ``os.cpu_count()``; at most :func:`max_pool_workers`).
        initializer: called once in each worker before its first task.
        initargs: arguments of ``initializer``.

    Raises:
        ExecutorError: ``num_workers`` above :func:`max_pool_workers`.
    """

    name = "process"

    def __init__(
        self,
        num_workers: int | None = None,
        initializer: Callable[..., None] | None = None,
        initargs: tuple[Any, ...] = (),
    ) -> None:
        super().__init__(num_workers)
        ceiling = max_pool_workers()
        if num_workers is not None and num_workers > ceiling:
            raise ExecutorError(
                f"--num-workers {num_workers} exceeds the ceiling of {ceiling} processes for "
                f"--executor process ({POOL_WORKERS_PER_CPU} per CPU of this machine); use "
                "fewer, or --executor ray with a cluster"
            )
        self._initializer, self._initargs = initializer, initargs
        self._pool: ProcessPoolExecutor | None = None
        self._procs: dict[int, Any] = {}  # pid -> multiprocessing.Process of the pool

    def _get_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            _tracker_guard.install()  # a killed resource tracker: one warning, no tracebacks
            with _single_threaded_children():
                self._pool = ProcessPoolExecutor(
                    self.num_workers,
                    mp_context=get_context("spawn"),
                    initializer=_worker_init,
                    initargs=(
                        os.getpid(),
                        self._initializer,
                        self._initargs,
                        signal.getsignal(signal.SIGINT) is signal.SIG_IGN,
                    ),
                )
            self._procs = {}
        return self._pool

    def _track(self, pool: ProcessPoolExecutor) -> None:
        """Remember the pool's worker processes (to name a dead one, to kill the rest)."""
        self._procs.update(getattr(pool, "_processes", None) or {})

    def _who_died(self, exc: BaseException) -> str:
        """One line naming the dead worker(s) of a broken pool.

        A broken pool terminates its surviving workers (SIGTERM), and their exit codes may be
        collected before the one that broke it: the workers are polled until every one has
        exited (or 2 s passed), and the deaths other than those SIGTERMs are named (all of
        them when there are no others).
        """
        deadline = time.monotonic() + 2.0
        while True:
            codes = {pid: proc.exitcode for pid, proc in self._procs.items()}
            dead = {pid: code for pid, code in codes.items() if code is not None and code != 0}
            settled = all(code is not None for code in codes.values())
            if (dead and settled) or time.monotonic() > deadline:
                break
            time.sleep(0.05)
        dead = {pid: c for pid, c in dead.items() if c != -signal.SIGTERM} or dead
        parts = []
        for pid, code in sorted(dead.items()):
            if code < 0:
                try:
                    how = f"killed by {signal.Signals(-code).name}"
                except ValueError:
                    how = f"killed by signal {-code}"
            else:
                how = f"exited with code {code}"
            parts.append(f"PID {pid} {how}")
        if parts:
            return f"a process-pool worker died while running tasks ({'; '.join(parts)})"
        return f"a process-pool worker died while running tasks ({exc or type(exc).__name__})"

    def _map(
        self,
        fn: Callable[[T], R],
        tasks: list[T],
        weights: list[int],
        bar: tqdm,
        on_result: Callable[[int, R], object] | None,
    ) -> list[R]:
        pool = self._get_pool()
        out: list[Any] = [None] * len(tasks)
        futures: dict[Future[R], int] = {}
        pending: set[Future[R]] = set()
        handled: set[Future[R]] = set()  # results handed to on_result (exactly once each)

        def finish(fut: Future[R]) -> None:
            if fut in handled:
                return
            i = futures[fut]
            # a SIGINT / SIGTERM waits until this result is recorded: it is handed over whole,
            # once (a signal raised in between would lose it or hand it over twice)
            with hold_signals():
                out[i] = fut.result()  # re-raises the worker's exception
                if on_result is not None:
                    on_result(i, out[i])
                handled.add(fut)
            bar.update(weights[i])

        try:
            with _single_threaded_children():  # the pool spawns its workers lazily, on submit
                for i, t in enumerate(tasks):
                    fut = pool.submit(fn, t)
                    futures[fut] = i
                    pending.add(fut)
            self._track(pool)
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in sorted(done, key=futures.__getitem__):
                    finish(fut)
        except BrokenProcessPool as exc:
            why = self._who_died(exc)
            self._discard()
            raise WorkerDiedError(why) from None
        except Exception:
            for fut in pending:
                fut.cancel()
            raise
        except BaseException:  # KeyboardInterrupt, SIGTERM: keep what the workers finish
            # every future not handed over yet: still running, queued, or done but not yet
            # finished when the signal came (``wait`` had already moved it out of ``pending``).
            # A second signal while the workers hand back (bounded by STOP_GRACE_SECONDS) waits
            # until they have: raised there it would abandon every result not yet collected
            with hold_signals():
                self._stop(futures, set(futures) - handled, finish)
            raise
        return out

    def _stop(
        self,
        futures: dict[Future[R], int],
        pending: set[Future[R]],
        finish: Callable[[Future[R]], None],
    ) -> None:
        """Cancel what has not started, ask the workers to stop, collect, then kill them."""
        if self._pool is not None:
            # from here on the pool is being discarded: a worker that exits on SIGUSR1 can make
            # the manager thread call ``terminate_broken`` on futures cancelled just below, which
            # raises ``InvalidStateError`` in that thread (CPython 3.11) before ``_discard`` runs
            _discarded.discard(self._pool)
        for fut in pending:
            fut.cancel()
        self._signal_workers(signal.SIGUSR1)
        running = {f for f in pending if not f.cancelled()}
        deadline = time.monotonic() + STOP_GRACE_SECONDS
        with contextlib.suppress(Exception):
            while running and time.monotonic() < deadline:
                done, running = wait(
                    running,
                    timeout=max(0.0, deadline - time.monotonic()),
                    return_when=FIRST_COMPLETED,
                )
                for fut in sorted(done, key=futures.__getitem__):
                    with contextlib.suppress(Exception):
                        finish(fut)
        self._discard()

    def _signal_workers(self, signum: int) -> None:
        for proc in list(self._procs.values()):
            if proc.exitcode is None and proc.pid is not None:
                with contextlib.suppress(OSError):
                    os.kill(proc.pid, signum)

    def _discard(self) -> None:
        """Kill the pool's workers and forget the pool (the next map starts a fresh one)."""
        pool, self._pool = self._pool, None
        if pool is None:
            return
        self._track(pool)
        _discarded.discard(pool)  # its manager thread may raise once the workers are killed
        self._signal_workers(signal.SIGKILL)
        with contextlib.suppress(Exception):
            pool.shutdown(wait=True, cancel_futures=True)
        self._procs = {}

    def close(self) -> None:  # noqa: D102
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


def _ray_call(fn: Callable[[T], R], task: T) -> R:
    """Body of every Ray task (module-level so Ray pickles it by reference)."""
    return fn(task)


#: test hook (fault-injection tests): Ray tasks from this index on never finish
HOLD_FROM_VAR = "SELENV_TEST_RAY_HOLD_FROM_TASK"
#: test hook: the folder where a held task writes ``task-<index>.pid`` (its worker's PID)
HOLD_DIR_VAR = "SELENV_TEST_RAY_HOLD_DIR"


def _held_call(fn: Callable[[T], R], index: int, folder: str, task: T) -> R:
    """Announce ``<folder>/task-<index>.pid``, then wait until killed or cancelled."""
    from selenv.atomic import write_text

    write_text(os.path.join(folder, f"task-{index}.pid"), f"{os.getpid()}\n")
    while True:
        time.sleep(0.05)


def _hold_hook() -> tuple[int, str] | None:
    """``(first held task, folder)`` of the Ray test hook, or ``None`` (the normal case)."""
    start, folder = os.environ.get(HOLD_FROM_VAR), os.environ.get(HOLD_DIR_VAR)
    if not start or not folder:
        return None
    return int(start), folder


#: seconds allowed for asking Ray what died (the answer is only a better message)
RAY_DIAGNOSIS_SECONDS = 5.0


def _first_sentences(text: str, limit: int = 160) -> str:
    """``text`` up to Ray's list of common causes, on one line, at most ``limit`` chars."""
    text = " ".join(text.split()).split(" Some common causes", 1)[0]
    text = text.rstrip(". ")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _alive_nodes(ray: Any) -> set[str] | None:
    """IDs of the Ray nodes alive now (``None`` if Ray cannot say)."""
    try:
        return {str(n["NodeID"]) for n in ray.nodes() if n.get("Alive")}
    except Exception:
        return None


def _ray_deaths(ray: Any, since_ms: int, nodes: set[str] | None) -> list[str]:
    """What Ray's control store knows died: nodes with Ray's reason, crashed workers.

    Reported: the ``nodes`` (alive when the map started; ``None``: any) that are dead now and
    the workers that crashed since ``since_ms``. The worker table is read through Ray's
    internal state accessor (as in Ray 2.60); this may raise anything, which only costs the
    message its detail.
    """
    common_pb2: Any = importlib.import_module("ray.core.generated.common_pb2")
    gcs_pb2: Any = importlib.import_module("ray.core.generated.gcs_pb2")
    found = []
    for node in ray.nodes():
        if not node.get("Alive", True) and (nodes is None or str(node.get("NodeID")) in nodes):
            why = _first_sentences(str(node.get("DeathReasonMessage") or "")) or "no reason given"
            found.append(f"node {node.get('NodeManagerAddress', '?')} stopped: {why}")
    crashed = {common_pb2.SYSTEM_ERROR, common_pb2.NODE_OUT_OF_MEMORY}
    accessor = ray._private.state.state._connect_and_get_accessor()
    for raw in accessor.get_worker_table():
        w = gcs_pb2.WorkerTableData.FromString(raw)
        if (
            not w.is_alive
            and w.worker_type == common_pb2.WORKER
            and w.exit_type in crashed
            and w.end_time_ms >= since_ms
        ):
            found.append(f"worker PID {w.pid}: {_first_sentences(w.exit_detail) or 'no detail'}")
    return found[:3]


def _ray_failure(
    ray: Any, err: BaseException, index: int, since_ms: int, nodes: set[str] | None
) -> str:
    """One line for a Ray error that is not the task's own: what died, as far as Ray knows.

    Ray's exception says only *that* something died (``WorkerCrashedError``,
    ``LocalRayletDiedError``, ``NodeDiedError``, ...); the node table (death reason, e.g. an
    agent the node fate-shares with) and the worker table (PID, exit detail) say what. Asked
    in a thread for at most :data:`RAY_DIAGNOSIS_SECONDS`; Ray's own first line otherwise.
    """
    found: list[str] = []

    def ask() -> None:
        # Ray records a death in its tables a moment after it fails the task: look again
        deadline = time.monotonic() + RAY_DIAGNOSIS_SECONDS / 2
        with contextlib.suppress(Exception):
            while not found:
                found.extend(_ray_deaths(ray, since_ms, nodes))
                if time.monotonic() > deadline:
                    break
                time.sleep(0.1)

    asker = threading.Thread(target=ask, daemon=True)
    asker.start()
    asker.join(RAY_DIAGNOSIS_SECONDS)
    name = type(err).__name__
    if not asker.is_alive() and found:
        what = "a Ray node stopped" if found[0].startswith("node ") else "a Ray worker died"
        return f"{what} while running task {index} ({name}; {'; '.join(found)})"
    first = _first_sentences((str(err).strip().splitlines() or [""])[0], 200)
    return f"a Ray worker died while running task {index} ({name}" + (
        f": {first})" if first else ")"
    )


class _RaySignals(DeferredSignals):
    """SIGINT and SIGTERM during a Ray map: recorded, then raised as ``KeyboardInterrupt``.

    Ray runs a signal's Python handler inside its blocking calls (``ray.wait``) and passes on
    ``KeyboardInterrupt`` only: another exception (a SIGTERM handler's) is dropped there and
    the signal is lost. So both become ``KeyboardInterrupt`` while the map runs; the map then
    hands a SIGTERM to the handler that was in place before (``signal.raise_signal``). A
    signal that was ignored stays ignored. Main thread only (elsewhere nothing changes).
    """

    def __init__(self) -> None:
        super().__init__(second_raises=False)

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self._previous.get(signum) is signal.SIG_IGN:
            return
        super()._handle(signum, frame)
        raise KeyboardInterrupt


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

    def _map(
        self,
        fn: Callable[[T], R],
        tasks: list[T],
        weights: list[int],
        bar: tqdm,
        on_result: Callable[[int, R], object] | None,
    ) -> list[R]:
        self.start()
        ray = self._ray
        remote = ray.remote(num_cpus=1, max_retries=0)(_ray_call)
        hold = _hold_hook()
        out: list[Any] = [None] * len(tasks)
        index: dict[Any, int] = {}  # tasks in flight: Ray reference -> task index
        todo = iter(enumerate(tasks))
        since_ms = int(time.time() * 1000)  # Ray's worker table times its deaths in wall ms
        nodes = _alive_nodes(ray)

        def submit(i: int, task: T) -> None:
            # ``fn`` travels inline with each task (a module-level function pickles as its
            # name): an object this process put into Ray's object store would tie this process
            # to the node's store, and a node that dies would then end it (Ray exits it).
            call: Callable[[T], R] = fn
            if hold is not None and i >= hold[0]:
                call = functools.partial(_held_call, fn, i, hold[1])
            index[remote.remote(call, task)] = i

        signals = _RaySignals()
        try:
            with signals:
                try:
                    for i, task in todo:
                        submit(i, task)
                        if len(index) >= self.num_workers:
                            break
                    while index:
                        (ref,), _ = ray.wait(list(index), num_returns=1)
                        i = index.pop(ref)
                        out[i] = self._result(ray, ref, i, since_ms, nodes)
                        if on_result is not None:
                            on_result(i, out[i])
                        bar.update(weights[i])
                        nxt = next(todo, None)
                        if nxt is not None:
                            submit(*nxt)
                except BaseException:
                    for ref in index:
                        with contextlib.suppress(Exception):
                            ray.cancel(ref, force=True)
                    raise
        except KeyboardInterrupt:
            if signals.received and signals.received[0] != signal.SIGINT:
                # the handler in place before the map (restored now) takes the signal in Python
                # code, e.g. SIGTERM -> the caller's Terminated
                signal.raise_signal(signals.received[0])
            raise
        return out

    @staticmethod
    def _result(ray: Any, ref: Any, i: int, since_ms: int, nodes: set[str] | None) -> Any:
        """The result of task ``i`` (its own exception re-raised as itself).

        Raises:
            WorkerDiedError: the worker or node running it is gone (the message names what).
        """
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as err:
            cause = getattr(err, "cause", None)
            if isinstance(cause, BaseException):
                raise cause from None
            raise
        except ray.exceptions.RayError as err:  # a worker, node or object is gone
            raise WorkerDiedError(_ray_failure(ray, err, i, since_ms, nodes)) from None

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
