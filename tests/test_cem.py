"""The cross-entropy method (selenv.learned.rl.cem): convergence, determinism, resumption."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from selenv.learned.rl.cem import CEMSettings, cem_generation, new_state, state_from_json

TARGET = np.array([1.5, -2.0, 0.25])


def _concave(x: np.ndarray) -> float:
    """A maximum of 0 at TARGET (closed form)."""
    return -float(np.sum((np.asarray(x) - TARGET) ** 2))


def _run(generations: int, seed: int = 3, settings: CEMSettings | None = None) -> object:
    settings = settings or CEMSettings(population=20, elite=5, init_std=2.0, min_std=0.0)
    state = new_state(TARGET.size, settings, seed)
    for _ in range(generations):
        state = cem_generation(state, settings, _concave)
    return state


def test_converges_to_the_closed_form_maximum() -> None:
    state = _run(30)
    np.testing.assert_allclose(state.mean, TARGET, atol=1e-3)
    assert state.best_value > -1e-5
    assert state.generation == 30 and len(state.history) == 30
    # the mean is candidate 0: its recorded score is the objective at the previous mean
    assert state.history[-1]["mean_value"] <= state.best_value


def test_the_first_candidate_is_the_mean_and_scores_are_ranked() -> None:
    seen: list[np.ndarray] = []

    def record(x: np.ndarray) -> float:
        seen.append(np.array(x))
        return _concave(x)

    settings = CEMSettings(population=6, elite=2, init_std=1.0, min_std=0.0)
    state = new_state(3, settings, 0, mean=[0.5, 0.5, 0.5])
    after = cem_generation(state, settings, record)
    np.testing.assert_array_equal(seen[0], [0.5, 0.5, 0.5])
    values = np.array([_concave(x) for x in seen])
    elite = np.stack([seen[i] for i in np.argsort(-values, kind="stable")[:2]])
    np.testing.assert_allclose(after.mean, elite.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(after.std, elite.std(axis=0), rtol=1e-12)
    assert after.best_value == values.max()
    assert state.generation == 0  # the input state is not modified


def test_same_seed_same_search_and_json_resumption_is_exact() -> None:
    a, b = _run(6, seed=11), _run(6, seed=11)
    assert a.to_json() == b.to_json()
    assert _run(6, seed=12).mean != a.mean
    settings = CEMSettings(population=20, elite=5, init_std=2.0, min_std=0.0)
    half = _run(3, seed=11)
    state = state_from_json(json.loads(json.dumps(half.to_json())), TARGET.size)
    for _ in range(3):
        state = cem_generation(state, settings, _concave)
    assert state.to_json() == a.to_json()


def test_map_fn_is_used_for_the_evaluations() -> None:
    calls: list[int] = []

    def counting_map(fn, items):  # type: ignore[no-untyped-def]
        items = list(items)
        calls.append(len(items))
        return [fn(x) for x in items]

    settings = CEMSettings(population=5, elite=2)
    cem_generation(new_state(3, settings, 0), settings, _concave, counting_map)
    assert calls == [5]


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"population": 1}, "population"),
        ({"population": 4, "elite": 5}, "elite"),
        ({"elite": 0}, "elite"),
        ({"elite": 2.5}, "elite"),
        ({"init_std": 0.0}, "init_std"),
        ({"init_std": math.nan}, "init_std"),
        ({"min_std": -1.0}, "min_std"),
    ],
)
def test_bad_settings_are_refused_by_name(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        new_state(3, CEMSettings(**kwargs), 0)


def test_bad_mean_state_and_scores_are_refused() -> None:
    with pytest.raises(ValueError, match="mean must hold 3"):
        new_state(3, CEMSettings(), 0, mean=[1.0, 2.0])
    with pytest.raises(ValueError, match="dim"):
        new_state(0, CEMSettings(), 0)
    good = _run(1).to_json()
    with pytest.raises(ValueError, match="std"):
        state_from_json({**good, "std": [1.0, math.inf, 1.0]}, 3)
    with pytest.raises(ValueError, match="fields"):
        state_from_json({**good, "extra": 1}, 3)
    with pytest.raises(ValueError, match="JSON object"):
        state_from_json([1, 2], 3)
    settings = CEMSettings(population=3, elite=1)
    with pytest.raises(ValueError, match="candidate"):
        cem_generation(new_state(3, settings, 0), settings, lambda x: math.nan)
