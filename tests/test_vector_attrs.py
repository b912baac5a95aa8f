"""``call`` / ``get_attr`` / ``set_attr`` of the native vector envs against ``SyncVectorEnv``.

Gymnasium's ``SyncVectorEnv`` over ``gymnasium.make`` envs is the reference: for the same seeds
and actions, every attribute both expose per sub-env must agree (generators by their state,
masks and budgets by value), user attributes round-trip the same way, and the length and name
errors are the same kinds.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from test_vector_base import IDS, SHORT, _actions  # the short episodes and random valid actions

import selenv  # noqa: F401
from selenv.envs.vector import BatchedVectorEnv

B = 3


def _pair(env_id: str, **kw: object) -> tuple[BatchedVectorEnv, gym.vector.VectorEnv]:
    native = gym.make_vec(env_id, num_envs=B, **SHORT[env_id], **kw)
    sync = gym.make_vec(env_id, num_envs=B, vectorization_mode="sync", **SHORT[env_id], **kw)
    assert isinstance(native, BatchedVectorEnv)
    return native, sync


def _state(rng: np.random.Generator) -> dict:
    return rng.bit_generator.state


@pytest.mark.parametrize("env_id", IDS)
def test_sub_env_attributes_agree_with_sync_vector_env(env_id: str) -> None:
    native, sync = _pair(env_id)
    native.reset(seed=7)
    sync.reset(seed=7)
    rng = np.random.default_rng(0)
    for _ in range(4):  # crosses an episode end: the autoreset draws from the same generators
        for name in ("np_random_seed", "render_mode"):
            assert native.get_attr(name) == sync.get_attr(name), name
        assert [_state(g) for g in native.get_attr("np_random")] == [
            _state(g) for g in sync.get_attr("np_random")
        ]
        masks = native.call("action_masks")
        assert len(masks) == B
        for mine, theirs in zip(masks, sync.call("action_masks"), strict=True):
            np.testing.assert_array_equal(mine, theirs)
        if "budget_left" in type(native).sub_env_attributes:
            budgets = native.get_attr("budget_left")
            assert budgets == sync.get_attr("budget_left")
            assert all(type(b) is int for b in budgets)
        actions = _actions(native, rng)
        native.step(actions)
        sync.step(actions)
    assert native.get_attr("np_random_seed") == (7, 8, 9)
    assert native.get_attr("observation_space") == (native.single_observation_space,) * B
    assert native.get_attr("action_space") == sync.get_attr("action_space")
    # the single env's metadata (the vector env's own differs: it has the vector render modes)
    assert native.get_attr("metadata") == sync.get_attr("metadata")
    assert [s.id for s in native.get_attr("spec")] == [s.id for s in sync.get_attr("spec")]
    native.close()
    sync.close()


@pytest.mark.parametrize("env_id", IDS)
def test_user_attributes_and_errors_match_sync_vector_env(env_id: str) -> None:
    native, sync = _pair(env_id)
    for venv in (native, sync):
        venv.reset(seed=1)
        venv.set_attr("task_id", [10, 11, 12])
        assert venv.get_attr("task_id") == (10, 11, 12)
        venv.set_attr("task_id", "shared")  # a single value goes to every sub-env
        assert venv.get_attr("task_id") == ("shared",) * B
        with pytest.raises(ValueError, match="values"):
            venv.set_attr("task_id", [1, 2])
        with pytest.raises(AttributeError):
            venv.get_attr("no_such_attribute")
    with pytest.raises(AttributeError, match="did you mean 'task_id'"):
        native.get_attr("task_idd")
    if "budget_left" not in type(native).sub_env_attributes:  # neither side has one
        with pytest.raises(AttributeError):
            sync.get_attr("budget_left")
        with pytest.raises(AttributeError):
            native.get_attr("budget_left")
    native.close()
    sync.close()


def test_assigned_generators_drive_the_next_episodes_as_on_sync() -> None:
    env_id = "selenv/FIMSelection-v1"
    native, sync = _pair(env_id)
    native.reset(seed=3)
    sync.reset(seed=3)
    for venv in (native, sync):
        venv.set_attr("np_random", [np.random.default_rng(100 + b) for b in range(B)])
        assert venv.get_attr("np_random_seed") == (-1,) * B  # gymnasium.Env's setter rule
    a, _ = native.reset()  # no seed: each sub-env draws from its assigned generator
    b, _ = sync.reset()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    with pytest.raises(TypeError, match="Generators"):
        native.set_attr("np_random", 5)
    native.close()
    sync.close()


def test_generators_before_the_first_reset_are_made_on_demand() -> None:
    native = gym.make_vec("selenv/FIMSelection-v1", num_envs=2)
    rngs = native.get_attr("np_random")
    assert all(isinstance(g, np.random.Generator) for g in rngs)
    seeds = native.get_attr("np_random_seed")
    assert all(isinstance(s, int) and s >= 0 for s in seeds)
    assert native.get_attr("np_random") == rngs  # made once, then kept
    native.close()


def test_env_state_and_vector_only_names_are_refused_with_a_reason() -> None:
    native = gym.make_vec("selenv/FIMSelection-v1", num_envs=2)
    native.reset(seed=0)
    with pytest.raises(AttributeError, match="shared"):
        native.set_attr("budget_left", 1)
    with pytest.raises(AttributeError, match="reset_mask"):
        native.call("reset")
    with pytest.raises(TypeError, match="no arguments"):
        native.call("action_masks", 1)
    with pytest.raises(TypeError, match="str"):
        native.get_attr(3)  # type: ignore[arg-type]
    native.close()


def test_call_render_returns_every_sub_env_frame() -> None:
    env_id = "selenv/FIMSelection-v1"
    native, sync = _pair(env_id, render_mode="rgb_array")
    native.reset(seed=2)
    sync.reset(seed=2)
    frames = native.call("render")
    theirs = sync.call("render")
    assert len(frames) == B
    for mine, ref in zip(frames, theirs, strict=True):
        assert mine.shape == ref.shape and mine.dtype == ref.dtype
        np.testing.assert_array_equal(mine, ref)
    plain = gym.make_vec(env_id, num_envs=2)
    assert plain.call("render") == (None, None)  # no render_mode: no frames, as the single env
    for venv in (native, sync, plain):
        venv.close()
