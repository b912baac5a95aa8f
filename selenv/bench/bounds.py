"""Certified bounds on the episodes' returns, and each agent's gap to them.

A family that can bound an episode's return declares ``FamilySpec.return_bound`` (for
FIMSelection the log-det continuous relaxation). :func:`return_bounds` computes it for every
seed of a bench run (one env reset per seed, in this process); :func:`gap_to_bound` gives an
agent's mean relative gap ``(bound - return) / |bound|`` over its seeds with a bootstrap 95 % CI,
the "gap" column of the learned-combinatorial-optimisation literature. With a bound that is not
the optimum the true gap is at most the reported one.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from selenv.bench.stats import bootstrap_ci
from selenv.families import FAMILIES
from selenv.families.spec import ReturnBound, load_attr

__all__ = ["bound_function", "gap_to_bound", "return_bounds"]


def bound_function(env_id: str) -> Any | None:
    """The family's ``bound(env)`` for a Gymnasium id of any version; ``None`` if it has none."""
    for fam in FAMILIES:
        if any(v.env_id == env_id for v in fam.versions):
            return None if fam.return_bound is None else load_attr(fam.return_bound)
    return None


def return_bounds(
    env_id: str, env_kwargs: dict[str, Any], seeds: Sequence[int]
) -> tuple[str, str, dict[int, float]] | None:
    """``(kind, method, {seed: bound})`` for the episodes seeded ``seeds``, or ``None``.

    ``None`` when the family has no bound or the configuration has none (the bound function
    returned ``None``). The env is built with ``env_kwargs`` and reset once per seed.
    """
    bound = bound_function(env_id)
    if bound is None or not seeds:
        return None
    env = gym.make(env_id, **env_kwargs)
    try:
        values: dict[int, float] = {}
        first: ReturnBound | None = None
        for seed in seeds:
            env.reset(seed=seed)
            got = bound(env.unwrapped)
            if got is None:
                return None
            first = first or got
            values[int(seed)] = float(got.value)
    finally:
        env.close()
    assert first is not None
    return first.kind, first.method, values


def gap_to_bound(
    returns: Sequence[float], seeds: Sequence[int], bounds: dict[int, float]
) -> tuple[float, float, float] | None:
    """Mean ``(bound - return) / |bound|`` over the seeds with a bound, and its 95 % CI.

    ``None`` when no seed has a bound. A gap is >= 0 up to rounding for a valid bound.
    """
    pairs = [(bounds[s], r) for s, r in zip(seeds, returns, strict=True) if s in bounds]
    if not pairs:
        return None
    b = np.array([p[0] for p in pairs])
    r = np.array([p[1] for p in pairs])
    gaps = (b - r) / np.maximum(np.abs(b), 1e-300)
    lo, hi = bootstrap_ci(gaps)
    return float(gaps.mean()), lo, hi
