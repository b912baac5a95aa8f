"""PettingZoo modules in the bench: multi-agent policies, centralised references, CLI and JSON."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import random_pool, random_spd

from selenv.agents import AGENTS, AgentSpec, agents_for, default_agents, make
from selenv.agents.fim_solvers import (
    brute_force_whitened,
    greedy_whitened,
    partition_greedy_whitened,
    partition_swap_whitened,
)
from selenv.agents.multiagent import CLUSTERING_MODULE, FIM_MODULE
from selenv.bench import multiagent_modules, plot_filename, run_bench
from selenv.cli import main
from selenv.core.information import as_candidates, logdet_objective
from selenv.families.clustering.multiagent_agents import ClusteringGreedyPolicy
from selenv.families.fim.multiagent_agents import CentralizedFIMPolicy, FIMGreedyPolicy
from selenv.multiagent import fim_selection_v0, receiver_clustering_v1
from selenv.multiagent.receiver_clustering_v1 import resolve_moves

FIM_KW = {"n_candidates": 10, "budgets": 3}
CL_KW = {"n_agents": 9, "horizon": 20}


def _pooled(seed: int, N: int = 12, d: int = 4) -> tuple[np.ndarray, np.ndarray]:
    r = np.random.default_rng(seed)
    Q0 = random_spd(r, d, 0.2)
    H, R = random_pool(r, N, d, m=2, pad=True)
    return as_candidates(Q0, H, R)


# -- partition-matroid solvers -------------------------------------------------------------------
def test_partition_greedy_respects_budgets_and_is_greedy_with_one_group() -> None:
    Q0, G = _pooled(0)
    groups, budgets = [[0, 2, 4, 6, 8, 10], [1, 3, 5], [7, 9, 11]], [2, 1, 3]
    sel = partition_greedy_whitened(Q0, G, groups, budgets)
    for members, budget in zip(groups, budgets, strict=True):
        assert sum(k in members for k in sel.indices) == budget
    assert sel.objective == pytest.approx(logdet_objective(Q0, G, list(sel.indices)))
    one = partition_greedy_whitened(Q0, G, [list(range(12))], [4])
    assert one.indices == greedy_whitened(Q0, G, 4).indices


def test_partition_swap_improves_keeps_counts_and_bounds_hold() -> None:
    for seed in range(8):
        Q0, G = _pooled(seed)
        groups, budgets = [list(range(0, 6)), list(range(6, 12))], [2, 2]
        g = partition_greedy_whitened(Q0, G, groups, budgets)
        s = partition_swap_whitened(Q0, G, groups, budgets)
        assert s.objective >= g.objective - 1e-12
        assert sorted(k // 6 for k in s.indices) == [0, 0, 1, 1]
        # optimum under the partition: best pair of group 0 with best pair of group 1
        best = -math.inf
        for a in range(6):
            for b in range(a + 1, 6):
                for c in range(6, 12):
                    for e in range(c + 1, 12):
                        best = max(best, logdet_objective(Q0, G, [a, b, c, e]))
        assert g.objective >= best / 2 - 1e-12  # matroid greedy bound
        assert s.objective <= best + 1e-9
        # one group holding everything: the unconstrained problem, brute force is the ceiling
        assert partition_swap_whitened(Q0, G, [list(range(12))], [3]).objective <= (
            brute_force_whitened(Q0, G, 3).objective + 1e-9
        )


def test_partition_solvers_validate_their_input() -> None:
    Q0, G = _pooled(1)
    with pytest.raises(ValueError, match="disjoint"):
        partition_greedy_whitened(Q0, G, [[0, 1], [1, 2]], [1, 1])
    with pytest.raises(ValueError, match="larger than the pool"):
        partition_greedy_whitened(Q0, G, [[0, 1]], [3])
    with pytest.raises(ValueError, match="outside"):
        partition_greedy_whitened(Q0, G, [[0, 12]], [1])
    with pytest.raises(ValueError, match="must match"):
        partition_greedy_whitened(Q0, G, [[0, 1]], [1, 1])
    with pytest.raises(ValueError, match="initial"):
        partition_swap_whitened(Q0, G, [[0, 1, 2], [3, 4]], [1, 1], initial=[0, 1])


# -- fim_selection_v0 ---------------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["cooperative", "independent"])
def test_centralized_plan_respects_pools_budgets_and_turns(mode: str) -> None:
    env = fim_selection_v0.parallel_env(
        mode=mode, invalid_action="raise", **{**FIM_KW, "budgets": [2, 4]}
    )
    for swap in (False, True):
        policy = CentralizedFIMPolicy(swap=swap)
        obs, infos = env.reset(seed=3)
        policy.reset(env, seed=3)
        played: dict[str, list[int]] = {a: [] for a in env.agents}
        while env.agents:
            actions = policy.act(obs, infos)
            for a in env.agents:
                if infos[a]["on_turn"]:
                    played[a].append(actions[a])
            obs, _rew, _terms, _truncs, infos = env.step(actions)  # raises on a masked pick
        P = env.problem
        assert policy.selection is not None
        picks = [int(P.pool(i)[k]) for i, a in enumerate(played) for k in played[a]]
        assert sorted(picks) == sorted(policy.selection.indices)
        assert {a: len(v) for a, v in played.items()} == {"agent_0": 2, "agent_1": 4}
        for i, a in enumerate(played):
            assert len(set(played[a])) == len(played[a]) and max(played[a]) < len(P.pool(i))
        final = next(iter(infos.values()))["objective"]
        assert final == pytest.approx(logdet_objective(P.Q0, P.G, picks), rel=1e-9)
        assert final == pytest.approx(policy.selection.objective, rel=1e-9)


def test_fim_module_bench_defaults_same_seeds_and_ordering(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: dict[str, list[tuple[int | None, float]]] = {}

    class Recorder(FIMGreedyPolicy):
        def reset(self, env: Any, seed: int | None = None) -> None:
            super().reset(env, seed)
            seen.setdefault(self.name, []).append((seed, float(env.problem.G.sum())))

    for tag in ("rec_a", "rec_b"):
        cls = type(tag, (Recorder,), {"name": tag})
        monkeypatch.setitem(AGENTS, tag, {FIM_MODULE: AgentSpec(tag, (FIM_MODULE,), cls)})
    names = ["greedy", "random", "centralized_greedy", "centralized_swap", "rec_a", "rec_b"]
    res = run_bench(FIM_MODULE, names, episodes=3, seed=11, progress=False)
    assert res.kind == "pettingzoo" and list(res.agents) == names
    assert seen["rec_a"] == seen["rec_b"] and [s for s, _ in seen["rec_a"]] == [11, 12, 13]
    r = {n: np.array(res.agents[n].returns) for n in names}
    assert np.all(r["centralized_swap"] >= r["centralized_greedy"] - 1e-9)
    assert r["centralized_greedy"].mean() >= r["random"].mean()
    np.testing.assert_allclose(r["greedy"], r["rec_a"])  # the same greedy on the same seeds
    # the return is the sum of the shared reward: the centre's final objective f
    for n in names:
        np.testing.assert_allclose(res.agents[n].returns, res.agents[n].final_objectives)
    assert res.baseline_name == "centralized_swap" and res.random_reference == "random"
    assert res.normalized_score("centralized_swap") == 1.0


def test_centralized_greedy_beats_independent_greedy_on_average() -> None:
    res = run_bench(
        FIM_MODULE,
        ["greedy", "centralized_greedy"],
        episodes=4,
        env_kwargs={"mode": "independent", **FIM_KW},
        baseline="greedy",
        progress=False,
    )
    p = res.paired("centralized_greedy")
    assert p is not None and p.mean_diff > 0


# -- receiver_clustering_v1 -----------------------------------------------------------------------
def test_clustering_greedy_edits_are_accepted_and_help_from_singletons() -> None:
    env = receiver_clustering_v1.parallel_env(initial="singletons", invalid_action="raise", **CL_KW)
    policy = make("greedy", CLUSTERING_MODULE)
    obs, infos = env.reset(seed=2)
    policy.reset(env, seed=2)
    changed = 0
    while env.agents:
        obs, _rew, _terms, _truncs, infos = env.step(policy.act(obs, infos))
        assert all(info["accepted"] for info in infos.values())  # the planned edit happened
        changed += next(iter(infos.values()))["changed"]
    assert changed > 0
    res = run_bench(
        CLUSTERING_MODULE,
        ["stay", "greedy"],
        episodes=2,
        env_kwargs={**CL_KW, "initial": "singletons"},
        progress=False,
    )
    assert res.agents["greedy"].mean_return > res.agents["stay"].mean_return


def test_clustering_greedy_leaves_out_swaps_the_resolution_rule_rejects() -> None:
    # clusters {0,1,2} and {3,4,5} (full), {6,7} and {8,9} (room), max_size 3
    labels = np.array([0, 0, 0, 1, 1, 1, 2, 2, 3, 3])
    n = labels.size
    for order in (np.arange(n), np.arange(n)[::-1]):  # a full-full swap: both rejected
        targets = labels.copy()
        targets[0], targets[3] = 1, 0
        new, accepted = resolve_moves(labels, targets, 3, order)
        assert np.array_equal(new, labels) and not accepted[0] and not accepted[3]
    edits = ClusteringGreedyPolicy().allowed_edits(labels, 3)
    iu, ju = np.triu_indices(n, k=1)
    swaps = [(int(iu[a - 1 - n * n]), int(ju[a - 1 - n * n])) for a in edits if a > n * n]
    assert swaps == [(6, 8), (6, 9), (7, 8), (7, 9)]  # only between the clusters with room
    for i, j in swaps:  # carried out whatever the visiting order
        targets = labels.copy()
        targets[i], targets[j] = labels[j], labels[i]
        for order in (np.arange(n), np.arange(n)[::-1]):
            assert resolve_moves(labels, targets, 3, order)[1].all()
    assert not ClusteringGreedyPolicy(swaps=False).allowed_edits(labels, 3).max() > n * n


def test_clustering_module_bench_runs_every_agent() -> None:
    res = run_bench(CLUSTERING_MODULE, episodes=2, env_kwargs={"horizon": 15}, progress=False)
    # the retired shipped rllib module (it plays `stay`) is not run by default
    assert list(res.agents) == default_agents(CLUSTERING_MODULE)
    assert {"random", "stay", "greedy"} <= set(res.agents)
    assert "rllib" in agents_for(CLUSTERING_MODULE) and "rllib" not in res.agents
    for r in res.agents.values():
        assert r.skipped is None and len(r.returns) == 2
        assert all(f > 0 for f in r.final_objectives)  # J
        assert all(ret < 0 for ret in r.returns)  # sum of -J
    assert res.random_reference == "random"


# -- CLI and JSON ----------------------------------------------------------------------------
def test_json_shape_is_the_same_for_single_and_multi_agent(tmp_path: Path) -> None:
    out = tmp_path / "res.json"
    argv = ["bench", "selenv/FIMSelection-v1", FIM_MODULE, "--agents", "greedy,random"]
    assert main([*argv, "--episodes", "2", "--json", str(out), "--no-progress"]) == 0
    single, multi = json.loads(out.read_text())["results"]
    assert single["kind"] == "gymnasium" and multi["kind"] == "pettingzoo"
    assert set(single) == set(multi)
    for name in ("greedy", "random"):
        assert set(single["agents"][name]) == set(multi["agents"][name])
        assert set(single["agents"][name]["paired"]) == set(multi["agents"][name]["paired"])


def test_cli_runs_a_module_with_a_baseline_and_plots(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plots = tmp_path / "plots"
    argv = ["bench", FIM_MODULE, "--env-kwargs", json.dumps(FIM_KW), "--episodes", "3"]
    assert main([*argv, "--baseline", "greedy", "--plot", str(plots), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(FIM_MODULE) and "Δ vs greedy [95 % CI]" in out
    assert (plots / plot_filename(FIM_MODULE)).stat().st_size > 1000
    assert plot_filename(FIM_MODULE) == "fim_selection_v0.png"
    bad = ["bench", FIM_MODULE, "--agents", "greedy", "--baseline", "stay", "--no-progress"]
    assert main(bad) == 2
    assert main(["bench", FIM_MODULE, "--env-kwargs", '{"nope": 1}', "--no-progress"]) == 2
    assert "--env-kwargs" in capsys.readouterr().err


def test_list_shows_the_modules_and_their_agents(capsys: pytest.CaptureFixture[str]) -> None:
    assert multiagent_modules() == [
        FIM_MODULE,
        CLUSTERING_MODULE,
        "selenv.multiagent.receiver_clustering_v0",  # release 0.1's, after the current ones
    ]
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for module in (FIM_MODULE, CLUSTERING_MODULE):
        assert f"\n{module}\n" in out
    block = out.split(f"\n{FIM_MODULE}\n")[1].split("\n\n")[0]
    for name in ("greedy", "random", "centralized_greedy", "centralized_swap"):
        assert f"  {name} " in block
