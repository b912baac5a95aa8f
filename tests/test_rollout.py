"""The ``rollout`` reference agents: options, forecasts, myopic limit, no peeking, quality."""

from __future__ import annotations

import copy
import dataclasses
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401
from selenv.agents import agents_for, make
from selenv.families.cooperative.forecast import CLForecast
from selenv.families.landmarks.forecast import LandmarkForecast

CL = "selenv/CLScheduling-v1"
LM = "selenv/LandmarkSelection-v1"
# small instances: 3 agents (6 pairs), 12 landmarks; explicit keywords, whatever the presets
CL_KW: dict[str, Any] = {"n_agents": 3, "budget": 2, "horizon": 25, "objective": "logdet"}
LM_KW: dict[str, Any] = {"n_landmarks": 12, "k": 2, "horizon": 25}


def _play(env: gym.Env[Any, Any], agent: Any, steps: int, seed: int) -> tuple[Any, Any]:
    """Reset with ``seed`` and play ``steps`` steps of ``agent``; return ``(obs, info)``."""
    obs, info = env.reset(seed=seed)
    agent.reset(env, seed=seed)
    for _ in range(steps):
        obs, _, terminated, _, info = env.step(agent.act(obs, info))
        assert not terminated
    return obs, info


def _episode(env_id: str, name: str, env_kw: dict[str, Any], seed: int, **kw: Any) -> float:
    env = gym.make(env_id, **env_kw)
    agent = make(name, env_id, **kw)
    obs, info = env.reset(seed=seed)
    agent.reset(env, seed=seed)
    total, done = 0.0, False
    while not done:
        obs, r, terminated, truncated, info = env.step(agent.act(obs, info))
        total += float(r)
        done = terminated or truncated
    return total


def _scramble(a: np.ndarray, start: int, rng: np.random.Generator) -> np.ndarray:
    """A copy of ``a`` whose entries from index ``start`` on are replaced by other values."""
    out = np.array(a, copy=True)
    out[start:] = out[start:] + rng.normal(size=out[start:].shape) * (1.0 + np.abs(out[start:]))
    return out


# -- registry and options --------------------------------------------------------------------
def test_registered_for_both_envs() -> None:
    assert "rollout" in agents_for(CL)
    assert "rollout" in agents_for(LM)
    assert "fast_rollout" in agents_for(CL)
    assert "fast_rollout" in agents_for(LM)


@pytest.mark.parametrize("env_id", [CL, LM])
@pytest.mark.parametrize(
    ("kwargs", "option"),
    [
        ({"top_k": 0}, "top_k"),
        ({"top_k": 1.5}, "top_k"),
        ({"top_k": True}, "top_k"),
        ({"horizon": -1}, "horizon"),
        ({"horizon": "5"}, "horizon"),
        ({"base": "nope"}, "base"),
    ],
)
def test_bad_options_raise_naming_the_option(
    env_id: str, kwargs: dict[str, Any], option: str
) -> None:
    with pytest.raises(ValueError, match=option):
        make("rollout", env_id, **kwargs)
    if env_id == CL:  # the batched version takes the same options
        with pytest.raises(ValueError, match=option):
            make("fast_rollout", env_id, **kwargs)


def test_refuses_the_wrong_env_and_a_brute_force_base_over_too_many_subsets() -> None:
    for name in ("rollout", "fast_rollout"):
        with pytest.raises(ValueError, match="CLScheduling"):
            make(name, CL).reset(gym.make(LM, **LM_KW), seed=0)
    env = gym.make(LM, **LM_KW)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="base='greedy'"):
        make("rollout", LM, max_subsets=10).reset(env, seed=0)


# -- forecasts agree with the simulators step by step ------------------------------------------
@pytest.mark.parametrize("objective", ["logdet", "trace"])
def test_cl_forecast_matches_the_simulator(objective: str) -> None:
    kw = {**CL_KW, "objective": objective, "beacons": ((-8.0, -8.0, 2.0),), "relative_every": 2}
    env = gym.make(CL, **kw)
    _play(env, make("greedy", CL), 9, seed=3)
    base = env.unwrapped
    sim = base.sim
    f = CLForecast.from_env(base)
    assert f.objective_value() == pytest.approx(base.objective_value(), rel=1e-12)
    for p in np.flatnonzero(base.action_masks()[:-1]):
        assert f.gain(int(p)) == pytest.approx(base.preview_gain(int(p)), rel=1e-9, abs=1e-12)
    for _ in range(12):  # predict (with the true next input), ZUPT, beacon, schedule
        ref = copy.deepcopy(sim)
        f = CLForecast.from_env(base)
        f.u_hold = np.array(sim.problem.inputs[sim.k])
        ref.predict()
        f.predict()
        np.testing.assert_allclose(f.x, ref.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(f.P, ref.P, rtol=1e-12, atol=1e-15)
        assert f.available() == ref.available()
        ref.zupt_updates()
        f.zupt_updates()
        np.testing.assert_allclose(f.P, ref.P, rtol=1e-10, atol=1e-15)
        f.x = ref.x.copy()  # beacon Jacobians at the same estimate
        ref.beacon_updates()
        f.beacon_updates()
        np.testing.assert_allclose(f.P, ref.P, rtol=1e-10, atol=1e-15)
        sim.step([])


def test_landmark_forecast_matches_the_filter() -> None:
    env = gym.make(LM, **LM_KW)
    obs, info = _play(env, make("brute_force", LM), 6, seed=2)
    base = env.unwrapped
    ekf = base.ekf
    f = LandmarkForecast.from_env(base)
    sel = [0, 5]
    f.update(sel, f.jacobians())
    obs, _, _, _, info = env.step(0)
    obs, _, _, _, info = env.step(5)
    # the env has updated (and predicted the next step): compare through a fresh copy
    assert info["objective"] == pytest.approx(f.cost(), abs=1e-9)
    f = LandmarkForecast.from_env(base)
    f.u_hold = np.array(base.problem.imu_measured[ekf.k])  # the true next IMU sample
    ekf.update([3, 7])
    f.P, f.x = ekf.P.copy(), ekf.x.copy()
    ekf.predict()
    f.predict()
    np.testing.assert_allclose(f.x, ekf.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(f.P, ekf.P, rtol=1e-12, atol=1e-15)


# -- horizon 0 is the myopic choice ------------------------------------------------------------
def test_cl_horizon_zero_is_greedy() -> None:
    env = gym.make(CL, **CL_KW)
    greedy, roll = make("greedy", CL), make("rollout", CL, horizon=0, top_k=2)
    obs, info = env.reset(seed=5)
    greedy.reset(env, seed=5)
    roll.reset(env, seed=5)
    done, n = False, 0
    while not done:
        a = greedy.act(obs, info)
        assert roll.act(obs, info) == a
        obs, _, done, _, info = env.step(a)
        n += 1
    assert n >= CL_KW["horizon"]


@pytest.mark.parametrize("objective", ["logdet", "trace", "max_eig"])
@pytest.mark.parametrize("base", ["brute_force", "greedy"])
def test_landmark_horizon_zero_is_brute_force(base: str, objective: str) -> None:
    """Horizon 0 plays brute force's optimum of the env's objective (trace: position MSE,
    max_eig: the largest position variance)."""
    env = gym.make(LM, **LM_KW, objective=objective)
    bf, roll = make("brute_force", LM), make("rollout", LM, horizon=0, base=base)
    obs, info = env.reset(seed=4)
    bf.reset(env, seed=4)
    roll.reset(env, seed=4)
    done = False
    while not done:
        a = bf.act(obs, info)
        assert roll.act(obs, info) == a
        obs, _, done, _, info = env.step(a)


# -- no peeking, determinism, the env untouched ------------------------------------------------
def _cl_pair(seed: int, steps: int) -> tuple[gym.Env[Any, Any], gym.Env[Any, Any]]:
    """Two CL envs in the same mid-episode state; the second one's future is rewritten."""
    a, b = gym.make(CL, **CL_KW), gym.make(CL, **CL_KW)
    _play(a, make("greedy", CL), steps, seed)
    _play(b, make("greedy", CL), steps, seed)
    base = b.unwrapped
    k, prob, rng = base.sim.k, base.problem, np.random.default_rng(99)
    new = dataclasses.replace(
        prob,
        states=_scramble(prob.states, k, rng),  # the truth from now on
        inputs_true=_scramble(prob.inputs_true, k, rng),
        inputs=_scramble(prob.inputs, k, rng),  # future inputs (k - 1 was used: it is known)
        relative_noise=_scramble(prob.relative_noise, k - 1, rng),  # incl. this step's
        zupt_noise=_scramble(prob.zupt_noise, k - 1, rng),
        beacon_noise=_scramble(prob.beacon_noise, k - 1, rng),
    )
    base.problem = base.sim.problem = new
    return a, b


def _cl_agent(name: str) -> Any:
    """A CL lookahead agent; ``cem`` with fixed nonzero weights (no checkpoint: any team)."""
    if name == "cem":
        from selenv.learned.families.cooperative import CLLearnedScorerAgent

        return CLLearnedScorerAgent(np.linspace(-2e-3, 2e-3, 12), horizon=2)
    return make(name, CL)


@pytest.mark.parametrize("name", ["rollout", "fast_rollout", "cem"])
def test_cl_rollout_does_not_peek_at_the_future(name: str) -> None:
    a, b = _cl_pair(seed=7, steps=11)
    ra, rb = _cl_agent(name), _cl_agent(name)
    ra.reset(a, seed=0)
    rb.reset(b, seed=0)
    choice_a, scores_a = ra.scores()
    choice_b, scores_b = rb.scores()
    assert choice_a == choice_b
    assert scores_a == scores_b  # bit for bit
    # the rewrite has teeth: the envs part ways, and the held (past) input does change scores
    for env in (a, b):
        env.step(env.unwrapped.n_pairs)
    assert not np.allclose(a.unwrapped.sim.x, b.unwrapped.sim.x)
    c, _ = _cl_pair(seed=7, steps=11)
    sim = c.unwrapped.sim
    sim.problem = c.unwrapped.problem = dataclasses.replace(
        sim.problem, inputs=_scramble(sim.problem.inputs, sim.k - 1, np.random.default_rng(1))
    )
    rc = _cl_agent(name)
    rc.reset(c, seed=0)
    assert rc.scores()[1] != scores_a


@pytest.mark.parametrize("name", ["rollout", "fast_rollout", "ppo_search"])
def test_landmark_rollout_does_not_peek_at_the_future(name: str) -> None:
    a, b = gym.make(LM, **LM_KW), gym.make(LM, **LM_KW)
    obs_a, info_a = _play(a, make("brute_force", LM), 14, seed=6)
    obs_b, info_b = _play(b, make("brute_force", LM), 14, seed=6)
    base = b.unwrapped
    k, prob, rng = base.ekf.k, base.problem, np.random.default_rng(98)
    new = dataclasses.replace(
        prob,
        states=_scramble(prob.states, k, rng),
        imu_true=_scramble(prob.imu_true, k, rng),
        imu_measured=_scramble(prob.imu_measured, k, rng),  # k - 1 was used: it is known
        F_true=_scramble(prob.F_true, k, rng),
        Q=_scramble(prob.Q, k, rng),
        measurement_noise=_scramble(prob.measurement_noise, k - 1, rng),  # incl. this step's
        measurements=_scramble(prob.measurements, k - 1, rng),
    )
    base.problem = base.ekf.problem = new
    ra, rb = make(name, LM), make(name, LM)
    ra.reset(a, seed=0)
    rb.reset(b, seed=0)
    if name == "rollout":
        choice_a, scores_a = ra.scores()
        choice_b, scores_b = rb.scores()
    else:  # the shortlist agents read the observation (ppo_search: the policy ranks it)
        choice_a, scores_a = ra.scores(obs_a, info_a)
        choice_b, scores_b = rb.scores(obs_b, info_b)
    assert choice_a == choice_b
    assert scores_a == scores_b
    for env in (a, b):  # the rewrite has teeth: the next update differs
        for j in choice_a:
            env.step(j)
    assert not np.allclose(a.unwrapped.ekf.x, b.unwrapped.ekf.x)


def _cl_snapshot(env: gym.Env[Any, Any]) -> tuple[Any, ...]:
    base = env.unwrapped
    sim = base.sim
    return sim.x.copy(), sim.P.copy(), sim.k, base.action_masks().copy(), base.budget_left


def _lm_snapshot(env: gym.Env[Any, Any]) -> tuple[Any, ...]:
    base = env.unwrapped
    st = base.state
    return (
        base.ekf.x.copy(),
        base.ekf.P.copy(),
        base.ekf.k,
        tuple(base.picks),
        st.selected.copy(),
        st.P.copy(),
        base.budget_left,
    )


def _same(s: tuple[Any, ...], t: tuple[Any, ...]) -> None:
    for u, v in zip(s, t, strict=True):
        if isinstance(u, np.ndarray):
            np.testing.assert_array_equal(u, v)
        else:
            assert u == v


@pytest.mark.parametrize(
    ("name", "env_id", "kw", "warm", "snapshot"),
    [
        ("rollout", CL, CL_KW, "greedy", _cl_snapshot),
        ("fast_rollout", CL, CL_KW, "greedy", _cl_snapshot),
        ("rollout", LM, LM_KW, "brute_force", _lm_snapshot),
        ("fast_rollout", LM, LM_KW, "brute_force", _lm_snapshot),
    ],
)
def test_deterministic_and_leaves_the_env_alone(
    name: str, env_id: str, kw: dict[str, Any], warm: str, snapshot: Any
) -> None:
    env = gym.make(env_id, **kw)
    obs, info = _play(env, make(warm, env_id), 8, seed=9)
    before = snapshot(env)
    first, second = make(name, env_id), make(name, env_id)
    first.reset(env, seed=0)
    second.reset(env, seed=1)
    a1 = first.act(obs, info)
    _same(before, snapshot(env))
    assert second.act(obs, info) == a1
    assert first.scores() == second.scores()
    _same(before, snapshot(env))


def test_landmark_plan_plays_the_chosen_subset_over_k_steps() -> None:
    env = gym.make(LM, **LM_KW)
    obs, info = env.reset(seed=1)
    agent = make("rollout", LM)
    agent.reset(env, seed=1)
    best, scores = agent.scores()
    assert len(best) == env.unwrapped.k and max(scores.values()) == scores[best]
    picks = []
    for _ in range(env.unwrapped.k):
        picks.append(agent.act(obs, info))
        obs, _, _, _, info = env.step(picks[-1])
    assert tuple(sorted(picks)) == best == tuple(info["last_selection"].tolist())


# -- quality (a sanity check on a few seeds, not a claim) ------------------------------------
def test_cl_rollout_is_not_worse_than_greedy_on_short_episodes() -> None:
    kw = {**CL_KW, "horizon": 20}
    diffs = [
        _episode(CL, "rollout", kw, s, top_k=2, horizon=3) - _episode(CL, "greedy", kw, s)
        for s in range(3)
    ]
    assert np.mean(diffs) >= -0.05


def test_landmark_rollout_is_not_worse_than_brute_force_on_short_episodes() -> None:
    kw = {**LM_KW, "horizon": 20}
    diffs = [
        _episode(LM, "rollout", kw, s, top_k=3, horizon=19) - _episode(LM, "brute_force", kw, s)
        for s in range(3)
    ]
    assert np.mean(diffs) >= -0.05


def test_landmark_candidates_without_enumeration_hold_the_greedy_subset() -> None:
    env = gym.make(LM, **LM_KW)
    obs, info = _play(env, make("greedy", LM), 4, seed=3)
    agent = make("rollout", LM, base="greedy", max_subsets=10, top_k=3, horizon=2)  # C(12, 2) = 66
    agent.reset(env, seed=0)
    greedy = make("greedy", LM)
    greedy.reset(env, seed=0)
    own = tuple(sorted(greedy.plan(obs, info)))
    cands = agent.candidates()
    assert own in cands and len(set(cands)) == len(cands) <= 4
    assert all(len(set(c)) == env.unwrapped.k for c in cands)
    best, scores = agent.scores()
    assert scores[best] == max(scores.values())


def test_cl_rollout_with_the_all_base_and_scarce_links_plays_an_episode() -> None:
    kw = {**CL_KW, "horizon": 8, "relative_every": 3, "objective": "trace"}
    assert np.isfinite(_episode(CL, "rollout", kw, 0, base="all", top_k=2, horizon=2))


@pytest.mark.parametrize(
    ("env_id", "options"),
    [
        ("selenv/CLScheduling-v1", {"top_k": 257}),
        ("selenv/CLScheduling-v1", {"horizon": 10_001}),
        ("selenv/LandmarkSelection-v1", {"top_k": 100_000}),
        ("selenv/LandmarkSelection-v1", {"max_subsets": 10**8}),
        ("selenv/ReceiverClustering-v1", {"samples": 1_001}),
        ("selenv/ReceiverClustering-v1", {"horizon": 10**8}),
    ],
)
def test_rollout_work_ceilings_refuse_before_any_work(env_id: str, options: dict) -> None:
    """Sizes that multiply a decision's work are bounded; ``allow_large=True`` lifts the bound."""
    from selenv.agents import make as make_agent
    from selenv.agents.rollout import ROLLOUT_CEILINGS

    ((name, value),) = options.items()
    with pytest.raises(ValueError, match=rf"{name}={value} is above its ceiling .*allow_large"):
        make_agent("rollout", env_id, **options)
    assert value > ROLLOUT_CEILINGS[name]
    agent = make_agent("rollout", env_id, allow_large=True, **options)
    assert getattr(agent, name) == value


# -- fast_rollout: the landmark rollout on a shortlist, candidates batched ---------------------
def _bound(name: str, env: gym.Env[Any, Any], **kw: Any) -> Any:
    agent = make(name, LM, **kw)
    agent.reset(env, seed=0)
    return agent


@pytest.mark.parametrize(("seed", "warm"), [(3, 4), (5, 10), (11, 16), (2, 40)])
@pytest.mark.parametrize("horizon", [0, 1, 6])
def test_fast_rollout_with_every_landmark_gives_the_rollout_scores(
    seed: int, warm: int, horizon: int
) -> None:
    """A second formulation: Joseph-form updates and brute force over all subsets per step."""
    kw = dict(LM_KW, horizon=50)
    env = gym.make(LM, **kw)
    _play(env, make("brute_force", LM), warm, seed=seed)
    fast = _bound("fast_rollout", env, top_k=4, horizon=horizon, shortlist=kw["n_landmarks"])
    ref = _bound("rollout", env, top_k=4, horizon=horizon)
    choice, scores = fast.scores()
    ref_choice, ref_scores = ref.scores()
    assert choice == ref_choice
    assert list(scores) == list(ref_scores)  # the same candidates, best one-step gain first
    ours, theirs = np.array(list(scores.values())), np.array(list(ref_scores.values()))
    if horizon == 0:  # gain log det(I + W P W^T) vs -log det P+: the same up to log det P
        np.testing.assert_allclose(np.diff(ours), np.diff(theirs), rtol=1e-9, atol=1e-12)
        return
    np.testing.assert_allclose(ours, theirs, rtol=1e-9)


def test_fast_rollout_stays_on_its_shortlist() -> None:
    env = gym.make(LM, **LM_KW)
    _play(env, make("brute_force", LM), 6, seed=8)
    gains = env.unwrapped.state.masked_gains()
    shortlist = set(np.argsort(-gains, kind="stable")[:4].tolist())
    choice, scores = _bound("fast_rollout", env, top_k=6, horizon=3, shortlist=4).scores()
    assert len(scores) == 6  # C(4, 2) subsets of the shortlist
    assert all(set(s) <= shortlist for s in scores)
    assert choice in scores
    # horizon 0: the best one-step subset within the shortlist
    best, _ = _bound("fast_rollout", env, horizon=0, shortlist=4).scores()
    full = _bound("fast_rollout", env, horizon=0, shortlist=LM_KW["n_landmarks"])
    assert best == next(s for s in full.scores()[1] if set(s) <= shortlist)


def test_fast_rollout_plays_whole_episodes_including_the_last_steps() -> None:
    env = gym.make(LM, **dict(LM_KW, horizon=12))
    obs, info = _play(env, make("fast_rollout", LM, horizon=4), 0, seed=4)
    agent = make("fast_rollout", LM, horizon=4)
    agent.reset(env, seed=4)
    done, steps = False, 0
    while not done:
        obs, _, terminated, truncated, info = env.step(agent.act(obs, info))
        done, steps = terminated or truncated, steps + 1
    assert steps == 12 * LM_KW["k"]


@pytest.mark.parametrize(
    "options",
    [{"top_k": 0}, {"horizon": -1}, {"shortlist": 0}, {"shortlist": 500}, {"top_k": 1.5}],
)
def test_fast_rollout_bad_options_raise(options: dict[str, Any]) -> None:
    with pytest.raises((TypeError, ValueError), match=next(iter(options))):
        make("fast_rollout", LM, **options)


def test_fast_rollout_refuses_another_objective_and_another_env() -> None:
    agent = make("fast_rollout", LM)
    with pytest.raises(ValueError, match="objective"):
        agent.reset(gym.make(LM, **LM_KW, objective="det"), seed=0)
    with pytest.raises(ValueError, match="LandmarkSelection"):
        agent.reset(gym.make("CartPole-v1"), seed=0)
