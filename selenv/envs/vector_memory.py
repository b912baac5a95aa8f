"""The memory a native vector env will need, estimated before its arrays are allocated.

``gymnasium.make_vec(id, num_envs=B)`` keeps every sub-env's state in arrays with a leading
``B`` axis, so its memory grows linearly in ``B`` at a rate that depends on the family and on
its sizes (candidates, landmarks, receivers, agents, horizon). For ``B`` above
:data:`PROBE_ABOVE` the rate is **measured** on the same class and keywords with ``B = 2`` and
``B = 8`` (construction, a seeded ``reset`` and one step, peak traced by :mod:`tracemalloc`,
after a ``B = 1`` warm-up that absorbs one-time caches), so it follows every family and
configuration without a formula to keep in step with the code; the estimate is
``margin * (peak(2) + (B - 2) * rate)``.

When that estimate exceeds the memory available now
(:func:`selenv.memory.available_memory`: Linux ``MemAvailable``, or ``os.sysconf`` pages,
capped by a cgroup v2 ``memory.max``), the
constructor raises a ``ValueError`` naming ``num_envs``, the estimate and the available memory
instead of running into a ``MemoryError`` seconds (and gigabytes) later.
"""

from __future__ import annotations

import contextlib
import tracemalloc
from typing import Any

from selenv.memory import available_memory, human_bytes

__all__ = ["MARGIN", "PROBE_ABOVE", "available_memory", "check_vector_memory", "human_bytes"]

#: ``num_envs`` above which the memory is estimated before allocating (below: never probed)
PROBE_ABOVE = 256
#: factor on the measured estimate (allocator overhead, fragmentation)
MARGIN = 1.25
#: the two small batch sizes the rate is measured on
_PROBE_SIZES = (2, 8)


def _traced_peak(cls: type, num_envs: int, args: tuple[Any, ...], kwargs: dict[str, Any]) -> int:
    """Peak traced bytes of building ``cls`` with ``num_envs``, a seeded reset and one step."""
    was_tracing = tracemalloc.is_tracing()
    if not was_tracing:
        tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    tracemalloc.reset_peak()
    try:
        env = cls(num_envs, *args, **kwargs)
        try:
            env.reset(seed=0)
            with contextlib.suppress(Exception):  # e.g. invalid_action="raise": reset counts
                env.step(env.action_space.sample())
        finally:
            env.close()
        return max(tracemalloc.get_traced_memory()[1] - base, 0)
    finally:
        if not was_tracing:
            tracemalloc.stop()


def check_vector_memory(
    cls: type, num_envs: int, args: tuple[Any, ...] = (), kwargs: dict[str, Any] | None = None
) -> int | None:
    """Refuse ``cls(num_envs, *args, **kwargs)`` when it would not fit in memory.

    Returns:
        The estimate in bytes (``None`` when ``num_envs <= PROBE_ABOVE``: not probed).

    Raises:
        ValueError: the estimate exceeds the available memory; names ``num_envs``, the
            estimate, the per-sub-env rate and the available memory.
    """
    if num_envs <= PROBE_ABOVE:
        return None
    kwargs = dict(kwargs or {})
    small, large = _PROBE_SIZES
    _traced_peak(cls, 1, args, kwargs)  # warm-up: one-time caches and imports are not a rate
    low = _traced_peak(cls, small, args, kwargs)
    high = _traced_peak(cls, large, args, kwargs)
    rate = max(high - low, 0) / (large - small)
    estimate = int(MARGIN * (low + (num_envs - small) * rate))
    free, source = available_memory()
    if free is not None and estimate > free:
        raise ValueError(
            f"num_envs={num_envs}: {cls.__name__} would need about {human_bytes(estimate)} "
            f"({human_bytes(rate)} per sub-env, measured with {small} and {large}), more than "
            f"the {human_bytes(free)} of memory available ({source}); use a smaller num_envs"
        )
    return estimate
