"""A process pool discarded on purpose ends without a thread traceback (``_discarded``)."""

from __future__ import annotations

import threading
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context

import pytest

from selenv.parallel import _discarded


class _Pool:
    """Stands in for a ProcessPoolExecutor: only its manager-thread attribute is read."""

    def __init__(self, thread: threading.Thread | None) -> None:
        self._executor_manager_thread = thread


@pytest.fixture
def seen(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The uncaught thread exceptions that reach the hook in place before ``install``."""
    got: list[str] = []
    monkeypatch.setattr(threading, "excepthook", lambda args: got.append(args.thread.name))
    monkeypatch.setattr(_discarded, "_previous", None)
    return got


def _failing(name: str, gate: threading.Event) -> threading.Thread:
    def body() -> None:
        gate.wait(30)
        raise OSError("handle is closed")

    return threading.Thread(target=body, name=name)


def test_a_discarded_pools_manager_thread_is_silent_and_others_are_not(seen: list[str]) -> None:
    gate = threading.Event()
    manager, other = _failing("manager", gate), _failing("other", gate)
    _discarded.discard(_Pool(manager))
    assert threading.excepthook is _discarded._hook
    manager.start()
    other.start()
    gate.set()
    manager.join(30)
    other.join(30)
    assert seen == ["other"]  # the other thread's exception still reaches the previous hook


def test_install_is_idempotent_and_a_pool_without_a_thread_records_nothing(
    seen: list[str],
) -> None:
    _discarded.install()
    _discarded.install()
    assert _discarded._previous is not _discarded._hook
    before = len(_discarded._discarded)
    _discarded.discard(_Pool(None))
    _discarded.discard(object())
    assert len(_discarded._discarded) == before


def test_a_real_pools_manager_thread_is_found() -> None:
    """The CPython attribute the hook relies on exists on this Python's ProcessPoolExecutor."""
    with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:
        assert pool.submit(abs, -3).result(timeout=120) == 3
        thread = pool._executor_manager_thread  # type: ignore[attr-defined]
        assert isinstance(thread, threading.Thread)
        _discarded.discard(pool)
        assert thread in _discarded._discarded


def test_a_stopped_map_discards_the_pool_before_asking_the_workers_to_stop(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A worker that leaves on the stop request can break the pool at once: the pool must be
    recorded as discarded before SIGUSR1, not only when its workers are killed."""
    import signal

    from selenv.parallel import ProcessExecutor

    executor = ProcessExecutor(1)
    recorded_at: dict[int, bool] = {}
    signal_workers = executor._signal_workers

    def spy(signum: int) -> None:
        pool = executor._pool
        thread = getattr(pool, "_executor_manager_thread", None)
        recorded_at[signum] = thread is not None and thread in _discarded._discarded
        signal_workers(signum)

    monkeypatch.setattr(executor, "_signal_workers", spy)

    def stop(index: int, result: int) -> None:
        raise KeyboardInterrupt

    try:
        with pytest.raises(KeyboardInterrupt):
            executor.map(abs, [-1, -2, -3, -4], on_result=stop)
    finally:
        executor.close()
    assert recorded_at.get(signal.SIGUSR1) is True


def test_results_done_when_a_signal_comes_are_all_handed_over_once(monkeypatch) -> None:
    """A signal while a batch of finished futures is being handed over loses none of them.

    ``wait`` is made to return every future at once (as it does when several finish between
    two looks); the signal comes while the first result is handed over. Each result must
    still reach ``on_result`` exactly once, and the interrupt must propagate.
    """
    import concurrent.futures as cf
    import os
    import signal

    from selenv.parallel import ProcessExecutor
    from selenv.parallel import executors as ex

    real_wait = cf.wait

    def all_at_once(fs, timeout=None, return_when=cf.ALL_COMPLETED):
        if timeout is None:  # the map loop: every future done in one batch
            return real_wait(fs, return_when=cf.ALL_COMPLETED)
        return real_wait(fs, timeout=timeout, return_when=return_when)

    monkeypatch.setattr(ex, "wait", all_at_once)
    got: list[int] = []

    def on_result(i: int, value: int) -> None:
        got.append(i)
        if len(got) == 1:
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while the batch is handed over

    executor = ProcessExecutor(num_workers=2)
    try:
        with pytest.raises(KeyboardInterrupt):
            executor.map(abs, [-1, -2, -3, -4], progress=False, on_result=on_result)
    finally:
        executor.close()
    assert sorted(got) == [0, 1, 2, 3]
