"""The cross-entropy method: policy search on episode returns (Rubinstein 1999).

For a policy with few parameters whose quality shows only in whole-episode returns -- here a
correction to greedy's one-step score whose payoff comes many steps later -- direct search on
the returns is the robust choice: no value estimate and no gradient of a long, noisy return.
Each generation samples ``population`` parameter vectors from ``N(mean, diag(std^2))`` (the
first one is the mean itself), scores them with ``evaluate`` (the caller uses common random
numbers: every candidate plays the same training seeds, so the comparison between candidates
is paired), and refits ``mean`` and ``std`` to the ``elite`` best; ``std`` gets a floor
``min_std`` added (the "noisy CEM" of Szita & Lőrincz 2006, Neural Computation 18(12), which
keeps the search from collapsing early).

The state after every generation is a plain JSON-able :class:`CEMState` (with the sampler's
bit-generator state), so a run stopped between generations resumes to the same result.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

__all__ = ["CEMSettings", "CEMState", "cem_generation", "new_state", "state_from_json"]


@dataclass(frozen=True)
class CEMSettings:
    """Search settings (all validated by :func:`new_state`).

    Attributes:
        population: candidates per generation (>= 2).
        elite: candidates the next distribution is fitted to (1 <= elite <= population).
        init_std: the first generation's standard deviation (> 0), every coordinate.
        min_std: floor added to the refitted standard deviation (>= 0).
    """

    population: int = 24
    elite: int = 6
    init_std: float = 2.0
    min_std: float = 0.05


@dataclass
class CEMState:
    """Where a search stands after ``generation`` generations.

    Attributes:
        generation: generations done.
        mean: (D,) the sampling mean; std: (D,) its standard deviations.
        best: (D,) the best candidate evaluated so far; best_value: its score.
        history: one record per generation (scores of the mean, the best and the elite).
        rng: the sampler's ``PCG64`` state (``bit_generator.state``).
    """

    generation: int
    mean: list[float]
    std: list[float]
    best: list[float]
    best_value: float
    rng: dict[str, Any]
    history: list[dict[str, float]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """A JSON-able dict (the inverse of :func:`state_from_json`)."""
        return asdict(self)


def _check_settings(settings: CEMSettings) -> None:
    for name in ("population", "elite"):
        value = getattr(settings, name)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if settings.population < 2:
        raise ValueError(f"population must be >= 2, got {settings.population}")
    if settings.elite > settings.population:
        raise ValueError(
            f"elite must be <= population ({settings.population}), got {settings.elite}"
        )
    if not (math.isfinite(settings.init_std) and settings.init_std > 0):
        raise ValueError(f"init_std must be a finite number > 0, got {settings.init_std!r}")
    if not (math.isfinite(settings.min_std) and settings.min_std >= 0):
        raise ValueError(f"min_std must be a finite number >= 0, got {settings.min_std!r}")


def new_state(
    dim: int, settings: CEMSettings, seed: int, mean: Sequence[float] | None = None
) -> CEMState:
    """The state before the first generation: ``mean`` (default 0) and ``std = init_std``.

    Raises:
        ValueError: a bad setting, ``dim < 1`` or a ``mean`` of the wrong length (named).
    """
    _check_settings(settings)
    if dim < 1:
        raise ValueError(f"dim must be >= 1, got {dim}")
    m = np.zeros(dim) if mean is None else np.asarray(mean, dtype=np.float64)
    if m.shape != (dim,) or not np.all(np.isfinite(m)):
        raise ValueError(f"mean must hold {dim} finite numbers, got {list(np.ravel(m))!r:.200}")
    rng = np.random.Generator(np.random.PCG64(seed))
    return CEMState(
        generation=0,
        mean=m.tolist(),
        std=[float(settings.init_std)] * dim,
        best=m.tolist(),
        best_value=-math.inf,
        rng=dict(rng.bit_generator.state),
    )


def state_from_json(obj: Any, dim: int) -> CEMState:
    """A :class:`CEMState` from its JSON (a resumed run); ``ValueError`` naming a bad field."""
    if not isinstance(obj, dict):
        raise ValueError(f"CEM state must be a JSON object, got {type(obj).__name__}")
    try:
        state = CEMState(**obj)
    except TypeError as exc:
        raise ValueError(f"CEM state has missing or unknown fields: {exc}") from None
    for name in ("mean", "std", "best"):
        arr = np.asarray(getattr(state, name), dtype=np.float64)
        if arr.shape != (dim,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"CEM state: {name} must hold {dim} finite numbers")
    if not isinstance(state.generation, int) or state.generation < 0:
        raise ValueError(f"CEM state: generation must be an int >= 0, got {state.generation!r}")
    return state


def cem_generation(
    state: CEMState,
    settings: CEMSettings,
    evaluate: Callable[[np.ndarray], float],
    map_fn: Callable[[Callable[[np.ndarray], float], Iterable[np.ndarray]], Iterable[float]] = map,
) -> CEMState:
    """One generation: sample, evaluate (through ``map_fn``, e.g. a pool's ``map``), refit.

    Candidate 0 is the current mean; the others ``mean + std * N(0, I)`` from the state's
    generator. Ties in the ranking keep the earlier candidate. Returns the new state (the
    argument is not modified).

    Raises:
        ValueError: ``evaluate`` returned a non-finite score (named with its candidate).
    """
    _check_settings(settings)
    rng = np.random.Generator(np.random.PCG64())
    rng.bit_generator.state = state.rng
    mean, std = np.asarray(state.mean), np.asarray(state.std)
    noise = rng.standard_normal((settings.population - 1, mean.size))
    candidates = [mean, *(mean + std * z for z in noise)]
    values = np.asarray(list(map_fn(evaluate, candidates)), dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        raise ValueError(f"evaluate returned {values[bad[0]]!r} for candidate {bad[0]}")
    order = np.argsort(-values, kind="stable")
    elite = np.stack([candidates[i] for i in order[: settings.elite]])
    top = int(order[0])
    best, best_value = state.best, state.best_value
    if values[top] > best_value:
        best, best_value = candidates[top].tolist(), float(values[top])
    record = {
        "generation": state.generation,
        "mean_value": float(values[0]),
        "best_value": float(values[top]),
        "elite_value": float(np.mean(values[order[: settings.elite]])),
    }
    return CEMState(
        generation=state.generation + 1,
        mean=elite.mean(axis=0).tolist(),
        std=(elite.std(axis=0) + settings.min_std).tolist(),
        best=list(best),
        best_value=best_value,
        rng=dict(rng.bit_generator.state),
        history=[*state.history, record],
    )
