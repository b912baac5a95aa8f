"""scripts/record_standings.py: standings from bench JSON, interleaved timings, the reference."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from conftest import load_script

rs = load_script("record_standings")
FIM = "selenv/FIMSelection-v1"


def _agent(returns: list[float], base: list[float], seconds: float) -> dict[str, Any]:
    d = np.asarray(returns) - np.asarray(base)
    return {
        "returns": returns,
        "decision_seconds_mean": seconds,
        "paired": {
            "mean_diff": float(d.mean()),
            "ci95": [float(d.min()), float(d.max())],
            "wins": int((d > 0).sum()),
            "ties": int((d == 0).sum()),
            "losses": int((d < 0).sum()),
        },
    }


def _doc(baseline: str = "greedy") -> dict[str, Any]:
    base = [1.0, 2.0, 3.0, 4.0]
    return {
        "provenance": {"argv": ["selenv", "bench", FIM], "timestamp": "2026-12-07T05:00:00"},
        "results": [
            {
                "env_id": FIM,
                "env_kwargs": {},
                "seed": 30000,
                "episodes": 4,
                "baseline": baseline,
                "complete": True,
                "agents": {
                    "greedy": _agent(base, base, 0.001),
                    "brute_force": _agent(base, base, 0.001),
                    "ppo": _agent([1.5, 2.5, 3.0, 4.5], base, 0.004),
                    "ppo_general": _agent([1.5, 2.5, 3.0, 4.5], base, 0.004),
                    "ppo:top_m=8": _agent([1.0, 2.0, 3.0, 4.0], base, 0.002),
                    "rollout": _agent([2.0, 3.0, 4.0, 5.0], base, 0.1),
                    "swap": _agent([1.1, 2.1, 3.1, 4.1], base, 0.002),
                },
            }
        ],
    }


def test_records_and_their_aliases_are_recorded_with_the_reference_share() -> None:
    got = rs.standings_of(_doc())
    names = sorted(entry["agent"] for _, entry in got)
    assert names == ["ppo", "ppo"]  # the record and its alias; no options, no heuristics
    entry = got[0][1]
    assert entry["mean_difference"] == pytest.approx(0.375)
    assert (entry["wins"], entry["ties"], entry["losses"]) == (3, 1, 0)
    assert entry["decision_time_ratio"] == pytest.approx(4.0)
    ref = entry["reference"]
    assert ref["agent"] == "rollout" and ref["share_of_edge"] == pytest.approx(0.375)
    lo, hi = ref["share_ci95"]
    assert lo <= 0.375 <= hi


def test_a_run_against_another_baseline_is_skipped(capsys: pytest.CaptureFixture[str]) -> None:
    assert rs.standings_of(_doc(baseline="brute_force")) == []
    assert "skipped" in capsys.readouterr().err


def test_interleaved_timings_replace_the_bench_ratios() -> None:
    (_, entry), _ = rs.standings_of(_doc())
    timing = {
        "env_id": FIM,
        "env_kwargs": {},
        "baseline": "greedy",
        "command": "benchmarks/bench_decision_time.py ...",
        "agents": {"greedy": {"ratio": 1.0}, "ppo": {"ratio": 2.5}, "rollout": {"ratio": 30.0}},
    }
    timed = rs.with_timing(entry, [timing])
    assert timed["decision_time_ratio"] == 2.5
    assert timed["reference"]["decision_time_ratio"] == 30.0
    assert timed["decision_time_command"] == timing["command"]
    other = {**timing, "env_kwargs": {"budget": 3}}
    assert rs.with_timing(entry, [other]) == entry  # another configuration: not used


def test_share_of_edge_is_the_ratio_of_mean_edges() -> None:
    base = np.zeros(5)
    share, (lo, hi) = rs.share_of_edge(np.full(5, 2.0), np.full(5, 4.0), base)
    assert share == 0.5 and lo == hi == 0.5
