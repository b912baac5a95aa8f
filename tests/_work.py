"""Work a refusal must come before, observed through the calls that do it (not through time).

A test of "refused up front" wraps the refusal in :func:`no_work` with the calls that would
do the expensive part (build a torch module, read weights, inflate arrays, start a run):
every call made while the block runs is recorded, and the block fails if any was made. How
long a refusal takes is a measurement, in ``benchmarks/bench_refusals.py``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any


def torch_work() -> list[tuple[object, str]]:
    """Building any torch module and reading any weights file (``torch.load``)."""
    import torch

    return [(torch.nn.Module, "__init__"), (torch, "load")]


def _recorder(real: Callable[..., Any], label: str, work: list[str]) -> Callable[..., Any]:
    def call(*args: Any, **kwargs: Any) -> Any:
        if label.endswith(".__init__") and args:
            work.append(f"built a {type(args[0]).__name__}")
        else:
            work.append(label)
        return real(*args, **kwargs)

    return call


@contextmanager
def recording(targets: list[tuple[object, str]]) -> Iterator[list[str]]:
    """Record every call of ``owner.name`` for each target while the block runs (restored)."""
    work: list[str] = []
    saved = []
    for owner, name in targets:
        real = getattr(owner, name)
        label = f"{getattr(owner, '__qualname__', getattr(owner, '__name__', owner))}.{name}"
        saved.append((owner, name, real))
        setattr(owner, name, _recorder(real, label, work))
    try:
        yield work
    finally:
        for owner, name, real in reversed(saved):
            setattr(owner, name, real)


@contextmanager
def no_work(targets: list[tuple[object, str]]) -> Iterator[None]:
    """The block must end before any call of the targets (e.g. ``torch_work()``)."""
    with recording(targets) as work:
        yield
    assert work == [], f"refused only after this work: {work}"
