"""``selenv bench`` reports each agent's gap to a certified bound on the episode's return."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from selenv.bench import format_table, run_bench
from selenv.bench.bounds import bound_function, gap_to_bound, return_bounds
from selenv.cli import main

FIM = "selenv/FIMSelection-v1"
SMALL = {"n_candidates": 6, "budget": 3}


def test_gap_to_bound_is_the_mean_relative_shortfall() -> None:
    mean, lo, hi = gap_to_bound([9.0, 18.0, 5.0], [1, 2, 3], {1: 10.0, 2: 20.0, 4: 1.0})
    assert mean == pytest.approx(0.1)  # seeds 1 and 2 only: (10-9)/10 and (20-18)/20
    assert lo == pytest.approx(0.1) and hi == pytest.approx(0.1)
    assert gap_to_bound([1.0], [5], {1: 2.0}) is None


def test_fim_bounds_hold_the_optimum_and_every_agent() -> None:
    res = run_bench(FIM, ["brute_force", "optimal", "greedy", "random"], episodes=4,
                    env_kwargs=SMALL, progress=False)  # fmt: skip
    assert res.bound_kind == "bound" and "relaxation" in (res.bound_method or "")
    assert sorted(res.bounds) == [0, 1, 2, 3]
    for name, agent in res.agents.items():
        bounds = np.array([res.bounds[s] for s in agent.seeds])
        assert np.all(np.asarray(agent.returns) <= bounds + 1e-9), name
    gaps = {n: res.gap_to_bound(n) for n in res.agents}
    assert all(g is not None and g[0] >= -1e-12 for g in gaps.values())
    assert gaps["optimal"] == pytest.approx(gaps["brute_force"])
    assert gaps["brute_force"][0] <= gaps["greedy"][0] <= gaps["random"][0]
    table = format_table(res)
    assert "gap to bound" in table.splitlines()[1] and "certified upper bound" in table
    doc = res.to_json()
    assert doc["return_bound"]["seeds"] == [0, 1, 2, 3]
    assert doc["agents"]["greedy"]["gap_to_bound"]["mean"] == pytest.approx(gaps["greedy"][0])


def test_no_bound_where_the_family_or_objective_has_none(tmp_path: Path) -> None:
    assert bound_function("selenv/LandmarkSelection-v1") is None
    assert return_bounds(FIM, {**SMALL, "objective": "trace"}, [0, 1]) is None
    res = run_bench(FIM, ["greedy"], episodes=2, env_kwargs=SMALL, progress=False, bounds=False)
    assert not res.bounds and res.gap_to_bound("greedy") is None
    assert "gap to bound" not in format_table(res)
    out = tmp_path / "r.json"
    argv = ["bench", FIM, "--agents", "greedy", "--episodes", "2", "--no-progress", "--no-bounds"]
    assert main([*argv, "--env-kwargs", json.dumps(SMALL), "--json", str(out)]) == 0
    doc = json.loads(out.read_text())["results"][0]
    assert doc["return_bound"] is None and doc["agents"]["greedy"]["gap_to_bound"] is None
