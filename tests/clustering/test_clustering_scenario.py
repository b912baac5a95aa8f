"""Receiver-clustering scenario: model, cost eq. (10) and Algorithm 1 against independent truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.linalg import solve_discrete_are

from selenv.core.kalman import kf_predict, kf_update
from selenv.core.riccati import riccati_pass, riccati_step
from selenv.families.clustering.filters import ClusterFilterBank, cluster_keys
from selenv.families.clustering.scenario import (
    ClusteringConfig,
    MultipathRegimes,
    axis_to_full,
    canonical_labels,
    clustering_cost,
    make_clustering_problem,
)


def _problem(n=6, n_max=14, seed=0, **kw):
    cfg = ClusteringConfig(n_agents=n, n_max_states=n_max, **kw)
    return make_clustering_problem(cfg, np.random.default_rng(seed))


def _cost_full(problem, full_posteriors, keys):
    """Eq. (10) straight from the definitions on full covariances (independent of the code)."""
    total = sum(np.trace(P) for P in full_posteriors)
    states = sum(P.shape[0] for P in full_posteriors)
    J_G = total / states
    J_C = max(
        sum(np.trace(P[4 * a : 4 * a + 2, 4 * a : 4 * a + 2]) for a in range(len(k))) / (2 * len(k))
        for P, k in zip(full_posteriors, keys, strict=True)
    )
    J_L = max(
        np.trace(P[4 * a : 4 * a + 2, 4 * a : 4 * a + 2]) / 2
        for P, k in zip(full_posteriors, keys, strict=True)
        for a in range(len(k))
    )
    return J_G + J_C + J_L, J_G, J_C, J_L


def test_riccati_step_matches_joseph_kalman_update() -> None:
    prob = _problem()
    members = (0, 2, 5)
    F, Q, H = prob.axis_model(members)
    R = prob.axis_noise(members)
    P = prob.axis_prior(3)
    x = np.zeros(7)
    for _ in range(5):
        x, Pm = kf_predict(x, P, F, Q)
        P = kf_update(x, Pm, np.zeros(6), H, R).P
    hist = riccati_pass(prob.axis_prior(3)[None], F, Q, H, R, 5)
    np.testing.assert_allclose(hist[0, -1], P, rtol=1e-10, atol=1e-12)


def _multipath_problem(n: int, seed: int, horizon: int, **kw):
    """Fast regime switching so that R changes every few steps."""
    regimes = MultipathRegimes(p_enter=0.3, p_leave=0.4, degraded_factor=4.0)
    cfg = ClusteringConfig(n_agents=n, n_max_states=14, regimes=regimes, **kw)
    return make_clustering_problem(cfg, np.random.default_rng(seed), horizon=horizon)


@pytest.mark.parametrize("noise", ["fixed", "time-varying"])
def test_per_axis_filters_equal_the_full_model_and_cost_matches_definition(noise: str) -> None:
    if noise == "fixed":
        prob = _problem(n=7, n_max=14, seed=3)
    else:
        prob = _multipath_problem(7, 3, horizon=12)
        assert len({prob.sigma_at(k).tobytes() for k in range(13)}) > 6
    labels = np.array([0, 1, 0, 2, 1, 2, 0])
    bank = ClusterFilterBank(prob, labels)
    keys = bank.clusters
    Ps = [axis_to_full(prob.axis_prior(len(k))) for k in keys]
    for k in range(1, 13):
        bank.step()
        for c, key in enumerate(keys):
            A, Q, C, R = prob.full_model(key, k)  # R_k of the measurement at step k
            x, Pm = kf_predict(np.zeros(A.shape[0]), Ps[c], A, Q)
            Ps[c] = kf_update(x, Pm, np.zeros(C.shape[0]), C, R).P
    for P_axis, P_full in zip(bank.posteriors(), Ps, strict=True):
        np.testing.assert_allclose(axis_to_full(P_axis), P_full, rtol=1e-9, atol=1e-12)
    J, J_G, J_C, J_L = _cost_full(prob, Ps, keys)
    got = bank.cost()
    assert got.J == pytest.approx(J, rel=1e-10)
    assert (got.J_G, got.J_C, got.J_L) == pytest.approx((J_G, J_C, J_L), rel=1e-10)


def test_algorithm1_window_uses_the_past_noise_of_each_step() -> None:
    """Algorithm 1 at k with time-varying R against an independent full-model recursion."""
    tau, K = 5, 11
    prob = _multipath_problem(6, 8, horizon=K + 10, tau=tau)
    old = np.array([0, 0, 1, 1, 2, 2])
    bank = ClusterFilterBank(prob, old)
    for _ in range(K):
        bank.step()
    maps = prob.selection_maps(old)
    P_l = sum(  # step 1 (bias averaged over the old clusters), full coordinates, at l = k - tau
        Mu.T @ axis_to_full(bank.history(key)[0]) @ Mu
        + Ms.T @ axis_to_full(bank.history(key)[0]) @ Ms / len(maps)
        for key, (Mu, Ms) in zip(bank.clusters, maps, strict=True)
    )
    new = np.array([0, 1, 0, 2, 1, 2])
    keys = cluster_keys(canonical_labels(new))
    Ps = []
    for key, (Mu, Ms) in zip(keys, prob.selection_maps(new), strict=True):
        P = Mu @ P_l @ Mu.T + Ms @ P_l @ Ms.T  # step 2
        for k in range(K - tau + 1, K + 1):  # steps 3-9 over the window, R_k of each step
            A, Q, C, R = prob.full_model(key, k)
            x, Pm = kf_predict(np.zeros(A.shape[0]), P, A, Q)
            P = kf_update(x, Pm, np.zeros(C.shape[0]), C, R).P
        Ps.append(P)
    assert bank.evaluate(new)[0] == pytest.approx(_cost_full(prob, Ps, keys)[0], rel=1e-10)
    # the future noise (steps > k) plays no part in Algorithm 1
    future = prob.regimes.copy()
    future[K + 1 :] = 1.0 - future[K + 1 :]
    other = dataclasses.replace(prob, regimes=future)
    bank.problem = other
    bank._new_time_step()  # drop the step's caches: recompute with the altered problem
    assert bank.evaluate(new)[0] == pytest.approx(_cost_full(prob, Ps, keys)[0], rel=1e-10)


def test_long_run_converges_to_the_riccati_steady_state() -> None:
    prob = _problem(n=5, n_max=14, seed=1, dt=0.5)
    bank = ClusterFilterBank(prob, [0, 0, 1, 1, 1])
    for _ in range(400):
        bank.step()
    for key, P_axis in zip(bank.clusters, bank.posteriors(), strict=True):
        A, Q, C, R = prob.full_model(key)
        P_pred = solve_discrete_are(A.T, C.T, Q, R)  # steady prediction covariance
        S = C @ P_pred @ C.T + R
        P_post = P_pred - P_pred @ C.T @ np.linalg.solve(S, C @ P_pred)
        np.testing.assert_allclose(axis_to_full(P_axis), P_post, rtol=1e-6, atol=1e-9)


def test_composed_prior_matches_the_selection_map_formula() -> None:
    prob = _problem(n=6, n_max=14, seed=2)
    old = np.array([0, 0, 1, 1, 2, 2])
    bank = ClusterFilterBank(prob, old)
    for _ in range(prob.config.tau + 5):
        bank.step()
    # Algorithm 1 step 1 with the paper's maps, on full covariances at the window start l
    maps = prob.selection_maps(old)
    P_l = sum(
        Mu.T @ axis_to_full(bank.history(key)[0]) @ Mu
        + Ms.T @ axis_to_full(bank.history(key)[0]) @ Ms / len(maps)
        for key, (Mu, Ms) in zip(bank.clusters, maps, strict=True)
    )
    new = np.array([0, 1, 0, 2, 1, 2])
    for key, (Mu, Ms) in zip(
        cluster_keys(canonical_labels(new)), prob.selection_maps(new), strict=True
    ):
        expected = Mu @ P_l @ Mu.T + Ms @ P_l @ Ms.T  # step 2, read per new cluster
        np.testing.assert_allclose(axis_to_full(bank._composed_prior(key)), expected, atol=1e-14)


def test_algorithm1_keeps_unchanged_clusters_and_recomputes_the_rest() -> None:
    prob = _problem(n=6, n_max=14, seed=4)
    bank = ClusterFilterBank(prob, [0, 0, 1, 1, 2, 2])
    for _ in range(30):
        bank.step()
    assert bank.evaluate(bank.labels)[0] == pytest.approx(bank.cost().J, rel=1e-12)
    before = bank.posteriors()
    cand = np.array([0, 0, 1, 2, 1, 2])  # cluster {0, 1} unchanged
    bank.evaluate(cand)
    assert bank.n_cluster_passes == 2  # only {2, 4} and {3, 5} were filtered
    assert bank.recluster(cand)
    np.testing.assert_array_equal(bank.history((0, 1))[-1], before[0])
    assert bank.cost().J == pytest.approx(bank.evaluate(cand)[0], rel=1e-12)
    # a re-proposed cluster is served from the cache at the same time step
    bank.evaluate(np.array([0, 0, 1, 1, 2, 2]))
    passes = bank.n_cluster_passes
    bank.evaluate(np.array([[0, 0, 1, 1, 2, 2], [0, 0, 1, 2, 1, 2]]))
    assert bank.n_cluster_passes == passes and bank.n_cost_evaluations == 6


def test_remark2_single_cluster_beats_any_clustering_beats_singletons() -> None:
    sigma = _problem(n=9, seed=5).sigma
    costs = {}
    for name, labels, nmax in (
        ("single", np.zeros(9, int), None),
        ("triples", np.repeat(np.arange(3), 3), 14),
        ("singletons", np.arange(9), 14),
    ):
        prob = make_clustering_problem(
            ClusteringConfig(n_agents=9, n_max_states=nmax, sigma=sigma), None
        )
        bank = ClusterFilterBank(prob, labels)
        for _ in range(100):
            bank.step()
        costs[name] = bank.cost().J
    assert costs["single"] < costs["triples"] < costs["singletons"]


def test_cost_function_matches_bank_statistics() -> None:
    prob = _problem(n=6, seed=6, weights=(0.5, 2.0, 1.5))
    bank = ClusterFilterBank(prob, [0, 1, 1, 2, 2, 2 - 2])
    for _ in range(10):
        bank.step()
    direct = clustering_cost(bank.posteriors(), prob.config.weights)
    assert bank.evaluate(bank.labels)[0] == pytest.approx(direct.J, rel=1e-12)
    assert direct.J == pytest.approx(0.5 * direct.J_G + 2.0 * direct.J_C + 1.5 * direct.J_L)


def test_canonical_labels_and_feasibility_errors() -> None:
    np.testing.assert_array_equal(canonical_labels([5, 5, 2, 9, 2]), [0, 0, 1, 2, 1])
    prob = _problem(n=6, n_max=14)
    assert prob.max_cluster_size == 3
    with pytest.raises(
        ValueError, match=r"cluster 4 \(receivers \[0, 1, 2, 3\]\).*18 > n_max_states = 14"
    ):
        prob.check_clustering([4, 4, 4, 4, 1, 1])
    with pytest.raises(ValueError, match=r"shape \(6,\)"):
        prob.check_clustering([0, 1])
    with pytest.raises(ValueError, match=r"\[0, 6\)"):
        prob.check_clustering([0, 1, 2, 3, 4, 6])
    with pytest.raises(ValueError, match=">= 0"):
        prob.check_clustering([0, 1, 2, 3, 4, -1])
    with pytest.raises(ValueError, match="integer labels"):
        prob.check_clustering([0.5, 1, 2, 3, 4, 5])
    bank = ClusterFilterBank(prob, np.arange(6))
    with pytest.raises(ValueError, match=r"candidates\[1\]: cluster"):
        bank.evaluate([np.arange(6), np.zeros(6, int)])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"sigma": np.zeros((4, 2))}, r"sigma must be finite and > 0.*sigma\[0, 0\] = 0"),
        ({"sigma": np.ones((3, 2))}, r"shape \(n_agents, 2\) = \(4, 2\)"),
        ({"sigma": np.full((4, 2), np.nan)}, "finite"),
        ({"noise_correlation": 1.0}, r"\[0, 1\)"),
        ({"noise_correlation": -0.1}, r"\[0, 1\)"),
        ({"n_max_states": 5}, "below one receiver's state count N\\(C\\)=6"),
        ({"dt": 0.0}, "dt"),
        ({"tau": 0}, "tau"),
        ({"weights": (0, 0, 0)}, "weights"),
        ({"n_agents": 0}, "n_agents"),
    ],
)
def test_bad_config_is_a_clear_value_error(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        ClusteringConfig(**{"n_agents": 4, **kwargs})


def test_sigma_draw_is_seeded_and_in_unit_interval() -> None:
    a = _problem(n=30, seed=11).sigma
    b = _problem(n=30, seed=11).sigma
    np.testing.assert_array_equal(a, b)
    assert np.all((a > 0) & (a <= 1))
    with pytest.raises(ValueError, match="rng is required"):
        make_clustering_problem(ClusteringConfig(n_agents=3))


def test_riccati_pass_validates_input() -> None:
    F = np.eye(3)
    with pytest.raises(ValueError, match="P0"):
        riccati_pass(np.eye(3), F, F, np.eye(3), np.eye(3), 2)
    with pytest.raises(ValueError, match="R must have shape"):
        riccati_pass(np.eye(3)[None], F, F, np.eye(3), np.eye(2), 2)
    with pytest.raises(ValueError, match="steps"):
        riccati_pass(np.eye(3)[None], F, F, np.eye(3), np.eye(3), -1)
    P = riccati_step(np.eye(3)[None], F, F, np.eye(3), np.eye(3))
    np.testing.assert_allclose(P[0], np.eye(3) * 2 / 3)  # (2 I)^-1 + I^-1 = 1.5 I, inverse
