"""The native vector env of selenv/CLScheduling-v1 replays the single env sub-env by sub-env."""

from __future__ import annotations

import warnings
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401
from selenv.agents import make
from selenv.envs.actions import MASKED
from selenv.envs.vector_check import check_vector_equivalence
from selenv.families.cooperative import batched
from selenv.families.cooperative import scenario as sc
from selenv.families.cooperative.vector import CLSchedulingVectorEnv

ENV_ID = "selenv/CLScheduling-v1"


def _old_track(kind: str, n_steps: int, dt: float, size: float, speed: float, phase: float) -> Any:
    """The former ``_track``: the polyline rebuilt with one ``linspace`` per segment."""
    t = np.linspace(0.0, 2 * np.pi, 4001)
    if kind == "circle":
        pts = size * np.stack([np.cos(t), np.sin(t)], -1)
    elif kind == "lemniscate":
        pts = size * np.stack([np.sin(t), np.sin(t) * np.cos(t)], -1)
    else:
        w, h, r = size, 0.6 * size, 0.3 * size
        corners = [
            (w - r, h - r, 0.0),
            (-(w - r), h - r, 0.5),
            (-(w - r), -(h - r), 1.0),
            (w - r, -(h - r), 1.5),
        ]
        segs = []
        for cx, cy, a0 in corners:
            ang = np.pi * (a0 + np.linspace(0.0, 0.5, 200))
            segs.append(np.stack([cx + r * np.cos(ang), cy + r * np.sin(ang)], -1))
        pts = np.concatenate([*segs, segs[0][:1]])
        pts = np.concatenate(
            [np.linspace(pts[i], pts[i + 1], 20, endpoint=False) for i in range(len(pts) - 1)]
        )
        pts = np.concatenate([pts, pts[:1]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    length = arc[-1]
    s = (phase / (2 * np.pi) * length + speed * dt * np.arange(n_steps + 2)) % length
    return np.stack([np.interp(s, arc, pts[:, 0]), np.interp(s, arc, pts[:, 1])], -1)


@pytest.mark.parametrize("kind", sc.TRACKS)
@pytest.mark.parametrize("size", [0.5, 6.0, 37.3])
def test_cached_track_equals_the_former_polyline(kind: str, size: float) -> None:
    for phase in (0.0, 1.1, 2 * np.pi * 5 / 6):
        new = sc._track(kind, 250, 0.1, size, 1.3, phase)
        np.testing.assert_allclose(new, _old_track(kind, 250, 0.1, size, 1.3, phase), rtol=1e-12)
        assert not new.flags.writeable
        assert sc._track(kind, 250, 0.1, size, 1.3, phase) is new  # cached


def test_truth_is_cached_and_read_only() -> None:
    cfg = sc.CLConfig(horizon=20)
    a = sc.make_cl_problem(cfg, np.random.default_rng(0))
    b = sc.make_cl_problem(sc.CLConfig(horizon=20, range_sigma=0.3), np.random.default_rng(1))
    assert a.states is b.states  # the truth does not depend on the noise
    assert not a.states.flags.writeable and not a.inputs.flags.writeable


def test_make_vec_returns_the_native_class() -> None:
    env = gym.make_vec(ENV_ID, num_envs=8)
    assert isinstance(env, CLSchedulingVectorEnv)
    assert env.num_envs == 8 and env.proto.preset == "benchmark"
    with pytest.warns(DeprecationWarning):
        old = gym.make_vec("selenv/CLScheduling-v0", num_envs=2)
    assert isinstance(old, CLSchedulingVectorEnv)
    assert old.proto.preset == "dense"  # release 0.1's configuration
    assert env.action_masks().shape == (8, env.n_pairs + 1)
    env.close()
    old.close()


@pytest.mark.parametrize("seeds", [[0, 1, 2], [7, 100, 3, 42]])
def test_random_masked_actions_replay_the_single_env(seeds: list[int]) -> None:
    counts = check_vector_equivalence(ENV_ID, num_envs=len(seeds), seeds=seeds, steps=14, horizon=4)
    assert counts["autoresets"] >= 2 * len(seeds)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"preset": "paper", "horizon": 6, "objective": "trace"},
        {"preset": "dense", "horizon": 3},
        {"n_agents": 3, "horizon": 3, "fusion": "pecmv", "objective": "trace"},
        {"n_agents": 3, "horizon": 3, "fusion": "ci", "model": "unicycle", "topology": "chain"},
        {"n_agents": 3, "horizon": 4, "bearing_sigma_deg": 2.0, "objective": "logdet"},
        {"n_agents": 3, "horizon": 4, "fusion": "naive", "budget": 2},
    ],
)
def test_other_keywords_replay_the_single_env(kwargs: dict[str, Any]) -> None:
    steps = 2 * kwargs["horizon"] * kwargs.get("budget", 1) + 4
    check_vector_equivalence(ENV_ID, num_envs=3, seeds=[5, 6, 7], steps=steps, **kwargs)


def test_greedy_heuristic_replays_the_single_env() -> None:
    agents: dict[int, Any] = {}

    def greedy(b: int, env: gym.Env[Any, Any], mask: np.ndarray, rng: np.random.Generator) -> Any:
        if b not in agents:
            agents[b] = make("greedy", ENV_ID)
            agents[b].reset(env)
        return agents[b].act(None, {"action_mask": mask})

    counts = check_vector_equivalence(ENV_ID, num_envs=3, steps=14, picker=greedy, horizon=4)
    assert counts["autoresets"] >= 6


def _sometimes_invalid(
    b: int, env: gym.Env[Any, Any], mask: np.ndarray, rng: np.random.Generator
) -> int:
    bad = np.flatnonzero(~np.asarray(mask, dtype=bool))
    if bad.size and rng.random() < 0.4:
        return int(rng.choice(bad))
    return int(rng.choice(np.flatnonzero(mask)))


@pytest.mark.parametrize("mode", ["noop", "terminate"])
def test_invalid_actions_replay_the_single_env(mode: str) -> None:
    check_vector_equivalence(
        ENV_ID,
        num_envs=3,
        steps=16,
        picker=_sometimes_invalid,
        horizon=4,
        budget=2,
        invalid_action=mode,
        invalid_action_penalty=-0.5,
    )


def test_invalid_action_modes_per_sub_env() -> None:
    for mode in ("noop", "terminate", "raise"):
        env = CLSchedulingVectorEnv(3, horizon=5, budget=2, invalid_action=mode)
        env.reset(seed=0)
        acts = np.array([0, 0, env.n_pairs])
        env.step(acts)  # sub-envs 0 and 1 process pair 0 (budget 2: the step goes on)
        again = np.array([env.n_pairs, 0, env.n_pairs])  # sub-env 1 repeats pair 0: masked
        if mode == "raise":
            k = env.k.copy()
            with pytest.raises(ValueError, match="sub-env 1: action 0 is invalid"):
                env.step(again)
            np.testing.assert_array_equal(env.k, k)  # nothing stepped
            continue
        _, rew, term, _, info = env.step(again)
        assert info["invalid_action"].tolist() == [False, True, False]
        assert info["invalid_code"].tolist() == [0, MASKED, 0]
        assert term.tolist() == [False, mode == "terminate", False]
        if mode == "terminate":
            assert rew[1] == 0.0
            obs, rew, term, _, info = env.step(np.array([env.n_pairs] * 3))  # autoreset of 1
            assert rew[1] == 0.0 and info["k"][1] == 1 and not info["invalid_action"][1]


def test_reset_mask_resets_only_the_masked_sub_envs() -> None:
    venv = CLSchedulingVectorEnv(3, horizon=6)
    singles: list[Any] = [gym.make(ENV_ID, horizon=6) for _ in range(3)]
    venv.reset(seed=[1, 2, 3])
    for env, s in zip(singles, [1, 2, 3], strict=True):
        env.reset(seed=s)
    for _ in range(2):
        acts = [int(np.flatnonzero(env.unwrapped.action_masks())[0]) for env in singles]
        venv.step(np.array(acts))
        for env, a in zip(singles, acts, strict=True):
            env.step(a)
    mask = np.array([True, False, True])
    obs, info = venv.reset(options={"reset_mask": mask})
    assert info["_k"].tolist() == [True, False, True]
    for b, env in enumerate(singles):
        o = env.reset()[0] if mask[b] else env.unwrapped._obs()
        for key, value in o.items():
            np.testing.assert_allclose(obs[key][b], value, rtol=3e-7, atol=1e-6, err_msg=key)
    assert venv.k.tolist() == [1, 3, 1]


def test_same_seed_gives_identical_arrays_and_none_continues() -> None:
    def run(seed: Any) -> list[np.ndarray]:
        env = CLSchedulingVectorEnv(2, horizon=3)
        obs, _ = env.reset(seed=seed)
        out = [obs["pair_gain"], env.x.copy()]
        for _ in range(5):
            m = env.action_masks()
            obs, rew, *_ = env.step(np.argmax(m, axis=1))
            out += [obs["logdet"], rew, env.P.copy()]
        return out

    for a, b in zip(run(11), run(11), strict=True):
        np.testing.assert_array_equal(a, b)
    env = CLSchedulingVectorEnv(2, horizon=3)
    env.reset(seed=None)
    first = env.x.copy()
    env.step(np.array([env.n_pairs] * 2))
    env.reset(seed=None)  # the generators continue: new realisations
    assert not np.array_equal(first, env.x)
    assert np.isfinite(env.P).all()


@pytest.mark.parametrize(
    ("num_envs", "exc"), [(0, ValueError), (-3, ValueError), (2.5, TypeError), (True, TypeError)]
)
def test_bad_num_envs_is_named(num_envs: Any, exc: type[Exception]) -> None:
    with pytest.raises(exc, match="num_envs"):
        CLSchedulingVectorEnv(num_envs)


def test_bad_actions_and_keywords_raise() -> None:
    env = CLSchedulingVectorEnv(3, horizon=4)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(4, dtype=int))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros((3, 2), dtype=int))
    with pytest.raises(TypeError, match="actions"):
        env.step(np.zeros(3))
    with pytest.raises(ValueError, match="sub-env 2"):
        env.step(np.array([0, 0, env.n_pairs + 1]))
    with pytest.raises(TypeError, match="bogus"):
        CLSchedulingVectorEnv(2, bogus=1)
    with pytest.raises(ValueError, match="fusion"):
        CLSchedulingVectorEnv(2, fusion="nope")
    with pytest.raises(ValueError, match="render_mode"):
        CLSchedulingVectorEnv(2, render_mode="human")


def test_check_fails_on_a_wrong_fusion(monkeypatch: pytest.MonkeyPatch) -> None:
    """The equivalence check can fail: a vector env that skips the relative update differs."""
    monkeypatch.setattr(CLSchedulingVectorEnv, "_relative_updates", lambda self, b, p: None)
    with pytest.raises(AssertionError):
        check_vector_equivalence(ENV_ID, num_envs=2, steps=6, horizon=8, fusion="naive")


def test_batched_fusion_matches_the_single_rows() -> None:
    rng = np.random.default_rng(3)
    n, K = 9, 12
    M = rng.normal(size=(K, n, n))
    P_i = M @ np.swapaxes(M, 1, 2) + np.eye(n)
    N = rng.normal(size=(K, n, n))
    P_j = N @ np.swapaxes(N, 1, 2) + np.eye(n)
    H_i = np.zeros((K, 1, n))
    H_i[:, 0, :3] = rng.normal(size=(K, 3))
    H_j = -H_i
    x_i, res, R = rng.normal(size=(K, n)), rng.normal(size=(K, 1)), np.array([[0.01]])
    x, P = batched.fuse("dmv", x_i, P_i, P_j, H_i, H_j, R, res)
    from selenv.core.fusion import dmv_update

    for k in range(K):
        ref = dmv_update(P_i[k], P_j[k], H_i[k], H_j[k], R, x_i=x_i[k], residual=res[k])
        np.testing.assert_allclose(P[k], ref.P, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(x[k], np.asarray(ref.x), rtol=1e-9, atol=1e-12)


def test_render_env_draws_a_sub_env() -> None:
    env = CLSchedulingVectorEnv(2, horizon=3, render_mode="rgb_array")
    env.reset(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        frame = env.render_env(1)
    assert frame.dtype == np.uint8 and frame.ndim == 3
    env.close()


def test_dmv_updates_replay_the_single_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """Long enough for DMV to update (``w* < 1``) in both envs, not only to skip."""
    updated: list[int] = []
    dmv = batched.dmv_fuse

    def spy(*args: Any) -> Any:
        x, P = dmv(*args)
        updated.append(int((P != args[1]).any(axis=(1, 2)).sum()))
        return x, P

    monkeypatch.setattr(batched, "dmv_fuse", spy)
    counts = check_vector_equivalence(ENV_ID, num_envs=2, seeds=[0, 1], steps=64, horizon=30)
    assert counts["autoresets"] >= 2
    assert sum(updated) >= 4
