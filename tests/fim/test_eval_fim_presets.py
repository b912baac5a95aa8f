"""scripts/eval_fim_presets.py: every cell's paired standing and its gap to the certified bound."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
from conftest import load_script

from selenv.agents import make
from selenv.agents.fim_exact import relaxation_bound_whitened
from selenv.bench.results import AgentResult
from selenv.bench.runner import run_episode


def test_cells_report_the_gap_to_the_relaxation_bound(tmp_path: Path, capsys) -> None:
    script = load_script("eval_fim_presets")
    out = tmp_path / "cells.json"
    args = ["--agent", "swap", "--presets", "example2_moving", "--budgets", "3", "--episodes", "3"]
    assert script.main([*args, "--env-kwargs", '{"n_candidates": 40}', "--json", str(out)]) == 0
    (c,) = json.loads(out.read_text())["cells"]
    assert c["bound_method"].startswith("continuous relaxation")
    # the gap recomputed seed by seed: the relaxation bound of each reset, swap's return
    env = gym.make("selenv/FIMSelection-v1", preset="example2_moving", budget=3, n_candidates=40)
    gaps = []
    for seed in (1000, 1001, 1002):
        env.reset(seed=seed)
        s = env.unwrapped.state
        bound = relaxation_bound_whitened(s.information, s.G, 3).bound
        ret = run_episode(env, make("swap", "selenv/FIMSelection-v1"), seed, AgentResult("swap"))[0]
        gaps.append((bound - ret) / abs(bound))
    np.testing.assert_allclose(c["gap_to_bound"]["mean"], np.mean(gaps), rtol=1e-9)
    assert 0.0 <= c["gap_to_bound"]["mean"] <= c["greedy_gap_to_bound"]["mean"]
    lo, hi = c["gap_to_bound"]["ci95"]
    assert lo <= c["gap_to_bound"]["mean"] <= hi
    table = capsys.readouterr().out
    assert "gap to bound: swap" in table and " %" in table.splitlines()[-1]
