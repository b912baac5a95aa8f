"""The objective registry: unknown names refused everywhere, built-ins and user objectives checked.

Independent truth: objectives recomputed from explicit inverses of the summed FIM
(``np.linalg.inv``), subsets enumerated with ``itertools``, and a naive greedy written here.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv
from selenv.agents import fim_solvers as fs
from selenv.agents.vns import vns, vns_whitened
from selenv.core.information import LogDetGainState
from selenv.core.objective_registry import (
    BUILTIN_OBJECTIVES,
    Objective,
    check_objective,
    get_objective,
    objective_names,
    register_objective,
    unregister_objective,
)
from selenv.core.objectives import (
    CriterionGainState,
    covariance_criterion,
    criterion_gains,
    make_gain_state,
    objective_value,
    subset_criteria,
    swap_criteria,
)
from selenv.families.cooperative.env import agent_objective
from selenv.families.landmarks.env import landmark_cost, landmark_interest

assert selenv  # registers the env ids

USER = "weighted_trace"
WEIGHTS = np.array([3.0, 1.0, 0.5, 2.0, 1.5])


def _weighted_trace(M: np.ndarray) -> np.ndarray:
    """``tr(W M)`` with ``W = diag(WEIGHTS[:p])``: a user cost without a closed-form downdate."""
    p = M.shape[-1]
    return np.einsum("...ii,i->...", M, WEIGHTS[:p])


@pytest.fixture
def user_objective() -> Iterator[Objective]:
    obj = register_objective(Objective(name=USER, description="weighted MSE", cost=_weighted_trace))
    yield obj
    unregister_objective(USER)


def _instance(seed: int, N: int = 7, m: int = 2, d: int = 5) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((d, d))
    return A @ A.T + 0.3 * np.eye(d), rng.standard_normal((N, m, d))


def _cost(name: str, M: np.ndarray) -> float:
    """Independent cost of one block (no registry code)."""
    if name == "logdet":
        return float(np.linalg.slogdet(M)[1])
    if name == "det":
        return float(np.linalg.det(M))
    if name == "trace":
        return float(np.trace(M))
    if name == "max_eig":
        return float(np.max(np.linalg.eigvalsh(M)))
    assert name == USER
    return float(np.sum(np.diag(M) * WEIGHTS[: M.shape[0]]))


def _f(Q0: np.ndarray, G: np.ndarray, S: list[int], name: str, interest=None) -> float:
    """``c(E Q0^-1 E^T) - c(E A_S^-1 E^T)`` by explicit inverses."""
    d = Q0.shape[0]
    A = Q0 + sum((G[k].T @ G[k] for k in S), np.zeros((d, d)))
    E = np.eye(d) if interest is None else np.eye(d)[list(interest)]
    return _cost(name, E @ np.linalg.inv(Q0) @ E.T) - _cost(name, E @ np.linalg.inv(A) @ E.T)


# -- unknown names are refused by every public function that takes objective= ----------------
Q0_S, G_S = _instance(0)
P_S = np.linalg.inv(Q0_S)
H_S, R_S = G_S, np.broadcast_to(np.eye(2), (7, 2, 2))
SEL, UNS = np.array([0, 1]), np.array([2, 3, 4])


def _calls() -> dict[str, Callable[[Any], object]]:
    pools = [(H_S[:3], R_S[:3]), (H_S[3:], R_S[3:])]
    groups = [[0, 1, 2], [3, 4, 5, 6]]
    return {
        "covariance_criterion": lambda o: covariance_criterion(P_S, o),
        "criterion_gains": lambda o: criterion_gains(P_S, G_S, o),
        "objective_value": lambda o: objective_value(Q0_S, G_S, [0], o),
        "make_gain_state": lambda o: make_gain_state(Q0_S, G_S, o),
        "CriterionGainState": lambda o: CriterionGainState(Q0_S, G_S, o),
        "subset_criteria": lambda o: subset_criteria(
            Q0_S, np.einsum("kmi,kmj->kij", G_S, G_S), np.array([[0, 1]]), o
        ),
        "swap_criteria": lambda o: swap_criteria(Q0_S, G_S, SEL, UNS, o),
        "greedy": lambda o: fs.greedy(Q0_S, H_S, R_S, 2, objective=o),
        "greedy_whitened": lambda o: fs.greedy_whitened(Q0_S, G_S, 2, objective=o),
        "lazy_greedy": lambda o: fs.lazy_greedy(Q0_S, H_S, R_S, 2, objective=o),
        "lazy_greedy_whitened": lambda o: fs.lazy_greedy_whitened(Q0_S, G_S, 2, objective=o),
        "brute_force": lambda o: fs.brute_force(Q0_S, H_S, R_S, 2, objective=o),
        "brute_force_whitened": lambda o: fs.brute_force_whitened(Q0_S, G_S, 2, objective=o),
        "swap": lambda o: fs.swap(Q0_S, H_S, R_S, 2, objective=o),
        "swap_whitened": lambda o: fs.swap_whitened(Q0_S, G_S, 2, objective=o),
        "vns": lambda o: vns(Q0_S, H_S, R_S, 2, objective=o),
        "vns_whitened": lambda o: vns_whitened(Q0_S, G_S, 2, objective=o),
        "cooperative_greedy": lambda o: fs.cooperative_greedy(Q0_S, pools, [1, 1], objective=o),
        "partition_greedy_whitened": lambda o: fs.partition_greedy_whitened(
            Q0_S, G_S, groups, [1, 1], objective=o
        ),
        "partition_swap_whitened": lambda o: fs.partition_swap_whitened(
            Q0_S, G_S, groups, [1, 1], objective=o
        ),
        "landmark_cost": lambda o: landmark_cost(np.eye(9), o),
        "landmark_interest": lambda o: landmark_interest(o),
        "agent_objective": lambda o: agent_objective(np.eye(5), o),
        "get_objective": lambda o: get_objective(o),
        "check_objective": lambda o: check_objective(o),
        "FIMSelection-v1": lambda o: gym.make("selenv/FIMSelection-v1", objective=o),
        "LandmarkSelection-v1": lambda o: gym.make("selenv/LandmarkSelection-v1", objective=o),
        "CLScheduling-v1": lambda o: gym.make("selenv/CLScheduling-v1", objective=o),
    }


CALLS = _calls()


@pytest.mark.parametrize("bad", ["foo", "logdet ", "LOGDET", ""])
@pytest.mark.parametrize("call", list(CALLS))
def test_unknown_objective_name_is_a_value_error_listing_the_known_ones(call, bad) -> None:
    with pytest.raises(ValueError, match="objective must be one of") as exc:
        CALLS[call](bad)
    msg = str(exc.value)
    assert all(name in msg for name in ("logdet", "trace", "max_eig", "det")), msg
    assert repr(bad) in msg


@pytest.mark.parametrize("call", list(CALLS))
def test_non_string_objective_is_a_type_error(call) -> None:
    # CLScheduling-v1 documents objective=None as "the preset's value"
    bads = (3, 2.0, get_objective("trace"))
    for bad in bads if call == "CLScheduling-v1" else (None, *bads):
        with pytest.raises(TypeError, match="objective"):
            CALLS[call](bad)


def test_registry_lists_the_builtins_and_refuses_to_replace_or_remove_them() -> None:
    assert objective_names()[:4] == ("logdet", "det", "trace", "max_eig")
    assert [o.name for o in BUILTIN_OBJECTIVES] == list(objective_names()[:4])
    assert get_objective("logdet").submodular and not get_objective("trace").submodular
    assert get_objective("det").solver_name == "logdet"
    assert get_objective("max_eig").solver_name == "max_eig"
    clone = Objective(name="trace", description="x", cost=np.trace)
    with pytest.raises(ValueError, match="built-in"):
        register_objective(clone)
    with pytest.raises(ValueError, match="built-in"):
        register_objective(clone, replace=True)
    with pytest.raises(ValueError, match="built-in"):
        unregister_objective("logdet")
    with pytest.raises(ValueError, match="not registered"):
        unregister_objective("nope")
    with pytest.raises(TypeError, match="Objective"):
        register_objective("trace")  # type: ignore[arg-type]


def test_objective_fields_are_validated() -> None:
    with pytest.raises(ValueError, match="identifier"):
        Objective(name="two words", description="", cost=np.trace)
    with pytest.raises(TypeError, match="callable"):
        Objective(name="x", description="", cost=3)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="submodular"):
        Objective(name="x", description="", cost=np.trace, submodular=1)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="solver_proxy"):
        register_objective(Objective(name="x", description="", cost=np.trace, solver_proxy="no"))
    assert "x" not in objective_names()


def test_duplicate_user_registration_needs_replace(user_objective) -> None:
    with pytest.raises(ValueError, match="already registered"):
        register_objective(user_objective)
    assert register_objective(user_objective, replace=True) is user_objective


# -- the built-ins and a user objective against independent recomputation ---------------------
@pytest.mark.parametrize("name", ["logdet", "det", "trace", "max_eig", USER])
def test_batched_gains_match_explicit_inverses(name, user_objective) -> None:
    """criterion_gains for every objective (before, ``"logdet"`` silently gave max-eig gains)."""
    for seed in range(5):
        Q0, G = _instance(seed)
        P = np.linalg.inv(Q0)
        want = [_f(Q0, G, [k], name) for k in range(G.shape[0])]
        np.testing.assert_allclose(criterion_gains(P, G, name), want, rtol=1e-9, atol=1e-12)
        if name == "logdet":  # and the log-det state's own gains
            np.testing.assert_allclose(LogDetGainState(Q0, G).gains, want, rtol=1e-9)


@pytest.mark.parametrize("name", ["det", "trace", "max_eig", USER])
def test_downdate_closed_forms_equal_the_generic_form(name, user_objective) -> None:
    rng = np.random.default_rng(5)
    A = rng.standard_normal((4, 4))
    M0 = A @ A.T + np.eye(4)
    V = 0.3 * rng.standard_normal((6, 2, 4))
    obj = get_objective(name)
    generic = obj.value(M0) - obj.value(M0 - np.einsum("kip,kiq->kpq", V, V))
    np.testing.assert_allclose(obj.downdate_gain(M0, V), generic, rtol=1e-9, atol=1e-12)


def test_user_objective_drives_every_solver(user_objective) -> None:
    for seed in range(4):
        Q0, G = _instance(seed)
        N = G.shape[0]
        vals = {S: _f(Q0, G, list(S), USER) for S in itertools.combinations(range(N), 2)}
        best = max(vals, key=vals.get)  # type: ignore[arg-type]
        bf = fs.brute_force_whitened(Q0, G, 2, objective=USER)
        assert bf.indices == best and bf.objective_name == USER
        np.testing.assert_allclose(bf.objective, vals[best], rtol=1e-9)
        S: list[int] = []  # the naive greedy
        for _ in range(3):
            gains = [_f(Q0, G, [*S, k], USER) if k not in S else -np.inf for k in range(N)]
            S.append(int(np.argmax(gains)))
        gr = fs.greedy_whitened(Q0, G, 3, objective=USER)
        assert list(gr.indices) == S
        np.testing.assert_allclose(gr.objective, _f(Q0, G, S, USER), rtol=1e-9)
        sw = fs.swap_whitened(Q0, G, 3, objective=USER)
        assert sw.objective >= gr.objective - 1e-12
        # K = 2 of 7 with l_max = 2: V_1 and V_2 enumerated whole cover every subset
        vn = vns_whitened(Q0, G, 2, objective=USER, m_l=(10**6, 10**6), rng=seed)
        assert tuple(vn.indices) == best
        with pytest.raises(ValueError, match="submodular"):
            fs.lazy_greedy_whitened(Q0, G, 2, objective=USER)


def test_user_objective_in_the_envs(user_objective) -> None:
    env = gym.make("selenv/FIMSelection-v1", objective=USER, n_candidates=20, budget=3)
    obs, info = env.reset(seed=3)
    base = env.unwrapped
    assert base.interest is not None  # not unit-invariant: scored on the target's (x, y)
    total = 0.0
    for _ in range(3):
        a = int(np.argmax(np.where(base.action_masks(), obs["gain"], -np.inf)))
        obs, r, _, _, info = env.step(a)
        total += r
    problem = base.problem
    picked = list(base.state.order)
    want = objective_value(problem.Q0, problem.G, picked, USER, base.interest)
    np.testing.assert_allclose([info["objective"], total], [want, want], rtol=1e-9)
    assert base.objective == USER
    lm = gym.make("selenv/LandmarkSelection-v1", objective=USER, n_landmarks=8, horizon=3)
    lm.reset(seed=0)
    _, _, _, _, info = lm.step(0)
    assert lm.unwrapped.interest == (0, 1, 2)
    cl = gym.make("selenv/CLScheduling-v1", objective=USER, horizon=3)
    _, info = cl.reset(seed=0)
    P = cl.unwrapped.sim.P
    want = sum(_cost(USER, P[i][:2, :2]) for i in range(P.shape[0]))
    np.testing.assert_allclose(info["objective"], want, rtol=1e-9)


@pytest.mark.parametrize("name", ["logdet", "det", "trace", "max_eig"])
def test_landmark_and_cl_costs_match_their_definitions(name) -> None:
    rng = np.random.default_rng(1)
    A = rng.standard_normal((9, 9))
    P = A @ A.T / 9 + 0.1 * np.eye(9)
    block = P if name in ("logdet", "det") else P[:3, :3]
    np.testing.assert_allclose(landmark_cost(P, name), _cost(name, block), rtol=1e-9)
    Ps = np.stack([P[:5, :5], P[4:, 4:]])
    block2 = Ps if name in ("logdet", "det") else Ps[:, :2, :2]
    want = [_cost(name, B) for B in block2]
    np.testing.assert_allclose(agent_objective(Ps, name), want, rtol=1e-9)
