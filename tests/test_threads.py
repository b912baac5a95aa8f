"""selenv.threads: one BLAS thread around the hot paths, the caller's counts restored after."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from selenv import threads
from selenv.agents.fim_solvers import greedy
from selenv.threads import (
    blas_threads,
    limit_threads,
    set_blas_threads,
    set_torch_threads,
    small_blas,
)

pytestmark = pytest.mark.skipif(not threads._blas_libs(), reason="no BLAS pool found")


@pytest.fixture
def two_blas_threads():
    before = blas_threads()
    set_blas_threads(2)
    yield
    set_blas_threads(before)


def test_small_blas_limits_inside_and_restores(two_blas_threads) -> None:
    assert blas_threads() == 2
    with small_blas():
        assert blas_threads() == 1
        with small_blas():  # nested: still one, and the outer restore is unaffected
            assert blas_threads() == 1
        assert blas_threads() == 1
    assert blas_threads() == 2


def test_decorator_restores_after_an_exception(two_blas_threads) -> None:
    seen = []

    @small_blas
    def work(x: int) -> int:
        seen.append(blas_threads())
        if x < 0:
            raise ValueError("negative")
        return 2 * x

    assert work(3) == 6
    with pytest.raises(ValueError, match="negative"):
        work(-1)
    assert seen == [1, 1]
    assert blas_threads() == 2
    assert work.__name__ == "work"


def test_public_solvers_run_with_one_thread_and_decide_the_same(
    two_blas_threads, monkeypatch
) -> None:
    rng = np.random.default_rng(0)
    Q0 = np.eye(6)
    H = rng.normal(size=(80, 1, 6))
    R = np.ones((80, 1, 1))
    seen = []
    real = threads._limit

    def spy(n: int = 1):
        seen.append(n)
        return real(n)

    monkeypatch.setattr(threads, "_limit", spy)
    inside = greedy(Q0, H, R, 8)
    assert seen and blas_threads() == 2
    monkeypatch.setenv("SELENV_BLAS_THREADS", "0")  # off: the caller's two threads
    outside = greedy(Q0, H, R, 8)
    assert list(inside.indices) == list(outside.indices)
    np.testing.assert_allclose(inside.objective, outside.objective, rtol=1e-12)


def test_switch_off_leaves_the_count(two_blas_threads, monkeypatch) -> None:
    monkeypatch.setenv("SELENV_BLAS_THREADS", "0")
    with small_blas():
        assert blas_threads() == 2


def test_limit_threads_sets_and_restores_torch_and_blas(two_blas_threads) -> None:
    before = torch.get_num_threads()
    with limit_threads(blas=1, torch=1):
        assert torch.get_num_threads() == 1 and blas_threads() == 1
    assert torch.get_num_threads() == before and blas_threads() == 2
    with limit_threads(blas=None, torch=None):  # None: untouched
        assert torch.get_num_threads() == before and blas_threads() == 2


@pytest.mark.parametrize("bad", [0, -1])
def test_bad_counts_are_value_errors(bad: int) -> None:
    with pytest.raises(ValueError, match="threads must be >= 1"):
        set_blas_threads(bad)
    with pytest.raises(ValueError, match="threads must be >= 1"):
        set_torch_threads(bad)
    with pytest.raises(ValueError, match="blas threads must be >= 1"), limit_threads(blas=bad):
        pass


@pytest.mark.parametrize("bad", [1.5, "2", True])
def test_bad_count_types_are_type_errors(bad: object) -> None:
    with pytest.raises(TypeError, match="threads must be an int"):
        set_blas_threads(bad)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="torch threads must be an int"):
        with limit_threads(torch=bad):  # type: ignore[arg-type]
            pass
