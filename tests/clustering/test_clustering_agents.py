"""Clustering agents in selenv/ReceiverClustering-v1, and the Greiff reproduction script."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from conftest import load_script

import selenv  # noqa: F401
from selenv.agents import agents_for, make
from selenv.families.clustering.filters import ClusterFilterBank
from selenv.families.clustering.ga import GAConfig, GeneticClustering
from selenv.families.clustering.labels import random_feasible_clustering
from selenv.families.clustering.scenario import ClusteringConfig, make_clustering_problem

ENV_ID = "selenv/ReceiverClustering-v1"


def _play(env, agent, seed, options=None):
    obs, info = env.reset(seed=seed, options=options)
    agent.reset(env, seed=seed)
    out = [(obs["assignment"].copy(), info["objective"])]
    done = False
    while not done:
        obs, _, term, trunc, info = env.step(agent.act(obs, info))
        out.append((obs["assignment"].copy(), info["objective"]))
        done = term or trunc
    return out


def test_registered_agents() -> None:
    names = set(agents_for(ENV_ID))
    assert {"ga", "greedy", "fixed_random", "singletons", "single_cluster"} <= names
    assert {"offline_static", "rollout"} <= names


def test_offline_static_keeps_one_solved_partition() -> None:
    for preset in ("paper", "multipath"):
        env = gym.make(ENV_ID, n_agents=9, horizon=40, tau=8, preset=preset)
        traj = _play(env, make("offline_static", ENV_ID), seed=5)
        labels = [lab for lab, _ in traj[1:]]
        assert all(np.array_equal(lab, labels[0]) for lab in labels)
        assert np.bincount(labels[0]).max() <= 3
        if preset == "paper":  # fixed noise: the offline solution beats a random partition
            keep = _play(env, make("fixed_random", ENV_ID), seed=5)
            assert sum(j for _, j in traj) < sum(j for _, j in keep)
    with pytest.raises(ValueError, match="levels"):
        make("offline_static", ENV_ID, levels="future")
    with pytest.raises(ValueError, match="warmup"):
        make("offline_static", ENV_ID, warmup=-1)


def test_ga_agent_waits_then_improves_and_stays_feasible() -> None:
    env = gym.make(ENV_ID, n_agents=12, horizon=40)
    agent = make("ga", ENV_ID, start_step=10)
    traj = _play(env, agent, seed=1)
    start = traj[0][0]
    for labels, _ in traj[:11]:
        np.testing.assert_array_equal(labels, start)  # k < 10: the initial clustering is kept
    assert all(np.bincount(lab).max() <= 3 for lab, _ in traj)
    keep = _play(env, make("fixed_random", ENV_ID), seed=1)  # same realisation, other start
    assert traj[-1][1] < traj[10][1]
    assert traj[-1][1] < np.mean([j for _, j in keep[-5:]]) * 1.05
    again = _play(env, make("ga", ENV_ID, start_step=10), seed=1)
    assert [j for _, j in again] == [j for _, j in traj]  # same seed, same trajectory


def test_ga_every_n_t_steps_only() -> None:
    env = gym.make(ENV_ID, n_agents=9, horizon=12)
    traj = _play(env, make("ga", ENV_ID, every=4), seed=2)
    changes = [k for k in range(1, len(traj)) if not np.array_equal(traj[k][0], traj[k - 1][0])]
    assert all((k - 1) % 4 == 0 for k in changes)  # actions at k = 0, 4, 8 may change it


def test_ga_best_cost_never_rises_at_a_fixed_time_on_the_real_cost() -> None:
    rng = np.random.default_rng(3)
    problem = make_clustering_problem(ClusteringConfig(n_agents=15), rng)
    bank = ClusterFilterBank(problem, random_feasible_clustering(15, 3, rng))
    for _ in range(25):
        bank.step()
    ga = GeneticClustering(bank.evaluate, bank.labels, 3, GAConfig(), rng=rng)
    best = [ga.best_cost]
    for _ in range(15):
        labels, cost = ga.generation()
        assert np.bincount(labels).max() <= 3
        best.append(cost)
    assert np.all(np.diff(best) <= 1e-15) and best[-1] < best[0]


def test_greedy_improves_on_its_start_in_both_action_modes() -> None:
    for mode in ("assignment", "edit"):
        env = gym.make(ENV_ID, n_agents=9, horizon=15, action_mode=mode)
        agent = make("greedy", ENV_ID, every=1)
        traj = _play(env, agent, seed=4)
        keep_env = gym.make(ENV_ID, n_agents=9, horizon=15)
        obs, _ = keep_env.reset(seed=4)
        for _ in range(15):
            obs, _, _, _, info = keep_env.step(obs["assignment"])
        assert traj[-1][1] < info["objective"]
        assert all(np.bincount(lab).max() <= 3 for lab, _ in traj)


def test_fixed_agents() -> None:
    env = gym.make(ENV_ID, n_agents=10, horizon=5)
    traj = _play(env, make("fixed_random", ENV_ID), seed=0)
    labels = [lab for lab, _ in traj[1:]]
    assert all(np.array_equal(lab, labels[0]) for lab in labels)
    assert sorted(np.bincount(labels[0]).tolist()) == [2, 2, 3, 3]
    sing = _play(env, make("singletons", ENV_ID), seed=0)
    np.testing.assert_array_equal(sing[-1][0], np.arange(10))
    with pytest.raises(ValueError, match=r"unconstrained lower bound.*n_max_states=None"):
        make("single_cluster", ENV_ID).reset(env, seed=0)
    free = gym.make(ENV_ID, n_agents=10, horizon=5, n_max_states=None)
    one = _play(free, make("single_cluster", ENV_ID), seed=0)
    assert one[-1][0].max() == 0 and one[-1][1] < sing[-1][1]


def test_agents_refuse_the_wrong_env_or_mode() -> None:
    edit = gym.make(ENV_ID, n_agents=6, horizon=3, action_mode="edit")
    edit.reset(seed=0)
    with pytest.raises(ValueError, match="action_mode"):
        make("ga", ENV_ID).reset(edit, seed=0)
    fim = gym.make("selenv/FIMSelection-v1", n_candidates=5, budget=2)
    fim.reset(seed=0)
    with pytest.raises(ValueError, match="needs selenv/ReceiverClustering-v1"):
        make("ga", ENV_ID).reset(fim, seed=0)
    with pytest.raises(ValueError, match="every"):
        make("ga", ENV_ID, every=0)
    with pytest.raises(ValueError, match="population_size"):
        make("ga", ENV_ID, population_size=1)


# -- scripts/reproduce_greiff.py --quick ----------------------------------------------------------


@pytest.fixture(scope="module")
def repro(tmp_path_factory):
    module = load_script("reproduce_greiff")
    out = tmp_path_factory.mktemp("greiff")
    argv = ["--quick", "--out", str(out), "--workers", "1", "--store", str(out / "store")]
    return out, module.main(argv)


def test_reproduction_resumes_from_its_store(repro) -> None:
    """Run again on the same --store, nothing is recomputed and every number is the same."""
    out, res = repro
    module = load_script("reproduce_greiff")
    argv = ["--quick", "--out", str(out / "again"), "--store", str(out / "store")]
    again = module.main([*argv, "--executor", "local"])
    for ops, row in res["table2"].items():
        np.testing.assert_array_equal(again["table2"][ops]["J"], row["J"])
        assert again["table2"][ops]["k_star"] == row["k_star"]
    for name, curves in res["fig3"].items():
        np.testing.assert_array_equal(again["fig3"][name]["J"], curves["J"])
    assert again["config"]["stored_wall_time_s"] == res["config"]["stored_wall_time_s"] > 0


def test_reproduction_writes_figures_and_orders_the_methods(repro) -> None:
    out, res = repro
    for name in ("greiff_fig3", "greiff_table2", "greiff_fig4"):
        assert (out / f"{name}.png").stat().st_size > 10_000
    f3 = res["fig3"]
    final = {k: np.atleast_2d(f3[k]["J"])[:, -1].mean() for k in f3}
    # Fig. 3 ordering: single cluster < GA < fixed random < singletons
    assert final["single_cluster"] < final["ga"] < final["fixed_random"] < final["singletons"]
    assert set(res["table2"]) and all(len(r["k_star"]) == 3 for r in res["table2"].values())
    f4 = res["fig4"]
    assert f4["m"][-1] < f4["m"][0] == 15  # N_max = 42: the GA merges clusters


def test_bench_counts_cost_evaluations_per_decision() -> None:
    """info["cost_evaluations"] reaches the bench: GA 20 per generation, a fixed clustering 0."""
    from selenv.bench import format_table, run_bench

    res = run_bench(
        "selenv/ReceiverClustering-v1",
        ["ga", "fixed_random", "greedy"],
        episodes=2,
        env_kwargs={"n_agents": 9, "horizon": 10},
        progress=False,
    )
    ga, fixed, greedy = (res.agents[a] for a in ("ga", "fixed_random", "greedy"))
    # one initial population (20) then one generation of 20 per step (10 per episode)
    assert ga.cost_evaluations == 2 * (20 + 10 * 20)
    assert ga.cost_evaluations_per_decision == pytest.approx(22.0)
    assert fixed.cost_evaluations == 0
    # greedy searches every 5th step, costing every allowed edit of the labels it sees
    assert greedy.cost_evaluations is not None and greedy.cost_evaluations > 0
    assert res.to_json()["agents"]["ga"]["cost_evaluations_per_decision"] == pytest.approx(22.0)
    assert "cost evals/decision" in format_table(res).splitlines()[1]


def test_reproduction_ga_variant_option(capsys) -> None:
    """--ga-variant: improved by default, literal / both accepted, anything else exit 2."""
    module = load_script("reproduce_greiff")
    assert module.parse_args([]).ga_variant == "improved"
    for v in ("improved", "literal", "both"):
        assert module.parse_args(["--ga-variant", v]).ga_variant == v
    with pytest.raises(SystemExit) as exc:
        module.parse_args(["--ga-variant", "Literal"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--ga-variant" in err and "'improved', 'literal', 'both'" in err
    assert module.ga_kwargs("improved") == {"start_step": module.GA_START}
    assert module.ga_kwargs("literal", operators=(1, 1, 1, 1, 1))["variant"] == "literal"


def test_k_star_bootstrap_is_paired_and_brackets_known_shifts() -> None:
    """Curves delayed by a known number of steps move k* by that shift, in every resample."""
    module = load_script("reproduce_greiff")
    rng = np.random.default_rng(3)
    runs, K = 40, 300
    rates = rng.uniform(0.02, 0.05, size=(runs, 1))
    k = np.arange(K + 1)
    base = 1.0 + 2.0 * np.exp(-rates * k)  # decreasing, noisy across runs
    shifted = 1.0 + 2.0 * np.exp(-rates * np.maximum(k - 25, 0))  # the same runs, 25 steps later
    ref = (1, 1, 1, 1, 1)
    out = module.k_star_bootstrap({(0, 1, 1, 1, 1): shifted, ref: base}, 0.01, ref, n_boot=200)
    assert out[ref]["diff"] == (0.0, 0.0)
    lo, hi = out[(0, 1, 1, 1, 1)]["diff"]
    # the curves differ only by the delay, up to the final-cost normalisation: k* moves by ~25
    assert 20 <= lo <= hi <= 30
    klo, khi = out[ref]["k"]
    assert klo <= module.k_star(base, 0.01) <= khi


def test_paired_final_cost_matches_scipy_paired_t() -> None:
    from scipy import stats

    module = load_script("reproduce_greiff")
    rng = np.random.default_rng(4)
    a, b = rng.normal(1.0, 0.1, (30, 5)), rng.normal(1.02, 0.1, (30, 5))
    mean, lo, hi = module.paired_final_cost(a, b)
    ci = stats.ttest_rel(a[:, -1], b[:, -1]).confidence_interval(0.95)
    assert mean == pytest.approx(float(np.mean(a[:, -1] - b[:, -1])))
    assert (lo, hi) == pytest.approx((ci.low, ci.high))


def test_reproduction_save_folder_checked_before_work(tmp_path, capsys) -> None:
    module = load_script("reproduce_greiff")
    with pytest.raises(SystemExit) as exc:
        module.parse_args(["--save", str(tmp_path / "missing" / "t.npz")])
    assert exc.value.code == 2 and "--save" in capsys.readouterr().err
