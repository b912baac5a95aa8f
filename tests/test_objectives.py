"""A- and E-optimal objectives (trace / max_eig of the CRLB) in the solvers, envs and agents.

Every check here recomputes ``f`` independently: the inverse of the summed FIM (``np.linalg.inv``,
not the Cholesky / Woodbury paths of the code), enumerations with ``itertools`` and a naive
greedy written in the test.
"""

from __future__ import annotations

import itertools

import gymnasium as gym
import numpy as np
import pytest

import selenv
from selenv.agents import fim_solvers as fs
from selenv.agents.vns import vns_whitened
from selenv.core.information import LogDetGainState, logdet_objective
from selenv.core.objectives import (
    CriterionGainState,
    criterion_gains,
    make_gain_state,
    objective_value,
)

FIM_ID = "selenv/FIMSelection-v1"
LM_ID = "selenv/LandmarkSelection-v1"
CASES = [("trace", None), ("trace", [0, 2]), ("max_eig", None), ("max_eig", [1, 3, 4])]


def _instance(seed: int, N: int = 9, m: int = 2, d: int = 5) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((d, d))
    return A @ A.T + 0.3 * np.eye(d), rng.standard_normal((N, m, d))


def _f(Q0, G, S, objective, interest=None) -> float:
    """Independent ``f(S)``: explicit inverses of ``Q0`` and of the summed FIM."""
    d = Q0.shape[0]
    A = Q0 + sum((G[k].T @ G[k] for k in S), np.zeros((d, d)))
    if objective == "logdet":
        return float(np.linalg.slogdet(A)[1] - np.linalg.slogdet(Q0)[1])
    E = np.eye(d) if interest is None else np.eye(d)[list(interest)]

    def crit(P):
        B = E @ P @ E.T
        return np.trace(B) if objective == "trace" else np.max(np.linalg.eigvalsh(B))

    return float(crit(np.linalg.inv(Q0)) - crit(np.linalg.inv(A)))


def _naive_greedy(Q0, G, budget, objective, interest=None) -> list[int]:
    S: list[int] = []
    for _ in range(budget):
        vals = [
            _f(Q0, G, [*S, k], objective, interest) if k not in S else -np.inf
            for k in range(G.shape[0])
        ]
        S.append(int(np.argmax(vals)))
    return S


@pytest.mark.parametrize("m", [1, 2, 3])
@pytest.mark.parametrize(("objective", "interest"), CASES)
def test_gains_match_direct_recomputation(m, objective, interest) -> None:
    for seed in range(3):
        Q0, G = _instance(seed, m=m)
        st = CriterionGainState(Q0, G, objective, interest=interest)
        for _ in range(4):
            before = _f(Q0, G, st.order, objective, interest)
            direct = [_f(Q0, G, [*st.order, k], objective, interest) - before for k in range(9)]
            sel = st.selected
            np.testing.assert_allclose(st.gains[~sel], np.array(direct)[~sel], atol=1e-10)
            assert st.gain_of(3) == pytest.approx(direct[3], abs=1e-10)
            j = int(np.argmax(st.masked_gains()))
            gain = st.add(j)
            assert gain == pytest.approx(direct[j], abs=1e-10)
            assert st.objective == pytest.approx(
                _f(Q0, G, st.order, objective, interest), abs=1e-10
            )
        assert objective_value(Q0, G, st.order, objective, interest) == pytest.approx(
            st.objective, abs=1e-10
        )


def test_trace_rank_one_gain_closed_form_and_finite_difference() -> None:
    rng = np.random.default_rng(7)
    d = 4
    A = rng.standard_normal((d, d))
    Q0 = A @ A.T + np.eye(d)
    P = np.linalg.inv(Q0)
    g = rng.standard_normal(d)
    E = np.eye(d)[[0, 1]]
    # Sherman-Morrison closed form of tr(E P E^T) - tr(E (Q0 + g g^T)^-1 E^T)
    closed = float(np.sum((E @ P @ g) ** 2) / (1.0 + g @ P @ g))
    gain = criterion_gains(P, g[None, None, :], "trace", np.array([0, 1]))[0]
    assert gain == pytest.approx(closed, rel=1e-12)
    direct = np.trace(E @ P @ E.T) - np.trace(E @ np.linalg.inv(Q0 + np.outer(g, g)) @ E.T)
    assert gain == pytest.approx(direct, rel=1e-9)

    # d/dt gain(sqrt(t) g) at t = 0 is |E P g|^2 (first-order perturbation of the inverse)
    def tr_post(t: float) -> float:
        return float(np.trace(E @ np.linalg.inv(Q0 + t * np.outer(g, g)) @ E.T))

    h = 1e-5
    fd = -(tr_post(h) - tr_post(-h)) / (2 * h)
    assert fd == pytest.approx(float(np.sum((E @ P @ g) ** 2)), rel=1e-6)
    small = criterion_gains(P, np.sqrt(h) * g[None, None, :], "trace", np.array([0, 1]))[0]
    assert small / h == pytest.approx(fd, rel=1e-4)


@pytest.mark.parametrize("objective", ["logdet", "trace", "max_eig"])
def test_brute_force_matches_itertools_enumeration_on_raw_arrays(objective) -> None:
    interest = None if objective == "logdet" else [0, 3]
    for seed in range(4):
        rng = np.random.default_rng(100 + seed)
        d, N, m = 5, 8, 2
        A = rng.standard_normal((d, d))
        Q0 = A @ A.T + 0.5 * np.eye(d)
        H = rng.standard_normal((N, m, d))
        L = rng.standard_normal((N, m, m)) * 0.3 + np.eye(m)
        R = L @ np.swapaxes(L, -1, -2)  # SPD noise per candidate
        G = np.linalg.solve(np.linalg.cholesky(R), H)  # whitened in the test, independently
        best = max(
            itertools.combinations(range(N), 3), key=lambda S: _f(Q0, G, S, objective, interest)
        )
        sol = fs.brute_force(Q0, H, R, 3, objective=objective, interest=interest)
        assert tuple(sorted(sol.indices)) == best
        assert sol.objective == pytest.approx(_f(Q0, G, best, objective, interest), abs=1e-9)
        assert sol.objective_name == objective


@pytest.mark.parametrize(("objective", "interest"), CASES)
def test_greedy_is_the_naive_greedy_and_greedy_le_swap_le_brute_force(objective, interest) -> None:
    for seed in range(6):
        Q0, G = _instance(200 + seed, N=10, m=2 if seed % 2 else 1)
        gr = fs.greedy_whitened(Q0, G, 3, objective=objective, interest=interest)
        assert list(gr.indices) == _naive_greedy(Q0, G, 3, objective, interest)
        sw = fs.swap_whitened(Q0, G, 3, objective=objective, interest=interest)
        bf = fs.brute_force_whitened(Q0, G, 3, objective=objective, interest=interest)
        assert gr.objective <= sw.objective + 1e-12
        assert sw.objective <= bf.objective + 1e-12
        for sol in (gr, sw, bf):
            assert sol.objective == pytest.approx(_f(Q0, G, sol.indices, objective, interest))
        # a swap result admits no improving 1-swap (local optimum), checked by enumeration
        S = set(sw.indices)
        for i, j in itertools.product(sorted(S), sorted(set(range(10)) - S)):
            assert _f(Q0, G, (S - {i}) | {j}, objective, interest) <= sw.objective + 1e-9
        v = vns_whitened(Q0, G, 1, objective=objective, interest=interest, rng=0)
        b1 = fs.brute_force_whitened(Q0, G, 1, objective=objective, interest=interest)
        assert v.indices == b1.indices  # VNS enumerates V_1 when K = 1


def test_trace_greedy_can_be_suboptimal_so_the_gap_is_real() -> None:
    # not submodular: brute force beats greedy strictly on some instance of this family
    gaps = []
    for seed in range(40):
        Q0, G = _instance(300 + seed, N=8, m=1, d=4)
        gr = fs.greedy_whitened(Q0, G, 3, objective="trace")
        bf = fs.brute_force_whitened(Q0, G, 3, objective="trace")
        gaps.append(bf.objective - gr.objective)
    assert min(gaps) >= -1e-12 and max(gaps) > 1e-6


def test_logdet_default_matches_a_fresh_logdet_gain_state() -> None:
    Q0, G = _instance(5, N=12)
    state = LogDetGainState(Q0, G, track_gains=True)
    for _ in range(4):
        state.add(int(np.argmax(state.masked_gains())))
    for sol in (
        fs.greedy_whitened(Q0, G, 4),
        fs.greedy_whitened(Q0, G, 4, objective="logdet"),
    ):
        assert sol.indices == tuple(state.order)
        assert sol.objective == logdet_objective(Q0, G, state.order)  # exact, not approx
        assert sol.objective_name == "logdet"
    assert type(make_gain_state(Q0, G)) is LogDetGainState
    # the default env (its batched core, shared with the vector env): rewards and observed
    # gains those of a fresh log-det state, within the portability tolerances
    env = gym.make(FIM_ID, n_candidates=8, budget=4).unwrapped
    obs, info = env.reset(seed=3)
    ref = LogDetGainState(env.problem.Q0, env.problem.G, track_gains=True, track_whitened=True)
    assert env.objective == "logdet"
    for a in (5, 0, 11, 2):
        np.testing.assert_allclose(
            obs["gain"], np.where(ref.selected, 0.0, ref.gains).astype(np.float32),
            rtol=3e-7, atol=1e-6,
        )  # fmt: skip
        obs, r, _, _, info = env.step(a)
        np.testing.assert_allclose(r, ref.add(a), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(info["objective"], ref.objective, rtol=1e-9, atol=1e-12)


def test_bad_objective_or_interest_is_a_clear_error() -> None:
    Q0, G = _instance(0)
    H, R = G, np.eye(2)
    for solver in (fs.greedy, fs.swap, fs.brute_force, fs.lazy_greedy):
        with pytest.raises(ValueError, match="objective"):
            solver(Q0, H, R, 2, objective="mse")
        with pytest.raises(TypeError, match="objective"):
            solver(Q0, H, R, 2, objective=3)
    with pytest.raises(ValueError, match="objective"):
        vns_whitened(Q0, G, 2, objective="a_optimal")
    with pytest.raises(ValueError, match="interest"):
        fs.greedy(Q0, H, R, 2, objective="trace", interest=[0, 9])
    with pytest.raises(ValueError, match="interest"):
        fs.greedy(Q0, H, R, 2, objective="trace", interest=[1, 1])
    with pytest.raises(TypeError, match="interest"):
        fs.greedy(Q0, H, R, 2, objective="trace", interest=[0.5])
    with pytest.raises(ValueError, match="interest"):
        fs.greedy(Q0, H, R, 2, interest=[0])  # log det scores the whole parameter
    with pytest.raises(ValueError, match="objective"):
        gym.make(FIM_ID, objective="mse")
    with pytest.raises(TypeError, match="objective"):
        gym.make(FIM_ID, objective=None)
    with pytest.raises(ValueError, match="objective"):
        gym.make(LM_ID, objective="a_optimal")


def test_lazy_greedy_refuses_non_submodular_objectives() -> None:
    Q0, G = _instance(1)
    for objective in ("trace", "max_eig"):
        with pytest.raises(ValueError, match="submodular"):
            fs.lazy_greedy_whitened(Q0, G, 2, objective=objective)
    env = gym.make(FIM_ID, n_candidates=6, budget=2, objective="trace", invalid_action="raise")
    obs, info = env.reset(seed=0)
    agent = selenv.agents.make("lazy_greedy", FIM_ID)
    agent.reset(env, seed=0)
    with pytest.raises(ValueError, match="submodular"):
        agent.act(obs, info)


def _position_f(problem, S, objective) -> float:
    ix = [problem.param_names.index("x"), problem.param_names.index("y")]
    return _f(np.asarray(problem.Q0), np.asarray(problem.G), S, objective, ix)


@pytest.mark.parametrize("objective", ["trace", "max_eig"])
def test_fim_env_return_is_f_of_the_selected_set_and_agents_optimise_it(objective) -> None:
    env = gym.make(FIM_ID, n_candidates=6, budget=3, objective=objective).unwrapped
    results = {}
    for name in ("greedy", "swap", "brute_force", "random"):
        obs, info = env.reset(seed=11)
        agent = selenv.agents.make(name, FIM_ID)
        agent.reset(env, seed=11)
        ret, done, picks = 0.0, False, []
        while not done:
            if not picks:  # the observed gains are the direct marginal gains of the objective
                direct = [_position_f(env.problem, [k], objective) for k in range(env.n)]
                np.testing.assert_allclose(obs["gain"], direct, rtol=1e-5, atol=1e-6)
            a = agent.act(obs, info)
            picks.append(a)
            obs, r, done, _, info = env.step(a)
            assert env.observation_space.contains(obs)
            ret += r
        f = _position_f(env.problem, picks, objective)
        assert ret == pytest.approx(f, rel=1e-9, abs=1e-9)
        assert info["objective"] == pytest.approx(f, rel=1e-9, abs=1e-9)
        assert env.objective == objective
        results[name] = (f, picks)
    problem = env.problem
    naive = _naive_greedy(
        np.asarray(problem.Q0),
        np.asarray(problem.G),
        3,
        objective,
        [problem.param_names.index("x"), problem.param_names.index("y")],
    )
    assert results["greedy"][1] == naive  # the agent optimises the env's objective
    best = max(_position_f(problem, S, objective) for S in itertools.combinations(range(env.n), 3))
    assert results["brute_force"][0] == pytest.approx(best, rel=1e-9)
    assert results["greedy"][0] <= results["swap"][0] + 1e-12 <= best + 2e-12


def _position_criterion(P: np.ndarray, objective: str) -> float:
    """``tr`` or ``lambda_max`` of the position block, by numpy's own routines."""
    block = P[:3, :3]
    return float(np.trace(block) if objective == "trace" else np.linalg.eigvalsh(block)[-1])


@pytest.mark.parametrize("objective", ["trace", "max_eig"])
def test_landmark_position_cost_is_that_of_the_ekf_posterior(objective: str) -> None:
    """The env's trace / max-eig cost equals the criterion of the information-form posterior,
    and brute force picks the subset that minimises it (checked against every subset)."""
    env = gym.make(LM_ID, n_landmarks=7, k=2, horizon=4, objective=objective).unwrapped
    obs, info = env.reset(seed=2)
    agent = selenv.agents.make("brute_force", LM_ID)
    agent.reset(env, seed=2)
    R = env.problem.R_landmark
    Rinv = np.linalg.inv(R)
    for _ in range(4):
        P_pred = env.ekf.P.copy()
        H, _ = env.ekf.candidates()

        def post_trace(S, P_pred=P_pred, H=H):  # information form, explicit inverses
            info_form = np.linalg.inv(P_pred) + sum(H[j].T @ Rinv @ H[j] for j in S)
            return _position_criterion(np.linalg.inv(info_form), objective)

        costs = {S: post_trace(S) for S in itertools.combinations(range(7), 2)}
        picks = []
        for _ in range(2):
            a = agent.act(obs, info)
            picks.append(a)
            obs, r, done, _, info = env.step(a)
        assert env.objective == objective
        assert info["objective"] == pytest.approx(post_trace(picks), rel=1e-6)
        assert r == -info["objective"]
        assert costs[tuple(sorted(picks))] == pytest.approx(min(costs.values()), rel=1e-9)
    assert done  # the last update is not followed by a prediction: P is the posterior
    assert info["objective"] == pytest.approx(_position_criterion(env.ekf.P, objective), rel=1e-12)


@pytest.mark.parametrize("objective", ["trace", "max_eig"])
def test_landmark_vns_and_greedy_run_on_position_objectives(objective: str) -> None:
    for name in ("vns", "greedy", "swap"):
        env = gym.make(LM_ID, n_landmarks=6, k=1, horizon=3, objective=objective).unwrapped
        obs, info = env.reset(seed=4)
        agent = selenv.agents.make(name, LM_ID)
        agent.reset(env, seed=4)
        for _ in range(3):
            gains = env.state.gains.copy()
            a = agent.act(obs, info)
            assert a == int(np.argmax(gains))  # k = 1: every solver takes the best trace gain
            obs, r, done, _, info = env.step(a)
        assert done


@pytest.mark.parametrize("objective", ["trace", "max_eig"])
def test_partition_and_cooperative_solvers_take_the_objective(objective) -> None:
    Q0, G = _instance(9, N=10)
    one = fs.partition_greedy_whitened(Q0, G, [list(range(10))], [3], objective=objective)
    assert one.indices == fs.greedy_whitened(Q0, G, 3, objective=objective).indices
    groups, budgets = [[0, 1, 2, 3, 4], [5, 6, 7, 8, 9]], [2, 1]
    pg = fs.partition_greedy_whitened(Q0, G, groups, budgets, objective=objective)
    ps = fs.partition_swap_whitened(Q0, G, groups, budgets, objective=objective)
    best = max(
        (_f(Q0, G, a + b, objective), a + b)
        for a in itertools.combinations(groups[0], 2)
        for b in itertools.combinations(groups[1], 1)
    )
    assert pg.objective <= ps.objective + 1e-12 <= best[0] + 2e-12
    assert ps.objective == pytest.approx(_f(Q0, G, ps.indices, objective))
    assert sum(i in groups[0] for i in ps.indices) == 2  # the partition is respected
    eye = np.eye(2)
    coop = fs.cooperative_greedy(Q0, [(G[:5], eye), (G[5:], eye)], [2, 1], objective=objective)
    union = [*coop.selections[0].indices, *(5 + i for i in coop.selections[1].indices)]
    assert coop.objective == pytest.approx(_f(Q0, G, union, objective), abs=1e-10)
