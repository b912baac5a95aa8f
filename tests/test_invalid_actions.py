"""The three ``invalid_action`` modes of every env and PettingZoo module (selenv.envs.actions).

A no-op must leave the selection / clustering exactly as a reference that did nothing (checked
against a second env on the same seed), spend the slot or time step, flag the step and add the
penalty; ``raise`` must raise; ``terminate`` must end the episode with the penalty.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401
from selenv.envs.actions import (
    INFEASIBLE,
    INVALID_CODES,
    MASKED,
    InvalidActionRule,
    check_discrete,
    invalid_code,
)
from selenv.multiagent import fim_selection_v0, receiver_clustering_v1

PEN = -0.5


def _make(env_id: str, mode: str = "noop", **kw: Any) -> Any:
    return gym.make(env_id, invalid_action=mode, invalid_action_penalty=PEN, **kw).unwrapped


# -- the rule itself -------------------------------------------------------------------------------
def test_rule_validation_and_behaviour() -> None:
    with pytest.raises(ValueError, match="invalid_action must be one of"):
        InvalidActionRule("skip")
    with pytest.raises(TypeError, match="invalid_action_penalty must be a float"):
        InvalidActionRule("noop", "1")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="finite"):
        InvalidActionRule("noop", float("inf"))
    assert InvalidActionRule("noop").check("action 1", None) is False
    assert InvalidActionRule("noop").check("action 1", "masked") is True
    with pytest.raises(ValueError, match="action 1 is invalid: masked"):
        InvalidActionRule("raise").check("action 1", "masked")
    assert InvalidActionRule.info(None) == {"invalid_action": False, "invalid_code": 0}
    assert InvalidActionRule.info("masked: 3 is taken") == {
        "invalid_action": True,
        "invalid_code": 1,
    }
    assert InvalidActionRule.info("infeasible: too big")["invalid_code"] == 2
    assert INVALID_CODES[MASKED] == "masked" and INVALID_CODES[INFEASIBLE] == "infeasible"
    with pytest.raises(ValueError, match="must start with one of"):
        invalid_code("why")  # every env reason names its kind
    batched = InvalidActionRule.masked_info(np.array([False, True]))
    assert batched["invalid_action"].tolist() == [False, True]
    assert (
        batched["invalid_code"].tolist() == [0, MASKED]
        and batched["invalid_code"].dtype == np.int64
    )
    assert check_discrete(np.array([3]), 5) == 3
    for bad, err in (
        (1.0, TypeError),
        (True, TypeError),
        (np.array([1, 2]), TypeError),
        (5, ValueError),
    ):
        with pytest.raises(err):
            check_discrete(bad, 5)


# -- FIMSelection-v1 -------------------------------------------------------------------------------
def test_fim_noop_spends_the_slot_and_selects_nothing() -> None:
    env = _make("selenv/FIMSelection-v1")
    env.reset(seed=0)
    env.step(3)
    order, objective, left = list(env.state.order), env.state.objective, env.budget_left
    obs, r, term, trunc, info = env.step(3)
    assert r == PEN and not term and not trunc
    assert info["invalid_action"] and info["invalid_code"] == MASKED
    assert env.state.order == order and env.state.objective == objective
    assert env.budget_left == left - 1 and obs["budget_left"][0] == pytest.approx((left - 1) / 10)
    assert not env.step(4)[4]["invalid_action"]


def test_fim_episode_is_bounded_even_if_every_action_is_invalid() -> None:
    env = _make("selenv/FIMSelection-v1")
    env.reset(seed=1)
    steps, done, info = 0, False, {}
    while not done:
        _obs, _r, done, _t, info = env.step(0)
        steps += 1
    assert steps == env.spec.max_episode_steps == env.budget
    assert info["n_selected"] == 1


@pytest.mark.parametrize(
    ("env_id", "first", "bad", "kw"),
    [
        ("selenv/FIMSelection-v1", 2, 2, {}),
        ("selenv/LandmarkSelection-v1", 2, 2, {}),
        ("selenv/CLScheduling-v1", 0, 0, {"budget": 2}),  # two picks per filter step
    ],
)
def test_raise_and_terminate_modes(env_id: str, first: int, bad: int, kw: dict) -> None:
    strict = _make(env_id, "raise", **kw)
    strict.reset(seed=0)
    strict.step(first)
    with pytest.raises(ValueError, match=f"action {bad} is invalid: masked"):
        strict.step(bad)
    term = _make(env_id, "terminate", **kw)
    term.reset(seed=0)
    term.step(first)
    _obs, r, terminated, truncated, info = term.step(bad)
    assert (r, terminated, truncated) == (PEN, True, False) and info["invalid_action"]
    with pytest.raises(RuntimeError, match="reset"):
        term.step(1)


def test_out_of_space_actions_are_errors_in_every_mode() -> None:
    for mode in ("noop", "raise", "terminate"):
        env = _make("selenv/FIMSelection-v1", mode)
        env.reset(seed=0)
        with pytest.raises(ValueError, match="out of range"):
            env.step(env.n)
        with pytest.raises(TypeError, match="integer"):
            env.step(0.0)


# -- LandmarkSelection-v1 --------------------------------------------------------------------------
def test_landmark_noop_slot_updates_with_the_valid_picks_only() -> None:
    env = _make("selenv/LandmarkSelection-v1", horizon=3)  # k = 2
    env.reset(seed=4)
    env.step(5)
    _obs, r, _term, _trunc, info = env.step(5)  # masked: the step closes with one landmark
    assert info["invalid_action"] and info["last_selection"].tolist() == [5, -1]  # -1: padding
    ref = gym.make("selenv/LandmarkSelection-v1", horizon=3, k=1).unwrapped  # same flight
    ref.reset(seed=4)
    _obs, r_ref, *_ = ref.step(5)
    np.testing.assert_allclose(env.ekf.P, ref.ekf.P, rtol=1e-12, atol=1e-15)
    assert r == pytest.approx(r_ref + PEN, rel=1e-12)


# -- CLScheduling-v1 -------------------------------------------------------------------------------
def test_cl_noop_on_the_last_slot_equals_stopping() -> None:
    kw = {"budget": 2}  # two picks per filter step: the no-op spends the second
    env = _make("selenv/CLScheduling-v1", **kw)
    ref = gym.make("selenv/CLScheduling-v1", **kw).unwrapped
    env.reset(seed=2)
    ref.reset(seed=2)
    r1, r1_ref = env.step(0)[1], ref.step(0)[1]
    assert r1 == r1_ref
    _obs, r2, _t, _tr, info = env.step(0)  # pair 0 again: masked, spends the last slot
    _obs, r2_ref, *_ = ref.step(ref.n_pairs)  # stop
    assert info["invalid_action"] and info["invalid_code"] == MASKED
    assert env.sim.k == ref.sim.k == 2
    assert r2 == pytest.approx(r2_ref + PEN, rel=1e-12, abs=1e-12)
    np.testing.assert_array_equal(env.sim.P, ref.sim.P)


# -- ReceiverClustering-v1 -------------------------------------------------------------------------
@pytest.mark.parametrize("action_mode", ["assignment", "edit"])
def test_clustering_noop_keeps_the_clustering_and_runs_the_filter(action_mode: str) -> None:
    env = _make("selenv/ReceiverClustering-v1", action_mode=action_mode)
    ref = gym.make("selenv/ReceiverClustering-v1", action_mode=action_mode).unwrapped
    env.reset(seed=3)
    ref.reset(seed=3)
    labels = env.bank.labels.copy()
    if action_mode == "assignment":
        bad, keep = np.zeros(env.n, np.int64), labels  # one cluster of 30 > max size 3
    else:
        bad, keep = int(np.flatnonzero(~env.action_masks())[0]), 0
    _obs, r, _t, _tr, info = env.step(bad)
    _obs, r_ref, *_ = ref.step(keep)
    assert info["invalid_action"]
    assert info["invalid_code"] == (INFEASIBLE if action_mode == "assignment" else MASKED)
    np.testing.assert_array_equal(env.bank.labels, labels)
    assert env.bank.k == ref.bank.k == 1
    assert r == pytest.approx(r_ref + PEN, rel=1e-12)
    strict = _make("selenv/ReceiverClustering-v1", "raise", action_mode=action_mode)
    strict.reset(seed=3)
    with pytest.raises(ValueError, match="is invalid"):
        strict.step(bad)


# -- PettingZoo ------------------------------------------------------------------------------------
def test_fim_multiagent_noop_charges_only_the_offender() -> None:
    kw = {"mode": "independent", "invalid_action_penalty": PEN}
    env = fim_selection_v0.parallel_env(**kw)
    env.reset(seed=0)
    env.step({"agent_0": 1, "agent_1": 1})
    f = env.state()
    _obs, rew, _terms, _truncs, infos = env.step({"agent_0": 1, "agent_1": 2})
    assert infos["agent_0"]["invalid_action"] and not infos["agent_1"]["invalid_action"]
    assert rew["agent_0"] == pytest.approx(rew["agent_1"] + PEN)
    n = (len(f) - 4) // 2
    assert env.state()[n : 2 * n].sum() == f[n : 2 * n].sum() + 1  # only agent_1 picked
    term = fim_selection_v0.parallel_env(**{**kw, "invalid_action": "terminate"})
    term.reset(seed=0)
    term.step({"agent_0": 1, "agent_1": 1})
    _obs, rew, terms, _truncs, _infos = term.step({"agent_0": 1, "agent_1": 2})
    assert all(terms.values()) and term.agents == [] and rew == {"agent_0": PEN, "agent_1": 0.0}


def test_clustering_multiagent_masked_label_means_stay() -> None:
    kw = {"n_agents": 7, "horizon": 3, "invalid_action_penalty": PEN}
    env, ref = receiver_clustering_v1.parallel_env(**kw), receiver_clustering_v1.parallel_env(**kw)
    start = {"clustering": [0, 0, 0, 1, 1, 2, 2]}  # cluster 0 full (max size 3)
    env.reset(seed=0, options=start)
    ref.reset(seed=0, options=start)
    stay = {a: int(env.bank.labels[i]) for i, a in enumerate(env.possible_agents)}
    _o, rew, _t, _tr, infos = env.step(stay | {"receiver_4": 0})
    _o, rew_ref, *_ = ref.step(stay)
    assert infos["receiver_4"]["invalid_action"] and not infos["receiver_4"]["accepted"]
    np.testing.assert_array_equal(env.bank.labels, ref.bank.labels)
    assert rew["receiver_4"] == pytest.approx(rew_ref["receiver_4"] + PEN, rel=1e-12)
    assert rew["receiver_0"] == rew_ref["receiver_0"]
