"""A folder of finished task results, so a long :meth:`Executor.map` can stop and resume.

A long Monte Carlo run (thousands of seeded episodes) is a list of tasks whose results depend
only on the task. :func:`resumable_map` runs the tasks that the store does not hold yet, writes
the finished results to the store as they come in (every ``flush_every`` results or
``flush_seconds``, and once more when the map stops for any reason, Ctrl-C and worker deaths
included) and returns every result in task order, read back from the store. Run the same
command again after a stop and only the missing tasks run.

Storage: each flush writes one ``part-*.npz`` file atomically (temporary file + rename), read
back with ``allow_pickle=False``, so an interrupted write never leaves a half file and loading
never executes code. A result is a ``dict[str, numpy.ndarray]`` (what the reproduction scripts
return per episode); a task is keyed by the SHA-256 of its canonical JSON (numbers written
exactly, arrays with dtype and shape), so a changed task (another seed, horizon or keyword) is
a different key and is run, never confused with a stored one.

Each part also records the wall seconds spent between its flush and the previous one, so
:meth:`ResultStore.compute_seconds` is the wall time the stored results cost over every
session that added to them.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from selenv.atomic import atomic_path
from selenv.parallel.executors import Executor

Result = dict[str, np.ndarray]
_FIELD = re.compile(r"^([0-9a-f]{64})__(.+)$")
_WALL = "__wall_seconds__"


def _canonical(value: Any) -> Any:
    """``value`` as plain JSON types; arrays as ``{"dtype", "shape", "data"}``; tuples as lists."""
    if isinstance(value, np.ndarray):
        data = value.ravel().tolist()
        return {"dtype": value.dtype.str, "shape": list(value.shape), "data": data}
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        keys = list(value)
        if not all(isinstance(k, str) for k in keys):
            kinds = [type(k).__name__ for k in keys]
            raise TypeError(f"task: mapping keys must be str, got {kinds}")
        return {k: _canonical(value[k]) for k in sorted(keys)}
    if isinstance(value, list | tuple):
        return [_canonical(v) for v in value]
    if value is None or isinstance(value, bool | int | float | str):
        return value
    raise TypeError(f"task: cannot key a value of type {type(value).__name__}")


def task_key(task: Any) -> str:
    """SHA-256 (hex) of the task's canonical JSON (floats by their exact ``repr``)."""
    text = json.dumps(_canonical(task), sort_keys=True, allow_nan=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


class ResultStore:
    """Finished results in ``folder`` (created on the first write), keyed by :func:`task_key`."""

    def __init__(self, folder: str | os.PathLike[str]) -> None:
        self.folder = Path(folder)
        if self.folder.exists() and not self.folder.is_dir():
            raise ValueError(f"store folder {self.folder} exists and is not a folder")
        self._results: dict[str, Result] = {}
        self._wall = 0.0
        self._load()

    def _load(self) -> None:
        if not self.folder.is_dir():
            return
        for part in sorted(self.folder.glob("part-*.npz")):
            with np.load(part, allow_pickle=False) as data:
                for name in data.files:
                    if name == _WALL:
                        self._wall += float(data[name])
                        continue
                    m = _FIELD.match(name)
                    if m is None:
                        raise ValueError(f"{part}: unexpected array {name!r} (not a store part)")
                    self._results.setdefault(m.group(1), {})[m.group(2)] = data[name]

    def __contains__(self, key: str) -> bool:
        return key in self._results

    def __len__(self) -> int:
        return len(self._results)

    def get(self, key: str) -> Result:
        """The stored result of ``key`` (``KeyError`` when missing)."""
        return self._results[key]

    def compute_seconds(self) -> float:
        """Wall seconds recorded with the stored parts (summed over every run that wrote)."""
        return self._wall

    def write(self, results: Mapping[str, Result], wall_seconds: float) -> Path | None:
        """Store ``results`` (key -> result) as one new part file; ``None`` when empty."""
        if not results:
            return None
        arrays: dict[str, np.ndarray] = {_WALL: np.asarray(float(wall_seconds))}
        for key, result in results.items():
            if not isinstance(result, Mapping):
                raise TypeError(f"result: expected a dict of arrays, got {type(result).__name__}")
            for field, value in result.items():
                arr = np.asarray(value)
                if arr.dtype == object:
                    raise TypeError(f"result field {field!r}: object arrays cannot be stored")
                arrays[f"{key}__{field}"] = arr
        stamp = f"{time.time_ns():020d}-{os.getpid()}"
        target = self.folder / f"part-{stamp}.npz"
        with atomic_path(target) as temp:
            with open(temp, "wb") as fh:
                np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]
        for key, result in results.items():
            self._results[key] = {f: np.asarray(v) for f, v in result.items()}
        self._wall += float(wall_seconds)
        return target


def resumable_map(
    pool: Executor,
    fn: Callable[[Any], Result],
    tasks: Sequence[Any],
    store: ResultStore | None,
    *,
    desc: str | None = None,
    unit: str = "task",
    flush_every: int = 50,
    flush_seconds: float = 120.0,
) -> list[Result]:
    """``pool.map(fn, tasks)`` that skips the tasks ``store`` holds and stores the new results.

    Without a store this is ``pool.map``. With one, finished results are flushed to it every
    ``flush_every`` results or ``flush_seconds`` (checked as results arrive) and when the map
    ends or is interrupted; the returned list holds every task's result in task order.
    """
    if store is None:
        return pool.map(fn, tasks, desc=desc, unit=unit)
    if flush_every < 1:
        raise ValueError(f"flush_every: expected >= 1, got {flush_every}")
    keys = [task_key(t) for t in tasks]
    todo = sorted({k: i for i, k in enumerate(keys) if k not in store}.values())
    pending: dict[str, Result] = {}
    last = time.perf_counter()

    def flush() -> None:
        nonlocal last
        now = time.perf_counter()
        store.write(pending, now - last)
        pending.clear()
        last = now

    def on_result(j: int, result: Result) -> None:
        pending[keys[todo[j]]] = result
        if len(pending) >= flush_every or time.perf_counter() - last >= flush_seconds:
            flush()

    if todo:
        label = desc if len(todo) == len(tasks) else f"{desc} ({len(tasks) - len(todo)} stored)"
        try:
            pool.map(fn, [tasks[i] for i in todo], desc=label, unit=unit, on_result=on_result)
        finally:
            flush()
    return [store.get(k) for k in keys]
