"""Every step's ``info`` has the same keys, shapes and numeric dtypes, in every env and module.

Learners that batch ``info`` into buffers (TorchRL's batched ``GymEnv``, Tianshou's replay
buffer, RLlib's episodes) need one fixed schema: a key that appears only on some steps leaves
holes (NaN in Tianshou), a ``str`` or a variable-length list cannot become a tensor. Each env is
walked through reset, valid steps, an invalid (masked or infeasible) step and its terminal step,
in the single env, the native vector env and the PettingZoo modules.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401  (registers the envs)
from selenv.envs.actions import INVALID_CODES
from selenv.multiagent import fim_selection_v0, receiver_clustering_v1

ALL_IDS = sorted(i for i in gym.registry if i.startswith("selenv/"))
SHORT: dict[str, dict[str, Any]] = {  # short episodes; the schema does not depend on them
    "FIMSelection": {"n_candidates": 10, "budget": 4},
    "LandmarkSelection": {"horizon": 3},
    "CLScheduling": {"horizon": 3, "budget": 2},  # two pairs per step: the first is masked
    "ReceiverClustering": {"horizon": 3, "n_agents": 6},  # -v2: 6 placements per filter step
}


def _short(env_id: str) -> dict[str, Any]:
    return SHORT[env_id.split("/")[1].split("-")[0]]


def _schema(info: dict[str, Any]) -> dict[str, tuple[str, tuple[int, ...]]]:
    """key -> (numpy dtype kind, shape); fails on anything that is not a bool or number."""
    out = {}
    for key, value in info.items():
        arr = np.asarray(value)
        assert arr.dtype.kind in "biuf", f"info[{key!r}] is {type(value).__name__} {arr.dtype}"
        out[key] = (arr.dtype.kind, arr.shape)
    return out


def _first(mask: np.ndarray, allowed: bool) -> int | None:
    where = np.flatnonzero(np.asarray(mask, dtype=bool) == allowed)
    return int(where[0]) if where.size else None


def _masked_action(env: gym.Env) -> Any:
    """An action in the space that is invalid now, or ``None`` if every action is allowed."""
    base = env.unwrapped
    mask = np.asarray(base.action_masks(), dtype=bool)
    if isinstance(env.action_space, gym.spaces.Discrete):
        return _first(mask, False)
    # ReceiverClustering's assignment mode: one label per receiver; all in one cluster
    # breaks the state limit (infeasible) whatever the mask says
    return np.zeros(env.action_space.shape, dtype=np.int64)


def _valid_action(env: gym.Env, info: dict[str, Any]) -> Any:
    if isinstance(env.action_space, gym.spaces.Discrete):
        return _first(info["action_mask"], True)
    return env.unwrapped.bank.labels.copy()  # keep the clustering: always feasible


@pytest.mark.parametrize("mode", ["noop", "terminate"])
@pytest.mark.parametrize("env_id", ALL_IDS)
def test_single_env_info_schema_is_fixed(env_id: str, mode: str) -> None:
    env = gym.make(env_id, invalid_action=mode, **_short(env_id))
    assert env.metadata["invalid_codes"] == INVALID_CODES
    _, info = env.reset(seed=0)
    want = _schema(info)
    assert want["invalid_action"] == ("b", ()) and want["invalid_code"][0] in "iu"
    steps, invalid_seen, done = 0, False, False
    while not done:
        bad = None if invalid_seen or steps < 1 else _masked_action(env)
        action = _valid_action(env, info) if bad is None else bad
        _, reward, terminated, truncated, info = env.step(action)
        assert _schema(info) == want, f"step {steps}"
        assert np.isfinite(reward)
        if bad is not None:
            invalid_seen = True
            code = int(info["invalid_code"])
            assert info["invalid_action"] and INVALID_CODES[code] in ("masked", "infeasible")
            assert terminated == (mode == "terminate")
        else:
            assert not info["invalid_action"] and info["invalid_code"] == 0
        steps += 1
        done = terminated or truncated
    assert invalid_seen, "the walk never found an invalid action"


VECTOR_IDS = [i for i in ALL_IDS if not i.endswith("-v0") and gym.spec(i).vector_entry_point]


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_info_keys_that_are_observation_keys_have_their_shape(env_id: str) -> None:
    """TorchRL stores the info keys beside the observation keys: a shared name needs one shape."""
    env = gym.make(env_id, **_short(env_id))
    obs, info = env.reset(seed=0)
    shared = set(obs) & set(info)
    for key in shared:
        assert np.shape(info[key]) == np.shape(obs[key]), key
    obs, _, _, _, info = env.step(_valid_action(env, info))
    for key in set(obs) & set(info):
        assert np.shape(info[key]) == np.shape(obs[key]), key


@pytest.mark.parametrize("env_id", VECTOR_IDS)
def test_vector_env_infos_hold_every_key_for_every_sub_env(env_id: str) -> None:
    """Native ``make_vec`` envs: the same keys (all ``_key`` masks true) through autoresets."""
    venv = gym.make_vec(env_id, num_envs=3, **_short(env_id))
    _, infos = venv.reset(seed=0)
    keys = sorted(infos)
    shapes = {k: (np.asarray(v).dtype.kind, np.asarray(v).shape) for k, v in infos.items()}
    rng = np.random.default_rng(0)
    ends = 0
    for t in range(40):
        masks = np.asarray(venv.action_masks(), dtype=bool)
        space = venv.single_action_space
        if isinstance(space, gym.spaces.MultiDiscrete):  # one label per receiver
            m = masks.reshape(3, len(space.nvec), -1)
            actions = np.argmax(rng.random(m.shape) + m, axis=-1)
        else:
            actions = np.argmax(rng.random(masks.shape) + masks, axis=-1)
            if t == 1:  # sub-env 0 repeats a masked action where there is one
                blocked = np.flatnonzero(~masks[0])
                if blocked.size:
                    actions[0] = blocked[0]
        _, _, terminated, truncated, infos = venv.step(actions)
        ends += int(np.sum(terminated | truncated))
        assert sorted(infos) == keys, f"step {t}"
        for key in keys:
            arr = np.asarray(infos[key])
            assert (arr.dtype.kind, arr.shape) == shapes[key], f"step {t}: {key}"
            if key.startswith("_"):
                assert arr.all(), f"step {t}: {key} is not set for every sub-env"
    assert ends >= 3  # the walk went through autoresets
    venv.close()


def _pz_walk(env: Any, seed: int) -> None:
    obs, infos = env.reset(seed=seed)
    want = {a: _schema(infos[a]) for a in env.agents}
    rng = np.random.default_rng(seed)
    invalid_seen, t = False, 0
    while env.agents:
        actions = {}
        for a in env.agents:
            mask = np.asarray(obs[a]["action_mask"], dtype=bool)
            actions[a] = int(np.argmax(rng.random(mask.shape) + mask))
        if not invalid_seen and t >= 1:
            for a in env.agents:
                blocked = _first(obs[a]["action_mask"], False)
                acts = np.asarray(obs[a].get("on_turn", [1]))[0] == 1
                if blocked is not None and acts:
                    actions[a], invalid_seen, bad = blocked, True, a
                    break
            else:
                bad = None
        else:
            bad = None
        obs, rewards, terms, truncs, infos = env.step(actions)
        for a, info in infos.items():
            assert _schema(info) == want[a], f"step {t}: {a}"
            assert np.isfinite(rewards[a])
        if bad is not None:
            assert infos[bad]["invalid_action"] and infos[bad]["invalid_code"] > 0
        t += 1
    assert invalid_seen, "the walk never found an invalid action"


@pytest.mark.parametrize("mode", ["cooperative", "independent"])
def test_fim_module_info_schema_is_fixed(mode: str) -> None:
    _pz_walk(fim_selection_v0.parallel_env(mode=mode, n_candidates=10, budgets=3), seed=0)


def test_clustering_module_info_schema_is_fixed() -> None:
    # max_size 2 on 4 receivers: clusters fill up, so masked labels occur
    _pz_walk(receiver_clustering_v1.parallel_env(horizon=6), seed=1)
