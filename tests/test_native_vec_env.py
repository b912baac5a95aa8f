"""The SB3 adapter over the native vector envs replays DummyVecEnv and trains MaskablePPO.

:class:`selenv.learned.rl.vec_env.NativeVecEnv` converts Gymnasium's ``NEXT_STEP`` autoreset
into SB3's same-step reset; driven with the same actions as a ``DummyVecEnv`` over
``gymnasium.make`` envs seeded alike, it must return the same observations (within the
portability tolerances), rewards, dones, terminal observations and masks, across episode
ends.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from sb3_contrib.common.maskable.utils import get_action_masks
from stable_baselines3.common.vec_env import DummyVecEnv

import selenv  # noqa: F401
from selenv.families import FAMILIES
from selenv.learned.rl.candidate_policy import make_maskable_ppo
from selenv.learned.rl.vec_env import NativeVecEnv, make_native_vec_env
from selenv.learned.rl.views import CandidateViewWrapper, view_for

#: small, short episodes, so a few dozen steps cross several episode ends; with the view the
#: training scripts use (a pure one: no previews)
CASES = {
    "selenv/FIMSelection-v1": ({"n_candidates": 20, "budget": 4}, None),
    "selenv/LandmarkSelection-v1": ({"horizon": 3}, None),
    "selenv/CLScheduling-v1": ({"horizon": 3}, "cl_pairs"),
    "selenv/ReceiverClustering-v1": ({"horizon": 4, "action_mode": "edit"}, "clustering_edits"),
}
IDS = [f.current_id for f in FAMILIES if f.vector_class is not None and f.current_id in CASES]


def _close(a: object, b: object, where: str) -> None:
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), where
        for k in a:
            _close(a[k], b[k], f"{where}[{k}]")
        return
    x, y = np.asarray(a), np.asarray(b)
    if x.dtype.kind == "f" or y.dtype.kind == "f":
        np.testing.assert_allclose(x, y, rtol=3e-7, atol=1e-6, err_msg=where)
    else:
        np.testing.assert_array_equal(x, y, err_msg=where)


def _dummy(env_id: str, kwargs: dict, view: str | None, n: int) -> DummyVecEnv:
    def make() -> gym.Env:
        env = gym.make(env_id, **kwargs)
        return env if view is None else CandidateViewWrapper(env, view_for(env_id, env, view))

    return DummyVecEnv([make for _ in range(n)])


@pytest.mark.parametrize("env_id", IDS)
def test_native_adapter_replays_dummy_vec_env(env_id: str) -> None:
    _replay(env_id, *CASES[env_id])


def _replay(env_id: str, kwargs: dict, view: str | None) -> None:
    n = 3
    native = make_native_vec_env(env_id, n, seed=11, view=view, env_kwargs=kwargs, monitor=False)
    dummy = _dummy(env_id, kwargs, view, n)
    dummy.seed(11)
    _close(native.reset(), dummy.reset(), "reset")
    rng = np.random.default_rng(0)
    ends = 0
    for t in range(40):
        masks = get_action_masks(dummy)
        np.testing.assert_array_equal(get_action_masks(native), masks, err_msg=f"mask {t}")
        actions = np.array([rng.choice(np.flatnonzero(m)) for m in masks])
        o1, r1, d1, i1 = native.step(actions)
        o2, r2, d2, i2 = dummy.step(actions)
        _close(o1, o2, f"step {t} obs")
        np.testing.assert_allclose(r1, r2, rtol=1e-6, atol=1e-6, err_msg=f"step {t} reward")
        np.testing.assert_array_equal(d1, d2, err_msg=f"step {t} dones")
        for b in np.flatnonzero(d2):
            ends += 1
            _close(i1[b]["terminal_observation"], i2[b]["terminal_observation"], f"t{t} term")
            assert i1[b]["TimeLimit.truncated"] == i2[b]["TimeLimit.truncated"]
    assert ends >= 2 * n  # the comparison crossed episode ends in every sub-env
    native.close()
    dummy.close()


@pytest.mark.parametrize("env_id", IDS)
def test_maskable_ppo_trains_on_the_native_vec_env(env_id: str) -> None:
    kwargs, view = CASES[env_id]
    venv = make_native_vec_env(env_id, 4, seed=0, view=view, env_kwargs=kwargs)
    model = make_maskable_ppo(venv, n_steps=16, batch_size=32, n_epochs=1, seed=0)
    model.learn(128)
    assert model.num_timesteps >= 128
    assert len(model.ep_info_buffer) > 0  # VecMonitor saw finished episodes
    venv.close()


def test_a_single_live_view_is_refused() -> None:
    """A view that reads the live env cannot be shared by the sub-envs: one per sub-env."""
    if "selenv/CLScheduling-v1" not in IDS:
        pytest.skip("no native CL vector env")
    env = gym.make("selenv/CLScheduling-v1")
    live = view_for("selenv/CLScheduling-v1", env, "cl_pairs_fused")
    assert live.live
    venv = gym.make_vec("selenv/CLScheduling-v1", num_envs=2)
    with pytest.raises(ValueError, match="one view per sub-env"):
        NativeVecEnv(venv, live)
    with pytest.raises(ValueError, match="expected 2 views"):
        NativeVecEnv(venv, [live])
    venv.close()
    env.close()


def test_live_view_on_the_native_cl_env_replays_dummy_vec_env() -> None:
    """``cl_pairs_fused`` (previewed fused gains) served by the vector env's ``sub_env``."""
    venv = gym.make_vec("selenv/CLScheduling-v1", num_envs=2)
    has = callable(getattr(venv, "sub_env", None))
    venv.close()
    if not has:
        pytest.skip("the CL vector env serves no sub_env previews")
    CASES["cl_fused"] = ({"horizon": 3}, "cl_pairs_fused")
    try:
        _replay("selenv/CLScheduling-v1", *CASES["cl_fused"])
    finally:
        del CASES["cl_fused"]


def test_needs_next_step_autoreset_and_masks() -> None:
    venv = gym.make_vec("CartPole-v1", num_envs=2, vectorization_mode="sync")
    with pytest.raises(ValueError, match="action_masks"):
        NativeVecEnv(venv)
    venv.close()
