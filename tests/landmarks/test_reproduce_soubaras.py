"""scripts/reproduce_soubaras.py: one --quick run; figures, cost ordering, RMSE vs CRLB, times.

Also checks the script's shortcut for the ``all`` method: driving ``LandmarkEKF`` with every
landmark gives the same filter as the env with ``k = N`` and the ``all`` agent.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from conftest import load_script

import selenv  # noqa: F401
from selenv.agents import make
from selenv.families.landmarks.scenario import LandmarkEKF

ENV_ID = "selenv/LandmarkSelection-v1"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("soubaras_figures")
    results = load_script("reproduce_soubaras").main(
        ["--quick", "--out", str(out), "--workers", "1"]
    )
    return out, results


def test_figures_written(run):
    out, results = run
    for name in ("soubaras_fig3", "soubaras_fig4", "soubaras_fig5", "soubaras_fig6"):
        path = out / f"{name}.png"
        assert path.is_file() and path.stat().st_size > 10_000, path
        assert results["figures"][name] == str(path)


def test_quick_config_and_shapes(run):
    _, results = run
    cfg = results["config"]
    assert cfg["quick"] and cfg["runs"] >= 3 and cfg["horizon"] >= 50
    T = cfg["horizon"]
    for m in ("all", "brute_force", "vns", "greedy"):
        s = results["methods"][m]
        for key in ("logdet_mean", "det_mean", "crlb_pos", "rmse", "filter_std"):
            assert s[key].shape == (T + 1,) and np.all(np.isfinite(s[key])), (m, key)
        assert np.all(s["rmse"] > 0)
    for m in ("brute_force", "vns", "greedy"):
        sels = results["methods"][m]["selections"]
        assert sels.shape == (cfg["runs"], T, 2)
        assert np.all(sels[..., 0] != sels[..., 1])  # two distinct landmarks per step
        assert results["methods"][m]["replay_gap"] < 1e-6  # the replay is the env's filter


def test_cost_ordering(run):
    _, results = run
    M, P = results["methods"], results["paired"]
    # every landmark beats any two by a wide margin (nats), at every step after the first
    assert M["all"]["cost_mean"] < M["brute_force"]["cost_mean"] - 5.0
    assert np.all(M["all"]["logdet_mean"][1:] < M["brute_force"]["logdet_mean"][1:])
    # brute force is optimal per step; over a trajectory VNS and greedy may be a hair lower,
    # but only by a small fraction of a nat per step
    tol = 0.05
    assert M["brute_force"]["cost_mean"] <= M["vns"]["cost_mean"] + tol
    assert M["brute_force"]["cost_mean"] <= M["greedy"]["cost_mean"] + tol
    assert abs(P["vns"]["logdet_gap_mean"]) < tol and abs(P["greedy"]["logdet_gap_mean"]) < tol
    # on the first step all three start from the same state: brute force is exactly optimal
    assert P["vns"]["logdet_gap_t"][0] >= -1e-9 and P["greedy"]["logdet_gap_t"][0] >= -1e-9


def test_vns_close_to_brute_force_on_the_same_states(run):
    _, results = run
    sv = results["solver"]
    assert sv["vns_same_first_step"] == 1.0  # warm start = brute force at the first step
    assert sv["vns_same_as_bf"] > 0.5
    assert 0.0 <= sv["vns_lost_mean"] < 0.01 and sv["vns_lost_max"] < 0.5


def test_crlb_of_selections_and_rmse(run):
    _, results = run
    M, conv = results["methods"], results["converged_mask"]
    crlb_all = M["all"]["crlb_pos"]
    for m in ("brute_force", "vns", "greedy"):
        # two landmarks carry less information than thirty, but the same order of magnitude
        ratio = M[m]["crlb_pos"][conv] / crlb_all[conv]
        assert np.all(ratio >= 1.0 - 1e-9) and np.all(ratio < 5.0), m
        assert M[m]["rmse_conv"] < 4.0 * M[m]["crlb_conv"], m
    # the all-landmark filter tracks its bound after convergence (within a factor of 3)
    rmse, crlb = M["all"]["rmse"][conv], crlb_all[conv]
    assert np.all(rmse < 3.0 * crlb) and np.all(rmse > crlb / 3.0)
    # the filter's own covariance equals the bound to first order (exact model, small errors)
    np.testing.assert_allclose(M["all"]["filter_std"][conv], crlb, rtol=0.05)


def test_table2_numbers_positive(run):
    _, results = run
    for key, row in results["table2"].items():
        assert row["mean"] > 0 and row["median"] > 0, key
        assert np.isfinite(row["mean"]) and row["mean"] < 1e3, key  # ms
    assert 0.0 <= results["solver"]["vns_changes"] <= 1.0


def test_direct_all_landmark_filter_equals_the_env_with_k_equal_n():
    n, horizon = 8, 15
    env = gym.make(ENV_ID, n_landmarks=n, k=n, horizon=horizon)
    obs, info = env.reset(seed=3)
    agent = make("all", ENV_ID)
    agent.reset(env, seed=3)
    costs, done = [], False
    while not done:
        obs, _, done, _, info = env.step(agent.act(obs, info))
        if info["picks"][0] < 0 or done:  # no pick open: an update just happened
            costs.append(info["objective"])
    ekf = LandmarkEKF(env.unwrapped.problem)
    direct = []
    for _ in range(horizon):
        ekf.predict()
        ekf.update(range(n))
        direct.append(ekf.logdet_P)
    np.testing.assert_allclose(costs, direct, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ekf.P, env.unwrapped.ekf.P, rtol=1e-12, atol=1e-15)
