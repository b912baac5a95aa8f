"""The result store behind resumable Monte Carlo runs (``selenv.parallel.store``).

A stopped map keeps every finished result; the rerun runs only the missing tasks and returns
the same results as one uninterrupted map; a changed task is a new key; loading never unpickles.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from selenv.parallel import make_executor
from selenv.parallel.store import ResultStore, resumable_map, task_key


def _episode(task: dict) -> dict[str, np.ndarray]:
    """A seeded stand-in for an episode: a short random walk and its length."""
    rng = np.random.default_rng(task["seed"])
    walk = np.cumsum(rng.normal(size=task["steps"]))
    return {"J": walk, "n": np.asarray(task["steps"])}


class Interrupt(Exception):
    pass


def _tasks(n: int, steps: int = 5) -> list[dict]:
    return [{"seed": s, "steps": steps, "sigma": np.array([0.1, 0.2])} for s in range(n)]


def test_task_key_is_exact_and_order_free() -> None:
    a = {"seed": 1, "sigma": np.array([0.1, 0.2]), "ops": (1, 0)}
    assert task_key(a) == task_key({"ops": [1, 0], "sigma": np.array([0.1, 0.2]), "seed": 1})
    assert task_key(a) != task_key({**a, "sigma": np.array([0.1, np.nextafter(0.2, 1)])})
    assert task_key(a) != task_key({**a, "sigma": np.array([0.1, 0.2], dtype=np.float32)})
    assert task_key(a) != task_key({**a, "sigma": np.array([[0.1, 0.2]])})
    assert task_key(a) != task_key({**a, "seed": 2})
    with pytest.raises(TypeError, match="cannot key"):
        task_key({"f": object()})


def test_interrupted_map_resumes_with_only_the_missing_tasks(tmp_path: Path) -> None:
    tasks = _tasks(12)
    expected = [_episode(t) for t in tasks]
    calls: list[int] = []

    def counted(task: dict) -> dict[str, np.ndarray]:
        calls.append(task["seed"])
        if len(calls) == 8 and task["seed"] == 7:
            raise Interrupt
        return _episode(task)

    with make_executor("local") as pool, pytest.raises(Interrupt):
        resumable_map(pool, counted, tasks, ResultStore(tmp_path), flush_every=3, desc="x")
    stored = ResultStore(tmp_path)
    assert len(stored) == 7  # seeds 0-6, flushed in parts of 3, 3 and the last 1 at the stop
    assert len(list(tmp_path.glob("part-*.npz"))) == 3
    assert not list(tmp_path.glob("*.tmp*"))
    calls.clear()
    with make_executor("local") as pool:
        got = resumable_map(pool, counted, tasks, stored, flush_every=3)
    assert calls == list(range(7, 12))
    for g, e in zip(got, expected, strict=True):
        np.testing.assert_array_equal(g["J"], e["J"])
        assert int(g["n"]) == 5
    calls.clear()
    with make_executor("local") as pool:  # all stored: nothing runs, the same results
        again = resumable_map(pool, counted, tasks, ResultStore(tmp_path))
    assert calls == []
    assert all(np.array_equal(a["J"], g["J"]) for a, g in zip(again, got, strict=True))
    assert ResultStore(tmp_path).compute_seconds() > 0


def test_process_pool_results_equal_the_local_ones(tmp_path: Path) -> None:
    tasks = _tasks(6, steps=4)
    with make_executor("process", num_workers=2) as pool:
        got = resumable_map(pool, _episode, tasks, ResultStore(tmp_path), flush_every=2)
    for g, t in zip(got, tasks, strict=True):
        np.testing.assert_array_equal(g["J"], _episode(t)["J"])


def test_a_changed_task_is_run_not_read_back(tmp_path: Path) -> None:
    with make_executor("local") as pool:
        resumable_map(pool, _episode, _tasks(3, steps=5), ResultStore(tmp_path))
        got = resumable_map(pool, _episode, _tasks(3, steps=6), ResultStore(tmp_path))
    assert [g["J"].shape for g in got] == [(6,)] * 3
    assert len(ResultStore(tmp_path)) == 6


def test_without_a_store_it_is_the_plain_map() -> None:
    tasks = _tasks(3)
    with make_executor("local") as pool:
        got = resumable_map(pool, _episode, tasks, None)
    assert [g["J"].tolist() for g in got] == [_episode(t)["J"].tolist() for t in tasks]


def test_bad_folders_and_foreign_files_are_refused(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="not a folder"):
        ResultStore(tmp_path / "file")
    np.savez(tmp_path / "part-0.npz", other=np.zeros(2))
    with pytest.raises(ValueError, match="not a store part"):
        ResultStore(tmp_path)
    pickled = tmp_path / "p"
    pickled.mkdir()
    with open(pickled / "part-1.npz", "wb") as fh:  # an npz holding an object array
        np.savez(fh, **{"0" * 64 + "__J": np.array([{"a": 1}], dtype=object)})
    with pytest.raises(ValueError, match="allow_pickle"):
        ResultStore(pickled)
    store = ResultStore(tmp_path / "new")
    with pytest.raises(TypeError, match="object arrays"):
        store.write({"k" * 64: {"J": np.array([None], dtype=object)}}, 0.0)
    with make_executor("local") as pool, pytest.raises(ValueError, match="flush_every"):
        resumable_map(pool, _episode, _tasks(1), store, flush_every=0)
