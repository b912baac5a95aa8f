"""One BLAS thread around the small-matrix hot paths, whatever the user's thread settings.

selenv's solvers and envs make many small LAPACK / BLAS calls (a ``(d, d)`` Cholesky with
``d <= 20``, a ``(N m, d) @ (d, d)`` product). With OpenBLAS's default of one thread per core,
calls above OpenBLAS's size threshold wake its worker threads, whose start-up costs more than
the work: measured on 2 cores under load, ``greedy`` (``d = 15``, ``K = 10``, ``N = 200``) took
11 ms with the default threads against 0.66 ms with one (``benchmarks/bench_threads.py``).
scikit-learn meets the same problem the same way: :mod:`threadpoolctl` limits the BLAS pools
of the process around the hot path and restores them after.

:func:`small_blas` is that context manager (and decorator). It is cheap enough for a call of
a millisecond (one ctypes call to read the pool size, two to set and restore it; nothing when
the pool already has one thread, as inside another :func:`small_blas` or with
``OPENBLAS_NUM_THREADS=1``), so it wraps whole solver calls, vector-env steps and bench
episodes, not single small operations. :func:`set_blas_threads` and :func:`set_torch_threads`
set the process-wide counts (``selenv bench --blas-threads / --torch-threads``).

``SELENV_BLAS_THREADS=0`` in the environment turns :func:`small_blas` off (the user's thread
settings are then left as they are).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

__all__ = ["blas_threads", "limit_threads", "set_blas_threads", "set_torch_threads", "small_blas"]

F = TypeVar("F", bound=Callable[..., Any])

_LIBS: list[Any] | None = None


def _blas_libs() -> list[Any]:
    """The BLAS library controllers of the process (discovered once; empty without any)."""
    global _LIBS
    if _LIBS is None:
        try:
            from threadpoolctl import ThreadpoolController
        except ImportError:  # pragma: no cover - a dependency; tolerate its absence
            _LIBS = []
        else:
            import numpy  # noqa: F401  (load numpy's BLAS before the discovery)

            controller = ThreadpoolController()
            _LIBS = [lib for lib in controller.lib_controllers if lib.user_api == "blas"]
    return _LIBS


def _enabled() -> bool:
    return os.environ.get("SELENV_BLAS_THREADS", "1") != "0"


def blas_threads() -> int:
    """The largest thread count among the process's BLAS pools (1 without a BLAS found)."""
    return max((int(lib.get_num_threads()) for lib in _blas_libs()), default=1)


def set_blas_threads(n: int) -> None:
    """Set every BLAS pool of the process to ``n`` threads.

    Raises:
        TypeError: ``n`` not an int.
        ValueError: ``n < 1``.
    """
    if isinstance(n, bool) or not isinstance(n, int):
        raise TypeError(f"blas threads must be an int, got {type(n).__name__}")
    if n < 1:
        raise ValueError(f"blas threads must be >= 1, got {n}")
    for lib in _blas_libs():
        lib.set_num_threads(n)


def set_torch_threads(n: int) -> None:
    """``torch.set_num_threads(n)`` (intra-op threads of the policies' small forward passes).

    Raises:
        TypeError: ``n`` not an int.
        ValueError: ``n < 1``.
    """
    if isinstance(n, bool) or not isinstance(n, int):
        raise TypeError(f"torch threads must be an int, got {type(n).__name__}")
    if n < 1:
        raise ValueError(f"torch threads must be >= 1, got {n}")
    import torch

    torch.set_num_threads(n)


@contextmanager
def _limit(n: int = 1) -> Iterator[None]:
    libs = _blas_libs() if _enabled() else []
    saved = [(lib, lib.get_num_threads()) for lib in libs]
    changed = [(lib, k) for lib, k in saved if k != n]
    for lib, _ in changed:
        lib.set_num_threads(n)
    try:
        yield
    finally:
        for lib, k in changed:
            lib.set_num_threads(k)


class _SmallBlas:
    """Context manager and decorator: one BLAS thread inside, the previous counts after."""

    def __enter__(self) -> None:
        self._cm = _limit()
        self._cm.__enter__()

    def __exit__(self, *exc: Any) -> None:
        self._cm.__exit__(*exc)

    def __call__(self, fn: F) -> F:
        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            with _limit():
                return fn(*args, **kwargs)

        return wrapper  # type: ignore[return-value]


def small_blas(fn: F | None = None) -> Any:
    """One BLAS thread for the duration of a block or a call.

    ``with small_blas(): ...`` or ``@small_blas`` on a function; restores the previous counts
    on exit, exceptions included. Nested uses cost one ctypes call each.
    """
    if fn is None:
        return _SmallBlas()
    return _SmallBlas()(fn)


@contextmanager
def limit_threads(blas: int | None = 1, torch: int | None = 1) -> Iterator[None]:
    """``blas`` BLAS threads and ``torch`` torch intra-op threads inside; restored after.

    ``None`` leaves that count as it is. torch is only touched if it is already imported
    (nothing imports it for this). The bench plays every block of episodes inside it.

    Raises:
        TypeError / ValueError: a count that is not an int >= 1.
    """
    for name, value in (("blas", blas), ("torch", torch)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int)):
            raise TypeError(f"{name} threads must be an int or None, got {type(value).__name__}")
        if value is not None and value < 1:
            raise ValueError(f"{name} threads must be >= 1, got {value}")
    import sys

    th = sys.modules.get("torch") if torch is not None else None
    before = th.get_num_threads() if th is not None else None
    if th is not None:
        th.set_num_threads(torch)
    try:
        if blas is None:
            yield
        else:
            with _limit(blas):
                yield
    finally:
        if th is not None and before is not None:
            th.set_num_threads(before)
