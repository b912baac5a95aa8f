"""The native vector env of ``selenv/ReceiverClustering-v1`` against ``B`` single envs.

Every equivalence test drives ``gymnasium.make_vec`` and ``B`` ``gymnasium.make`` envs in
lock-step (:func:`selenv.envs.vector_check.check_vector_equivalence`): observations, rewards,
flags, masks and infos must agree (decisions exactly, values within rtol 1e-9) across at least
two autoresets per sub-env.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401  (registers the envs and agents)
from selenv.agents import make as make_agent
from selenv.envs.actions import INFEASIBLE
from selenv.envs.vector_check import check_vector_equivalence, random_masked_action
from selenv.families.clustering.batched import clustering_costs
from selenv.families.clustering.env import ReceiverClusteringEnv, edit_action_count
from selenv.families.clustering.scenario import clustering_cost, make_clustering_problem
from selenv.families.clustering.vector import ReceiverClusteringVectorEnv

ID = "selenv/ReceiverClustering-v1"


def masked_pick(b: int, env: gym.Env[Any, Any], mask: np.ndarray, rng: np.random.Generator) -> Any:
    """A random allowed action: an edit, or a label per receiver from its row of the mask."""
    base = env.unwrapped
    m = np.asarray(mask, dtype=bool)
    if base.action_mode == "assignment":  # type: ignore[attr-defined]
        m = m.reshape(base.n, base.n)  # type: ignore[attr-defined]
    return random_masked_action(b, env, m, rng)


def keep_or_pick(b: int, env: gym.Env[Any, Any], mask: np.ndarray, rng: np.random.Generator) -> Any:
    """Half the time keep the clustering (a no-op), else a random allowed action."""
    base = env.unwrapped
    if rng.random() < 0.5:
        return 0 if base.action_mode == "edit" else base.bank.labels.copy()  # type: ignore[attr-defined]
    return masked_pick(b, env, mask, rng)


def check(num_envs: int, seeds: list[int], steps: int, **kwargs: Any) -> dict[str, int]:
    counts = check_vector_equivalence(
        ID, num_envs=num_envs, seeds=seeds, steps=steps, picker=keep_or_pick, **kwargs
    )
    assert counts["autoresets"] >= 2 * num_envs
    return counts


# -- registration ---------------------------------------------------------------------------------
def test_make_vec_returns_the_native_env() -> None:
    env = gym.make_vec(ID, num_envs=8)
    assert isinstance(env, ReceiverClusteringVectorEnv)
    assert env.num_envs == 8
    assert env.single_observation_space == gym.make(ID).observation_space
    env.close()


def test_make_vec_v0_warns_and_uses_the_release_presets() -> None:
    with pytest.warns(DeprecationWarning):
        env = gym.make_vec("selenv/ReceiverClustering-v0", num_envs=3)
    assert isinstance(env, ReceiverClusteringVectorEnv)
    assert env.settings.preset == "paper" and "action_mask" not in env.single_observation_space
    env.close()


# -- equivalence ----------------------------------------------------------------------------------
@pytest.mark.parametrize("seeds", [[0, 1, 2], [11, 11, 5], [123, 7, 42]])
@pytest.mark.parametrize("action_mode", ["assignment", "edit"])
def test_random_masked_actions_match_single_envs(seeds: list[int], action_mode: str) -> None:
    check(len(seeds), seeds, 16, horizon=5, action_mode=action_mode)


def test_paper_preset_and_other_keywords_match_single_envs() -> None:
    kwargs = dict(
        preset="paper",
        n_agents=12,
        n_max_states=18,
        tau=4,
        weights=(0.5, 2.0, 1.0),
        prior_std=(2.0, 0.5, 1.5),
        noise_correlation=0.5,
        horizon=6,
        initial="singletons",
    )
    check(3, [5, 6, 7], 16, **kwargs)
    check(3, [8, 9, 10], 16, action_mode="edit", **kwargs)


def test_multipath_overrides_and_unconstrained_clusters_match() -> None:
    check(2, [3, 4], 14, horizon=5, n_agents=9, n_max_states=None, p_enter=0.2, p_leave=0.3)


@pytest.mark.parametrize("action_mode", ["assignment", "edit"])
def test_greedy_agent_episodes_match_single_envs(action_mode: str) -> None:
    agents: dict[int, Any] = {}

    def greedy(b: int, env: gym.Env[Any, Any], mask: np.ndarray, rng: np.random.Generator) -> Any:
        agent = agents.get(b)
        if agent is None or agent.base is not env.unwrapped:
            agent = agents[b] = make_agent("greedy", ID, every=2)
            agent.reset(env, seed=b)
        return agent.act(None, {})

    # cost_evaluations counts the agent's searches on the single env's bank only
    keys = ["objective", "J_G", "J_C", "J_L", "n_clusters", "changed", "k", "action_mask"]
    counts = check_vector_equivalence(
        ID,
        num_envs=3,
        seeds=[1, 2, 3],
        steps=14,
        picker=greedy,
        info_keys=keys,
        horizon=5,
        tau=3,
        action_mode=action_mode,
    )
    assert counts["autoresets"] >= 6


@pytest.mark.parametrize("action_mode", ["assignment", "edit"])
def test_invalid_actions_noop_and_terminate_match_single_envs(action_mode: str) -> None:
    def sometimes_invalid(
        b: int, env: gym.Env[Any, Any], mask: np.ndarray, rng: np.random.Generator
    ) -> Any:
        base = env.unwrapped
        if rng.random() < 0.3:
            if action_mode == "edit":
                return int(rng.choice(np.flatnonzero(~np.asarray(mask, dtype=bool))))
            return np.zeros(base.n, dtype=np.int64)  # type: ignore[attr-defined]  # all in one
        return keep_or_pick(b, env, mask, rng)

    for mode, penalty in (("noop", -1.5), ("terminate", -3.0)):
        counts = check_vector_equivalence(
            ID,
            num_envs=3,
            seeds=[4, 5, 6],
            steps=16,
            picker=sometimes_invalid,
            horizon=5,
            action_mode=action_mode,
            invalid_action=mode,
            invalid_action_penalty=penalty,
        )
        assert counts["autoresets"] >= 6


def test_invalid_code_is_reported_for_every_sub_env() -> None:
    env = ReceiverClusteringVectorEnv(3)
    obs, _ = env.reset(seed=0)
    actions = obs["assignment"].copy()
    actions[1] = 0  # one cluster of 30 receivers: infeasible
    _, rewards, _, _, info = env.step(actions)
    assert info["invalid_action"].tolist() == [False, True, False]
    assert info["_invalid_code"].all()  # the same keys at every step, for every sub-env
    assert info["invalid_code"].tolist() == [0, INFEASIBLE, 0]


def test_same_step_mode_reports_the_terminating_reason_in_final_info() -> None:
    env = gym.make_vec(ID, num_envs=3, autoreset_mode="SameStep", invalid_action="terminate")
    obs, _ = env.reset(seed=0)
    actions = obs["assignment"].copy()
    actions[0] = 0  # infeasible: sub-env 0 ends and is reset within the step
    obs, rewards, terminated, _, info = env.step(actions)
    assert terminated.tolist() == [True, False, False]
    assert info["_final_info"].tolist() == [True, False, False]
    final = info["final_info"]
    assert final["_invalid_code"].tolist() == [True, False, False]
    assert final["invalid_code"][0] == INFEASIBLE
    assert info["invalid_code"].tolist() == [0, 0, 0]  # the new episode's reset info: valid
    assert obs["time"][0, 0] == 0.0  # the new episode's first observation


@pytest.mark.parametrize("action_mode", ["assignment", "edit"])
def test_raise_names_the_sub_env_and_changes_nothing(action_mode: str) -> None:
    env = ReceiverClusteringVectorEnv(3, invalid_action="raise", action_mode=action_mode)
    obs, _ = env.reset(seed=3)
    masks = env.action_masks()
    if action_mode == "edit":
        actions = np.zeros(3, dtype=np.int64)
        actions[2] = int(np.flatnonzero(~masks[2])[0])
    else:
        actions = obs["assignment"].copy()
        actions[2] = 0
    ks = [bank.k for bank in env.banks]  # type: ignore[union-attr]
    with pytest.raises(ValueError, match="sub-env 2"):
        env.step(actions)
    assert [bank.k for bank in env.banks] == ks  # type: ignore[union-attr]
    np.testing.assert_array_equal(env._observe()["assignment"], obs["assignment"])


# -- resets and seeding ---------------------------------------------------------------------------
def _singles(seeds: list[int], **kwargs: Any) -> list[dict[str, np.ndarray]]:
    return [gym.make(ID, **kwargs).reset(seed=s)[0] for s in seeds]


def _assert_obs_row(vobs: dict[str, np.ndarray], b: int, obs: dict[str, np.ndarray]) -> None:
    for key, value in obs.items():
        np.testing.assert_allclose(vobs[key][b], value, rtol=3e-7, err_msg=key)


def test_reset_mask_resets_only_the_masked_sub_envs() -> None:
    env = ReceiverClusteringVectorEnv(3, horizon=20)
    obs, _ = env.reset(seed=[10, 20, 30])
    for _ in range(3):
        obs, *_ = env.step(obs["assignment"])
    before = {key: value.copy() for key, value in obs.items()}
    mask = np.array([False, True, False])
    obs, info = env.reset(seed=[0, 77, 0], options={"reset_mask": mask})
    _assert_obs_row(obs, 1, _singles([77], horizon=20)[0])
    assert info["_objective"].tolist() == [False, True, False]
    for b in (0, 2):
        for key in before:
            np.testing.assert_array_equal(obs[key][b], before[key][b])
    assert [bank.k for bank in env.banks] == [3, 0, 3]  # type: ignore[union-attr]


def test_same_seed_twice_gives_identical_arrays() -> None:
    runs = []
    for _ in range(2):
        env = ReceiverClusteringVectorEnv(4, horizon=4, action_mode="edit")
        obs, _ = env.reset(seed=99)
        rng = np.random.default_rng(5)
        trace = [obs]
        for _ in range(10):
            masks = env.action_masks()
            actions = np.array([rng.choice(np.flatnonzero(m)) for m in masks])
            obs, rewards, terminated, _, _ = env.step(actions)
            trace.append({**obs, "reward": rewards, "terminated": terminated})
        runs.append(trace)
    for a, b in zip(*runs, strict=True):
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_seed_none_then_continued() -> None:
    env = ReceiverClusteringVectorEnv(2, horizon=3)
    obs, _ = env.reset()  # fresh random generators
    for _ in range(5):
        obs, *_ = env.step(obs["assignment"])
    assert env.observation_space.contains(obs)
    # after a seeded reset, an unseeded one continues each sub-env's generator
    env.reset(seed=[3, 4])
    obs, _ = env.reset()
    singles = []
    for s in (3, 4):
        single = gym.make(ID, horizon=3)
        single.reset(seed=s)
        singles.append(single.reset()[0])
    for b, o in enumerate(singles):
        _assert_obs_row(obs, b, o)


def test_reset_options_clustering_for_all_or_per_sub_env() -> None:
    env = ReceiverClusteringVectorEnv(2, n_agents=6, n_max_states=10)
    labels = np.array([5, 5, 3, 3, 1, 1])
    obs, _ = env.reset(seed=0, options={"clustering": labels})
    np.testing.assert_array_equal(obs["assignment"], [[0, 0, 1, 1, 2, 2]] * 2)
    rows = np.array([[0, 1, 2, 3, 4, 5], [0, 0, 0, 0, 0, 0]])
    with pytest.raises(ValueError, match=r"options\['clustering'\]\[1\]"):
        env.reset(seed=0, options={"clustering": rows})
    rows[1] = [1, 1, 0, 0, 2, 2]
    obs, _ = env.reset(seed=0, options={"clustering": rows})
    np.testing.assert_array_equal(obs["assignment"], [[0, 1, 2, 3, 4, 5], [0, 0, 1, 1, 2, 2]])
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(options={"bogus": 1})


# -- argument errors ------------------------------------------------------------------------------
@pytest.mark.parametrize("num_envs", [0, -1, True, 2.0, "4"])
def test_bad_num_envs_is_named(num_envs: Any) -> None:
    with pytest.raises((TypeError, ValueError), match="num_envs"):
        ReceiverClusteringVectorEnv(num_envs)


@pytest.mark.parametrize(
    "kwargs", [{"n_agents": 0}, {"preset": "x"}, {"action_mode": "y"}, {"tau": 0.5}]
)
def test_bad_keywords_fail_as_in_the_single_env(kwargs: dict[str, Any]) -> None:
    with pytest.raises((TypeError, ValueError)) as single:
        ReceiverClusteringEnv(**kwargs)
    with pytest.raises(type(single.value)) as vector:
        ReceiverClusteringVectorEnv(2, **kwargs)
    assert str(vector.value) == str(single.value)


def test_wrong_action_shapes_and_types_are_refused() -> None:
    env = ReceiverClusteringVectorEnv(2, n_agents=5)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="actions"):
        env.step(np.zeros((3, 5), dtype=np.int64))
    with pytest.raises(ValueError, match="actions"):
        env.step(np.zeros((2, 4), dtype=np.int64))
    with pytest.raises(TypeError):
        env.step(np.zeros((2, 5)))
    with pytest.raises(ValueError, match=r"actions\[1\]"):
        env.step(np.array([[0, 1, 2, 3, 4], [0, 1, 2, 3, 5]]))
    edit = ReceiverClusteringVectorEnv(2, n_agents=5, action_mode="edit")
    edit.reset(seed=0)
    with pytest.raises(ValueError, match="actions"):
        edit.step(np.zeros((2, 2), dtype=np.int64))
    with pytest.raises(ValueError, match=r"actions\[0\]"):
        edit.step(np.array([edit_action_count(5), 0]))
    with pytest.raises(TypeError):
        edit.step(np.array([0.0, 0.0]))


def test_render_env_draws_one_sub_env() -> None:
    env = ReceiverClusteringVectorEnv(2, n_agents=6, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render_env(1)
    assert frame is not None and frame.ndim == 3 and frame.shape[2] == 3
    env.close()
    with pytest.raises(ValueError, match="render_mode"):
        ReceiverClusteringVectorEnv(2, render_mode="human")


# -- the batched core -----------------------------------------------------------------------------
def test_batched_costs_equal_the_per_clustering_cost() -> None:
    rng = np.random.default_rng(0)
    posteriors, owner = [], []
    for b in range(4):
        for _ in range(1 + b):
            s = int(rng.integers(1, 4))
            A = rng.standard_normal((2 * s + 1, 2 * s + 1))
            posteriors.append(A @ A.T + np.eye(2 * s + 1))
            owner.append(b)
    pos = [P.diagonal()[0:-1:2] for P in posteriors]
    trace2 = np.array([2 * np.trace(P) for P in posteriors])
    states = np.array([2.0 * P.shape[0] for P in posteriors])  # N(C) = 4s + 2
    mean = np.array([p.mean() for p in pos])
    worst = np.array([p.max() for p in pos])
    weights = (0.3, 1.0, 2.0)
    costs = clustering_costs(trace2, states, mean, worst, np.array(owner), 4, weights)
    for b in range(4):
        mine = [P for P, o in zip(posteriors, owner, strict=True) if o == b]
        ref = clustering_cost(mine, weights)
        np.testing.assert_array_equal(costs[b], [ref.J, ref.J_G, ref.J_C, ref.J_L])


def test_histories_handed_out_stay_valid_as_banks_and_forks_step() -> None:
    banks = []
    for _ in range(2):  # a bank that is forked, and its untouched twin
        env = gym.make(ID, tau=3, horizon=40)
        env.reset(seed=2)
        banks.append(env.unwrapped.bank)  # type: ignore[attr-defined]
    bank, twin = banks
    for _ in range(6):  # fill the windows: then histories are appended in place
        bank.step()
        twin.step()
    key = bank.clusters[0]
    seen = bank.history(key)
    frozen = seen.copy()
    other = make_clustering_problem(bank.problem.config, np.random.default_rng(9), 40)
    fork = bank.fork(other)  # other noise: the forks' posteriors differ from the banks'
    fork2 = twin.fork(other)
    for _ in range(12):  # several buffer refills; the pairs step in opposite orders
        fork.step()
        bank.step()
        twin.step()
        fork2.step()
        np.testing.assert_array_equal(bank.history(key), twin.history(key))
        np.testing.assert_array_equal(fork.history(key), fork2.history(key))
        np.testing.assert_array_equal(seen, frozen)
    assert bank.history(key).shape[0] == 4
    assert not np.array_equal(fork.history(key), bank.history(key))
