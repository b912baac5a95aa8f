"""The shared behaviour of the native vector envs (selenv.envs.vector), on every family.

Autoreset modes (NEXT_STEP, SAME_STEP, DISABLED) give the same episodes; observations handed
out are never overwritten by a later step; seeds, reset masks and modes are validated.
"""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import selenv  # noqa: F401
from selenv.envs.vector import BatchedVectorEnv, check_num_envs, merge_infos
from selenv.families import FAMILIES

#: short episodes so that a few steps cross episode ends
SHORT = {
    "selenv/FIMSelection-v1": {"n_candidates": 10, "budget": 3},
    "selenv/LandmarkSelection-v1": {"horizon": 2},
    "selenv/CLScheduling-v1": {"horizon": 2},
    "selenv/ReceiverClustering-v1": {"horizon": 3},
    # 4 placements per filter step, 8 steps per episode
    "selenv/ReceiverClustering-v2": {"n_agents": 4, "horizon": 2},
}
IDS = [f.current_id for f in FAMILIES if f.vector_class is not None]
#: the frozen versions with a native vector env (their own keywords, still batched)
FROZEN_IDS = [
    f.version_id(k) for f in FAMILIES for k in range(1, f.version) if f.classes(k)[1] is not None
]


def _actions(venv: BatchedVectorEnv, rng: np.random.Generator) -> np.ndarray:
    space = venv.single_action_space
    masks = np.asarray(venv.action_masks(), dtype=bool)
    if isinstance(space, gym.spaces.MultiDiscrete):
        masks = masks.reshape(venv.num_envs, len(space.nvec), -1)
    return np.argmax(rng.random(masks.shape) + masks, axis=-1)


def _leaf_equal(a: object, b: object) -> bool:
    if isinstance(a, dict):
        return isinstance(b, dict) and all(_leaf_equal(a[k], b[k]) for k in a)
    return np.array_equal(np.asarray(a), np.asarray(b))


def _row(obs: dict, b: int) -> dict:
    return {k: np.asarray(v)[b].copy() for k, v in obs.items()}


@pytest.mark.parametrize("env_id", IDS + FROZEN_IDS)
def test_make_vec_returns_the_native_env_for_every_version(env_id: str) -> None:
    venv = gym.make_vec(env_id, num_envs=2)
    assert isinstance(venv, BatchedVectorEnv)
    assert venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    venv.close()
    old = env_id.rsplit("-v", 1)[0] + "-v0"
    with pytest.warns(DeprecationWarning, match="reproduces selenv 0.1"):
        venv0 = gym.make_vec(old, num_envs=2)
    assert isinstance(venv0, BatchedVectorEnv)
    venv0.close()
    loop = gym.make_vec(env_id, num_envs=2, vectorization_mode="sync")
    assert not isinstance(loop, BatchedVectorEnv)  # the Python loop is still available
    loop.close()


@pytest.mark.parametrize("env_id", IDS + FROZEN_IDS)
def test_same_step_and_next_step_give_the_same_episodes(env_id: str) -> None:
    kw = SHORT[env_id]
    nxt = gym.make_vec(env_id, num_envs=3, **kw)
    same = gym.make_vec(env_id, num_envs=3, autoreset_mode="SameStep", **kw)
    assert same.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    rng = np.random.default_rng(1)
    o_n, _ = nxt.reset(seed=5)
    o_s, _ = same.reset(seed=5)
    finals = 0
    for t in range(14):
        acts = _actions(nxt, rng)
        o_n, r_n, te_n, tr_n, _ = nxt.step(acts)
        o_s, r_s, te_s, tr_s, i_s = same.step(acts)
        np.testing.assert_allclose(r_s, r_n, rtol=1e-12, err_msg=f"step {t}")
        np.testing.assert_array_equal(te_s | tr_s, te_n | tr_n)
        ended = np.flatnonzero(te_n | tr_n)
        for b in range(3):
            if b not in ended:
                assert _leaf_equal(_row(o_s, b), _row(o_n, b)), f"step {t}, sub-env {b}"
        if ended.size:
            assert i_s["_final_obs"][ended].all() and i_s["_final_obs"].sum() == ended.size
            for b in ended:
                finals += 1
                assert _leaf_equal(i_s["final_obs"][b], _row(o_n, b))  # NEXT_STEP's last obs
            # NEXT_STEP resets them at the next step (their action ignored): its first
            # observations are the ones SAME_STEP returned already
            o_next, *_ = nxt.step(_actions(nxt, rng))
            for b in ended:
                assert _leaf_equal(_row(o_s, b), _row(o_next, b)), f"reset obs, sub-env {b}"
            break
    assert finals >= 1
    nxt.close()
    same.close()


@pytest.mark.parametrize("env_id", IDS + FROZEN_IDS)
def test_disabled_mode_refuses_a_finished_sub_env_until_reset(env_id: str) -> None:
    kw = SHORT[env_id]
    venv = gym.make_vec(env_id, num_envs=2, autoreset_mode=AutoresetMode.DISABLED, **kw)
    rng = np.random.default_rng(0)
    venv.reset(seed=0)
    for _ in range(100):
        _, _, te, tr, _ = venv.step(_actions(venv, rng))
        if (te | tr).any():
            break
    done = te | tr
    assert done.any()
    with pytest.raises(RuntimeError, match="reset them"):
        venv.step(_actions(venv, rng))
    venv.reset(options={"reset_mask": done})
    venv.step(_actions(venv, rng))  # every sub-env live again
    venv.close()


@pytest.mark.parametrize("env_id", IDS + FROZEN_IDS)
def test_observations_handed_out_are_not_overwritten(env_id: str) -> None:
    venv = gym.make_vec(env_id, num_envs=2, **SHORT[env_id])
    rng = np.random.default_rng(0)
    obs, _ = venv.reset(seed=0)
    snapshot = {k: np.array(v, copy=True) for k, v in obs.items()}
    for _ in range(4):
        venv.step(_actions(venv, rng))
    assert _leaf_equal(obs, snapshot), "a later step mutated an observation already returned"
    venv.close()


@pytest.mark.parametrize("env_id", IDS + FROZEN_IDS)
def test_same_seed_same_batch_and_seed_forms(env_id: str) -> None:
    kw = SHORT[env_id]
    a = gym.make_vec(env_id, num_envs=3, **kw)
    b = gym.make_vec(env_id, num_envs=3, **kw)
    oa, _ = a.reset(seed=7)
    ob, _ = b.reset(seed=[7, 8, 9])  # an int s means s, s + 1, s + 2
    assert _leaf_equal(oa, ob)
    with pytest.raises(ValueError, match="expected 3 seeds"):
        a.reset(seed=[1, 2])
    with pytest.raises(TypeError, match="seed must be None"):
        a.reset(seed=1.5)
    with pytest.raises(TypeError, match="reset_mask"):
        a.reset(options={"reset_mask": [True, False, True]})
    with pytest.raises(ValueError, match="reset_mask"):
        a.reset(options={"reset_mask": np.zeros(3, dtype=bool)})
    a.close()
    b.close()


def test_bad_modes_and_sizes() -> None:
    env_id = IDS[0]
    with pytest.raises(ValueError, match="autoreset_mode must be one of"):
        gym.make_vec(env_id, num_envs=2, autoreset_mode="sometimes")
    with pytest.raises(ValueError, match="num_envs must lie in"):
        check_num_envs(0)
    with pytest.raises(TypeError, match="num_envs must be an int"):
        check_num_envs(2.0)
    with pytest.raises(TypeError, match="num_envs must be an int"):
        check_num_envs(True)


def test_step_before_reset_is_refused() -> None:
    venv = gym.make_vec(IDS[0], num_envs=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(RuntimeError, match="reset"):
            venv.step(np.zeros(2, dtype=np.int64))
    venv.close()


def test_merge_infos_masks_and_object_values() -> None:
    out: dict = {}
    merge_infos(out, {"x": np.array([1.0, 2.0]), "s": ["a", "b"]}, np.array([0, 2]), 3)
    np.testing.assert_array_equal(out["x"], [1.0, 0.0, 2.0])
    np.testing.assert_array_equal(out["_x"], [True, False, True])
    assert out["s"].dtype == object and out["s"][2] == "b" and out["s"][1] is None
    merge_infos(out, {"x": np.array([5.0])}, np.array([1]), 3)
    np.testing.assert_array_equal(out["x"], [1.0, 5.0, 2.0])
    assert out["_x"].all() and not out["_s"][1]


@pytest.mark.parametrize("family", [f for f in FAMILIES if f.vector_class is not None])
def test_vector_env_takes_exactly_the_single_envs_keywords(family) -> None:
    """The two constructors list the same keywords with the same defaults (plus num_envs)."""
    import inspect

    from selenv.families.spec import load_attr

    def params(cls: type) -> dict[str, object]:
        sig = inspect.signature(cls.__init__)
        return {n: p.default for n, p in sig.parameters.items() if n not in ("self", "num_envs")}

    single, vector = load_attr(family.env_class), load_attr(family.vector_class)
    assert params(vector) == params(single)
