"""The native vector env of LandmarkSelection: make_vec, equivalence with the single env, errors."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401
from selenv.agents import make
from selenv.envs.vector_check import check_vector_equivalence
from selenv.families.landmarks.scenario import LandmarkConfig, scenario_static
from selenv.families.landmarks.vector import LandmarkSelectionVectorEnv

ENV_ID = "selenv/LandmarkSelection-v1"
SHORT: dict[str, Any] = {"n_landmarks": 8, "horizon": 5}  # k = 2: 10 steps an episode


def _any_action(b: int, env: Any, mask: np.ndarray, rng: np.random.Generator) -> int:
    """Uniform over every action, masked ones included (invalid picks half the time)."""
    return int(rng.integers(len(mask)))


def _agent_picker(name: str, n: int) -> Any:
    """A heuristic agent per sub-env, reset with each new episode of its single env."""
    agents = [make(name, ENV_ID) for _ in range(n)]
    bound: list[Any] = [None] * n

    def pick(b: int, env: Any, mask: np.ndarray, rng: np.random.Generator) -> int:
        base = env.unwrapped
        if base._done:
            return 0  # the episode ended: the vector env autoresets, the action is ignored
        if bound[b] is not base.problem:
            agents[b].reset(env, seed=b)
            bound[b] = base.problem
        return int(agents[b].act(base._obs(), base._info()))

    return pick


def test_make_vec_returns_the_native_class_v0_warns() -> None:
    env = gym.make_vec(ENV_ID, num_envs=8)
    assert isinstance(env, LandmarkSelectionVectorEnv) and env.num_envs == 8
    assert env.single_action_space == gym.spaces.Discrete(30)
    with pytest.warns(DeprecationWarning):
        old = gym.make_vec("selenv/LandmarkSelection-v0", num_envs=2)
    assert isinstance(old, LandmarkSelectionVectorEnv)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert obs["whitened"].shape == (8, 30, 18) and env.action_masks().shape == (8, 30)
    assert info["_objective"].all()


@pytest.mark.parametrize("seeds", [[0, 1, 2, 3], [7, 7, 123, 5], [40, 41, 42, 1000]])
def test_random_masked_actions_match_the_single_envs(seeds: list[int]) -> None:
    counts = check_vector_equivalence(ENV_ID, num_envs=4, seeds=seeds, steps=35, **SHORT)
    assert counts["autoresets"] >= 2 * 4 - 1 and counts["episodes"] >= 8


@pytest.mark.parametrize(
    "kwargs",
    [
        {"n_landmarks": 7, "horizon": 4, "k": 3, "objective": "trace"},
        {"n_landmarks": 6, "horizon": 4, "k": 1, "objective": "max_eig"},
        {"n_landmarks": 6, "horizon": 3, "k": 2, "objective": "det", "dt": 0.2},
        {
            "n_landmarks": 5,
            "horizon": 4,
            "k": 2,
            "landmarks": [
                [3e3, 1e3, 0],
                [-2e3, 4e3, 50],
                [1e3, -3e3, 10],
                [5e3, 5e3, 0],
                [-4e3, -4e3, 20],
            ],
            "aoa_sigma_deg": (0.3, 0.9),
        },
    ],
)
def test_non_default_keywords_match(kwargs: dict[str, Any]) -> None:
    counts = check_vector_equivalence(ENV_ID, num_envs=3, seeds=[3, 4, 5], steps=30, **kwargs)
    assert counts["autoresets"] >= 6


@pytest.mark.parametrize("name", ["greedy", "brute_force"])
def test_heuristics_as_pickers_match(name: str) -> None:
    counts = check_vector_equivalence(
        ENV_ID, num_envs=3, seeds=[0, 1, 2], steps=24, picker=_agent_picker(name, 3), **SHORT
    )
    assert counts["autoresets"] >= 3


def test_noop_with_masked_actions_matches() -> None:
    check_vector_equivalence(
        ENV_ID, num_envs=4, steps=35, picker=_any_action, invalid_action_penalty=-2.5, **SHORT
    )


def test_terminate_matches() -> None:
    counts = check_vector_equivalence(
        ENV_ID,
        num_envs=4,
        steps=30,
        picker=_any_action,
        invalid_action="terminate",
        invalid_action_penalty=-1.0,
        n_landmarks=3,
        horizon=5,
    )
    assert counts["episodes"] >= 12  # 8 without invalid picks: they end episodes early


def test_raise_names_the_sub_env_and_changes_nothing() -> None:
    env: Any = gym.make_vec(ENV_ID, num_envs=3, invalid_action="raise", **SHORT)
    obs, _ = env.reset(seed=0)
    obs, *_ = env.step(np.array([1, 2, 3]))
    before = {k: v.copy() for k, v in obs.items()}
    with pytest.raises(ValueError, match=r"sub-env 1: action 2 is invalid: masked"):
        env.step(np.array([0, 2, 4]))
    np.testing.assert_array_equal(env.action_masks().sum(1), [7, 7, 7])
    after = env.unwrapped._observe()
    for key in before:
        np.testing.assert_array_equal(after[key], before[key])
    _, r, _, _, info = env.step(np.array([0, 1, 4]))  # the filters update
    np.testing.assert_allclose(r, -info["objective"])
    assert not info["invalid_action"].any() and not info["invalid_code"].any()


def test_reset_mask_resets_only_the_masked_sub_envs() -> None:
    env: Any = gym.make_vec(ENV_ID, num_envs=3, **SHORT)
    ref = [gym.make(ENV_ID, **SHORT) for _ in range(3)]
    env.reset(seed=10)
    for b, e in enumerate(ref):
        e.reset(seed=10 + b)
    for a in ([0, 1, 2], [3, 4, 5], [6, 7, 0]):
        env.step(np.array(a))
        for e, ab in zip(ref, a, strict=True):
            e.step(ab)
    mask = np.array([False, True, False])
    obs, info = env.reset(seed=[None, 99, None], options={"reset_mask": mask})
    o1, i1 = ref[1].reset(seed=99)
    np.testing.assert_array_equal(info["_k"], mask)
    np.testing.assert_allclose(obs["gain"][1], o1["gain"], rtol=3e-7)
    assert info["k"][1] == 1 and info["objective"][1] == pytest.approx(i1["objective"], rel=1e-12)
    for b in (0, 2):  # untouched: still mid-step 2, one landmark picked
        assert obs["selected"][b].sum() == 1 and env.action_masks()[b].sum() == 7
    obs, *_ = env.step(np.array([1, 0, 2]))
    want = [e.step(a)[0] for e, a in zip(ref, (1, 0, 2), strict=True)]
    for b in range(3):
        np.testing.assert_allclose(obs["gain"][b], want[b]["gain"], rtol=3e-7, atol=1e-6)
        np.testing.assert_array_equal(obs["selected"][b], want[b]["selected"])


def test_same_seed_twice_gives_identical_arrays() -> None:
    def run() -> list[Any]:
        env: Any = gym.make_vec(ENV_ID, num_envs=4, **SHORT)
        out = [env.reset(seed=5)[0]]
        rng = np.random.default_rng(1)
        for _ in range(25):
            acts = [int(rng.choice(np.flatnonzero(m))) for m in env.action_masks()]
            obs, r, te, tr, info = env.step(np.array(acts))
            out += [obs, r, te, info["objective"], info["position_error"]]
        return out

    a, b = run(), run()
    for x, y in zip(a, b, strict=True):
        if isinstance(x, dict):
            for key in x:
                np.testing.assert_array_equal(x[key], y[key])
        else:
            np.testing.assert_array_equal(x, y)


def test_seed_none_then_continued() -> None:
    env: Any = gym.make_vec(ENV_ID, num_envs=3, **SHORT)
    obs, _ = env.reset()  # fresh entropy
    assert env.observation_space.contains(obs)
    seen = set()
    for _ in range(25):
        acts = [int(np.flatnonzero(m)[0]) for m in env.action_masks()]
        obs, r, te, tr, info = env.step(np.array(acts))
        assert env.observation_space.contains(obs) and np.all(np.isfinite(r))
        seen.update(np.flatnonzero(te).tolist())
    assert seen == {0, 1, 2}  # every sub-env ended and went on
    obs2, _ = env.reset()  # no seed: the generators continue
    assert not np.array_equal(obs2["whitened"], obs["whitened"])


@pytest.mark.parametrize(("bad", "err"), [(0, ValueError), (1.5, TypeError), (True, TypeError)])
def test_bad_num_envs_is_named(bad: Any, err: type[Exception]) -> None:
    with pytest.raises(err, match="num_envs"):
        LandmarkSelectionVectorEnv(num_envs=bad)


def test_bad_keywords_and_actions_are_named() -> None:
    with pytest.raises(TypeError, match="k must be an int"):
        LandmarkSelectionVectorEnv(2, k=2.0)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="colour"):
        LandmarkSelectionVectorEnv(2, colour="red")
    with pytest.raises(ValueError, match="objective"):
        LandmarkSelectionVectorEnv(2, objective="min_eig")
    env = LandmarkSelectionVectorEnv(3, **SHORT)
    env.reset(seed=0)
    for bad in (np.zeros((3, 1), np.int64), np.zeros(2, np.int64), np.zeros((4,), np.int64)):
        with pytest.raises(ValueError, match="shape"):
            env.step(bad)
    with pytest.raises(TypeError, match="integers"):
        env.step(np.array([0.0, 1.0, 2.0]))
    with pytest.raises(ValueError, match="sub-env 2 is out of range"):
        env.step(np.array([0, 1, 8]))


def test_render_env_draws_one_sub_env() -> None:
    env = LandmarkSelectionVectorEnv(2, render_mode="rgb_array", **SHORT)
    env.reset(seed=0)
    env.step(np.array([0, 1]))
    frame = env.render_env(1)
    assert frame is not None and frame.ndim == 3 and frame.dtype == np.uint8
    assert len(env.render()) == 2  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="render_mode"):
        LandmarkSelectionVectorEnv(2, render_mode="human")
    env.close()


def test_static_cache_is_read_only_and_shared() -> None:
    cfg = LandmarkConfig(n_landmarks=8, horizon=5)
    a, b = scenario_static(cfg), scenario_static(LandmarkConfig(n_landmarks=8, horizon=5))
    assert a is b
    for arr in (a.states, a.dcm, a.P0, a.R_landmark, a.init_std):
        assert not arr.flags.writeable
