"""selenv/FIMSelection-v1's native vector env replays the single env, sub-env by sub-env."""

from __future__ import annotations

import warnings
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv
from selenv.envs.actions import MASKED
from selenv.envs.vector_check import check_vector_equivalence, random_masked_action
from selenv.families.fim.env import FIMSelectionEnv
from selenv.families.fim.scenario import config_from, make_problem, make_problems
from selenv.families.fim.vector import FIMSelectionVectorEnv

ENV_ID = "selenv/FIMSelection-v1"
SMALL: dict[str, Any] = {"n_candidates": 12, "budget": 4}


def _sub(tree: dict[str, np.ndarray], b: int) -> dict[str, np.ndarray]:
    return {key: val[b] for key, val in tree.items()}


def _assert_same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert set(a) == set(b)
    for key in a:
        assert a[key].dtype == b[key].dtype, key
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_make_vec_returns_the_native_class() -> None:
    venv = gym.make_vec(ENV_ID, num_envs=8)
    assert type(venv) is FIMSelectionVectorEnv and venv.num_envs == 8
    assert venv.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    assert venv.single_observation_space == gym.make(ENV_ID).observation_space
    obs, _ = venv.reset(seed=0)
    assert venv.observation_space.contains(obs)
    assert venv.action_masks().shape == (8, venv.n) and venv.action_masks().dtype == bool
    with pytest.warns(DeprecationWarning):
        v0 = gym.make_vec("selenv/FIMSelection-v0", num_envs=2, preset="example2")
    assert type(v0) is FIMSelectionVectorEnv
    assert v0.config.preset == "example2_moving"  # v0's preset names are mapped
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # v1 does not warn
        gym.make_vec(ENV_ID, num_envs=2).close()


@pytest.mark.parametrize("seeds", [[0, 1, 2, 3], [11, 7, 123456, 2**31 - 1]])
def test_random_masked_episodes_match_the_single_env(seeds: list[int]) -> None:
    counts = check_vector_equivalence(ENV_ID, num_envs=4, seeds=seeds, steps=35)
    assert counts["autoresets"] >= 2 * 4  # every sub-env autoreset at least twice


@pytest.mark.parametrize(
    "kwargs",
    [
        {"preset": "example3_moving", "n_candidates": 10, "budget": 5},
        {"preset": "example1", "n_candidates": 15, "budget": 3, "randomize": False},
        {"objective": "trace", **SMALL},
        {"objective": "max_eig", **SMALL},
        {"objective": "det", "sensors": ["toa", "doppler"], **SMALL},
        {"n_candidates": 2, "budget": 3, "sensors": ["camera", "toa", "doppler"]},
    ],
)
def test_non_default_keywords_match_the_single_env(kwargs: dict[str, Any]) -> None:
    steps = 3 * (kwargs["budget"] + 1)
    counts = check_vector_equivalence(ENV_ID, num_envs=3, seeds=[5, 6, 7], steps=steps, **kwargs)
    assert counts["autoresets"] >= 2 * 3


def _greedy_picker() -> Any:
    agents: dict[int, Any] = {}

    def pick(b: int, env: gym.Env[Any, Any], mask: np.ndarray, rng: np.random.Generator) -> int:
        base: Any = env.unwrapped
        if base.budget_left == 0:  # the episode ended: this step autoresets, the action unused
            return 0
        if base.budget_left == base.budget:  # a new episode: a fresh agent
            agents[b] = selenv.agents.make("greedy", ENV_ID)
            agents[b].reset(env, seed=b)
        return int(agents[b].act(None, {"action_mask": mask}))

    return pick


@pytest.mark.parametrize("objective", ["logdet", "trace"])
def test_greedy_episodes_match_the_single_env(objective: str) -> None:
    counts = check_vector_equivalence(
        ENV_ID, num_envs=3, seeds=[3, 1, 4], steps=15, picker=_greedy_picker(),
        objective=objective, **SMALL,
    )  # fmt: skip
    assert counts["autoresets"] >= 2 * 3


def _sometimes_masked(
    b: int, env: gym.Env[Any, Any], mask: np.ndarray, rng: np.random.Generator
) -> int:
    if not mask.all() and rng.random() < 0.4:
        return int(rng.choice(np.flatnonzero(~mask)))  # an already selected candidate
    return int(random_masked_action(b, env, mask, rng))


@pytest.mark.parametrize("mode", ["noop", "terminate"])
def test_invalid_actions_match_the_single_env(mode: str) -> None:
    kwargs = {"invalid_action": mode, "invalid_action_penalty": -0.5, **SMALL}
    counts = check_vector_equivalence(
        ENV_ID, num_envs=4, steps=25, picker=_sometimes_masked, **kwargs
    )
    assert counts["autoresets"] >= 2 * 4


def test_invalid_noop_reports_the_code_where_invalid() -> None:
    venv = FIMSelectionVectorEnv(3, **SMALL)
    venv.reset(seed=0)
    venv.step(np.array([1, 2, 3]))
    _, rew, term, _, info = venv.step(np.array([1, 5, 3]))  # sub-envs 0 and 2 repeat a pick
    np.testing.assert_array_equal(info["invalid_action"], [True, False, True])
    np.testing.assert_array_equal(info["invalid_code"], [MASKED, 0, MASKED])
    assert rew[0] == 0.0 and rew[1] > 0.0 and not term.any()
    np.testing.assert_array_equal(info["n_selected"], [1, 2, 1])
    np.testing.assert_array_equal(venv.budget_left, [2, 2, 2])


def test_invalid_raise_names_the_sub_env_and_changes_nothing() -> None:
    venv = FIMSelectionVectorEnv(3, invalid_action="raise", **SMALL)
    venv.reset(seed=0)
    obs, *_ = venv.step(np.array([0, 1, 2]))
    with pytest.raises(ValueError, match=r"sub-env 2: action 2 is invalid: masked"):
        venv.step(np.array([3, 4, 2]))
    _assert_same(venv._observe(), obs)  # no sub-env was stepped
    np.testing.assert_array_equal(venv.budget_left, [3, 3, 3])


def test_reset_mask_resets_only_the_masked_sub_envs() -> None:
    venv = FIMSelectionVectorEnv(4, **SMALL)
    venv.reset(seed=10)
    obs, *_ = venv.step(np.array([0, 1, 2, 3]))
    mask = np.array([False, True, False, True])
    new, info = venv.reset(seed=[None, 21, None, 23], options={"reset_mask": mask})
    np.testing.assert_array_equal(info["_objective"], mask)
    for b in (0, 2):  # untouched
        _assert_same(_sub(new, b), _sub(obs, b))
    for b, seed in ((1, 21), (3, 23)):  # replay gymnasium.make(...).reset(seed=...)
        single, _ = gym.make(ENV_ID, **SMALL).reset(seed=seed)
        for key in single:
            np.testing.assert_allclose(new[key][b], single[key], rtol=3e-7, atol=1e-6)
    np.testing.assert_array_equal(venv.budget_left, [3, 4, 3, 4])


def _rollout(venv: FIMSelectionVectorEnv, seed: Any, steps: int) -> list[Any]:
    out: list[Any] = [venv.reset(seed=seed)[0]]
    rng = np.random.default_rng(0)
    for _ in range(steps):
        masks = venv.action_masks()
        acts = np.array([rng.choice(np.flatnonzero(m)) for m in masks])
        obs, rew, term, trunc, info = venv.step(acts)
        out.append((obs, rew, term, info["objective"]))
    return out


def test_same_seed_twice_gives_identical_arrays() -> None:
    a = _rollout(FIMSelectionVectorEnv(3, **SMALL), 5, 12)
    b = _rollout(FIMSelectionVectorEnv(3, **SMALL), 5, 12)
    _assert_same(a[0], b[0])
    for (oa, ra, ta, fa), (ob, rb, tb, fb) in zip(a[1:], b[1:], strict=True):
        _assert_same(oa, ob)
        for x, y in ((ra, rb), (ta, tb), (fa, fb)):
            np.testing.assert_array_equal(x, y)
    c = _rollout(FIMSelectionVectorEnv(3, **SMALL), 6, 1)
    assert not np.array_equal(a[0]["whitened"], c[0]["whitened"])


def test_seed_none_then_continued() -> None:
    venv = FIMSelectionVectorEnv(2, **SMALL)
    obs, _ = venv.reset()  # fresh entropy per sub-env
    assert not np.array_equal(obs["whitened"][0], obs["whitened"][1])
    again, _ = venv.reset()  # continues each sub-env's generator: new problems
    assert not np.array_equal(obs["whitened"], again["whitened"])
    for _ in range(2 * (SMALL["budget"] + 1)):  # autoresets keep working
        acts = np.array([np.flatnonzero(m)[0] for m in venv.action_masks()])
        obs, *_ = venv.step(acts)
    assert venv.observation_space.contains(obs)


@pytest.mark.parametrize(("bad", "err"), [(0, ValueError), (1.5, TypeError), (True, TypeError)])
def test_bad_num_envs_is_named(bad: Any, err: type[Exception]) -> None:
    with pytest.raises(err, match="num_envs"):
        FIMSelectionVectorEnv(bad)
    with pytest.raises(err, match="num_envs"):
        gym.make_vec(ENV_ID, num_envs=bad)


def test_keywords_are_validated_as_the_single_env() -> None:
    for kwargs in ({"budget": 0}, {"objective": "nope"}, {"invalid_action": "skip"},
                   {"sensors": "camera"}, {"n_candidates": 2.5}, {"render_mode": 5}):  # fmt: skip
        with pytest.raises((TypeError, ValueError)) as single:
            FIMSelectionEnv(**kwargs)
        with pytest.raises(type(single.value)) as vector:
            FIMSelectionVectorEnv(2, **kwargs)
        if "render_mode" not in kwargs:
            assert str(vector.value) == str(single.value)
    with pytest.raises(ValueError, match="render_mode"):
        FIMSelectionVectorEnv(2, render_mode="human")  # frames only: no windows
    with pytest.raises(TypeError):
        FIMSelectionVectorEnv(2, unknown=1)  # type: ignore[call-arg]


def test_bad_actions_are_refused() -> None:
    venv = FIMSelectionVectorEnv(3, **SMALL)
    venv.reset(seed=0)
    for bad in (np.array([0, 1]), np.array([[0, 1, 2]]), np.zeros((3, 2), np.int64), 1):
        with pytest.raises(ValueError, match="shape"):
            venv.step(bad)
    with pytest.raises(TypeError, match="integers"):
        venv.step(np.array([0.0, 1.0, 2.0]))
    with pytest.raises(TypeError, match="integers"):
        venv.step(np.array([True, False, True]))
    with pytest.raises(ValueError, match=r"sub-env 1"):
        venv.step(np.array([0, venv.n, 2]))
    venv.step(np.array([[0], [1], [2]]))  # (B, 1) is accepted
    np.testing.assert_array_equal(venv.budget_left, [3, 3, 3])


def test_render_env_draws_the_sub_env() -> None:
    venv = FIMSelectionVectorEnv(2, render_mode="rgb_array", **SMALL)
    venv.reset(seed=0)
    venv.step(np.array([0, 1]))
    frames = venv.render()
    assert frames is not None and len(frames) == 2
    assert frames[0].ndim == 3 and frames[0].dtype == np.uint8
    single = gym.make(ENV_ID, render_mode="rgb_array", **SMALL)
    single.reset(seed=1)
    single.step(1)
    np.testing.assert_array_equal(frames[1], single.render())
    venv.close()


def test_sub_env_views_match_the_single_env() -> None:
    venv = FIMSelectionVectorEnv(2, **SMALL)
    venv.reset(seed=3)
    venv.step(np.array([4, 5]))
    single: Any = gym.make(ENV_ID, **SMALL).unwrapped
    single.reset(seed=4)
    single.step(5)
    np.testing.assert_array_equal(venv.problem(1).G, single.problem.G)
    assert venv.state(1).order == single.state.order == [5]
    np.testing.assert_allclose(venv.state(1).information, single.state.information, rtol=1e-12)
    with pytest.raises(ValueError, match="i must lie"):
        venv.state(2)


def test_batched_problems_are_the_single_problems_and_read_only() -> None:
    cfg = config_from("example3_moving", n_candidates=20, randomize=True)
    batch = make_problems(cfg, [np.random.default_rng(s) for s in (4, 5, 6)])
    for j, seed in enumerate((4, 5, 6)):
        one = make_problem(cfg, np.random.default_rng(seed))
        for name in ("G", "H", "theta_true", "times", "positions", "camera_rotation"):
            np.testing.assert_array_equal(getattr(batch.problem(j), name), getattr(one, name))
    for arr in (batch.G, batch.times, batch.constants.Q0, batch.constants.R):
        assert not arr.flags.writeable
    fixed = make_problems(config_from("example1", n_candidates=9), [np.random.default_rng(0)])
    assert fixed.constants.fixed is not None and not fixed.G.flags.writeable
