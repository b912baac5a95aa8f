"""Batched previewed fusion gains of the CL vector env equal the single env's ``preview_gain``."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv  # noqa: F401
from selenv.agents import make
from selenv.families.cooperative.vector import CLSchedulingVectorEnv, CLSubEnv
from selenv.families.cooperative.view import VIEWS
from selenv.learned.rl.views import view_for

ENV_ID = "selenv/CLScheduling-v1"
RTOL, ATOL = 1e-9, 1e-12


def _single_previews(env: gym.Env[Any, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(P,) the single env's ``preview_gain`` of every open pair (0 when masked), its mask."""
    base: Any = env.unwrapped
    mask = np.asarray(base.action_masks(), dtype=np.bool_)
    out = np.zeros(len(mask) - 1)
    for p in np.flatnonzero(mask[:-1]):
        out[p] = base.preview_gain(int(p))
    return out, mask


def _greedy_from(gains: np.ndarray) -> int:
    """The greedy agent's rule on a row of previews: the first best pair if it helps, else stop."""
    p = int(np.argmax(gains))
    return p if gains[p] > 0.0 else gains.size


def _lockstep(seeds: list[int], steps: int, **kwargs: Any) -> dict[str, int]:
    """Drive the vector env and single envs with the greedy agent; compare every state's previews.

    Returns counts: ``rows`` (open pairs compared), ``positive`` (previews > 0),
    ``positive_reset`` (those of sub-envs after their first autoreset), ``autoresets``.
    """
    B = len(seeds)
    venv = gym.make_vec(ENV_ID, num_envs=B, **kwargs)
    assert isinstance(venv, CLSchedulingVectorEnv)
    singles = [gym.make(ENV_ID, **kwargs) for _ in range(B)]
    greedy = [make("greedy", ENV_ID) for _ in range(B)]
    venv.reset(seed=seeds)
    for env, agent, s in zip(singles, greedy, seeds, strict=True):
        env.reset(seed=s)
        agent.reset(env)
    counts = {"rows": 0, "positive": 0, "positive_reset": 0, "autoresets": 0}
    was_reset = np.zeros(B, dtype=bool)
    pending = np.zeros(B, dtype=bool)  # ended at the last step: the next one resets them
    for t in range(steps):
        gains = venv.preview_gains()
        assert gains.shape == (B, venv.n_pairs) and gains.dtype == np.float64
        masks = venv.action_masks()
        actions = np.zeros(B, dtype=np.int64)
        for b, (env, agent) in enumerate(zip(singles, greedy, strict=True)):
            ref, mask = _single_previews(env)
            np.testing.assert_array_equal(masks[b], mask, err_msg=f"step {t}, sub-env {b}: mask")
            np.testing.assert_allclose(
                gains[b], ref, rtol=RTOL, atol=ATOL, err_msg=f"step {t}, sub-env {b}"
            )
            assert np.all(gains[b][~mask[:-1]] == 0.0)  # masked pairs: exactly 0
            counts["rows"] += int(mask[:-1].sum())
            counts["positive"] += int((ref > 0.0).sum())
            counts["positive_reset"] += int((ref > 0.0).sum()) if was_reset[b] else 0
            if pending[b]:
                actions[b] = venv.n_pairs  # ignored by the vector env (autoreset)
                continue
            act = agent.act(None, {"action_mask": mask})
            assert _greedy_from(gains[b]) == act, f"step {t}, sub-env {b}: greedy decision"
            actions[b] = act
        _, _, term, trunc, _ = venv.step(actions)
        for b, env in enumerate(singles):
            if pending[b]:
                env.reset()  # the vector env resets it with its own generator
                greedy[b].reset(env)
                counts["autoresets"] += 1
                was_reset[b] = True
            else:
                _, _, te, tr, _ = env.step(int(actions[b]))
                assert (te, tr) == (bool(term[b]), bool(trunc[b]))
        pending = term | trunc
    venv.close()
    return counts


@pytest.mark.parametrize("seeds", [[0, 1, 2], [7, 42]])
def test_default_preset_dmv_previews_over_whole_episodes(seeds: list[int]) -> None:
    counts = _lockstep(seeds, steps=75)  # horizon 60, budget 1: an episode, then autoresets
    assert counts["autoresets"] == len(seeds)
    assert counts["positive"] > 100  # not all 0 (they are from the first beacon fix, step 10)
    assert counts["positive_reset"] > 0


@pytest.mark.parametrize(
    "kwargs",
    [
        {"n_agents": 3, "horizon": 24, "fusion": "dmv"},
        {"n_agents": 3, "horizon": 12, "fusion": "ci"},
        {"n_agents": 2, "horizon": 21, "fusion": "ci", "budget": 2, "objective": "logdet"},
        {"preset": "dense", "horizon": 12},  # budget 2, log det: processed pairs masked
        {"n_agents": 3, "horizon": 12, "bearing_sigma_deg": 2.0, "objective": "logdet"},
        {"preset": "paper", "horizon": 12, "objective": "trace"},  # pairs every fifth step
    ],
)
def test_small_team_and_ci_previews_across_autoresets(kwargs: dict[str, Any]) -> None:
    # the first beacon fix (step 10) breaks the cold start's symmetry: gains appear after it
    steps = 2 * kwargs["horizon"] * kwargs.get("budget", 1) + 2
    counts = _lockstep([3, 11, 5], steps=steps, **kwargs)
    assert counts["autoresets"] >= 3  # greedy stops early: budget-2 episodes may be shorter
    assert counts["positive"] > 0 and counts["positive_reset"] > 0


def test_default_preset_ci_previews() -> None:
    counts = _lockstep([4, 9], steps=13, fusion="ci", horizon=11)
    assert counts["autoresets"] == 2 and counts["positive"] > 0


def test_the_comparison_catches_a_wrong_fusion(monkeypatch: pytest.MonkeyPatch) -> None:
    """A vector env previewing with the naive EKF instead of DMV is caught."""
    orig = CLSchedulingVectorEnv._preview_rows

    def naive(self: CLSchedulingVectorEnv, b: np.ndarray, p: np.ndarray) -> np.ndarray:
        fusion = self.fusion
        self.fusion = "naive"
        try:
            return orig(self, b, p)
        finally:
            self.fusion = fusion

    monkeypatch.setattr(CLSchedulingVectorEnv, "_preview_rows", naive)
    with pytest.raises(AssertionError):
        _lockstep([0, 1], steps=10, horizon=8)


def test_previews_are_cached_per_state(monkeypatch: pytest.MonkeyPatch) -> None:
    venv = CLSchedulingVectorEnv(4, preset="dense", horizon=20)  # budget 2
    with pytest.raises(RuntimeError, match="reset"):
        venv.preview_gains()
    calls: list[int] = []
    orig = CLSchedulingVectorEnv._preview_rows

    def counted(self: CLSchedulingVectorEnv, b: np.ndarray, p: np.ndarray) -> np.ndarray:
        calls.append(b.size)
        return orig(self, b, p)

    monkeypatch.setattr(CLSchedulingVectorEnv, "_preview_rows", counted)
    venv.reset(seed=0)
    first = venv.preview_gains()
    assert venv.preview_gains() is first and len(calls) == 1  # no second computation
    assert calls[0] == int(venv.action_masks()[:, :-1].sum())  # one batched call, every open row
    assert not first.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        first[0, 0] = 1.0
    seen = [first]
    for _ in range(24):  # 12 filter steps, past the first beacon fix (step 10): gains > 0
        masks = venv.action_masks()
        venv.step(np.argmax(masks, axis=1))
        now = venv.preview_gains()
        assert all(now is not old for old in seen) and venv.preview_gains() is now
        seen.append(now)
    assert len(calls) == 25  # one computation per state
    assert not all(np.array_equal(seen[0], s) for s in seen[1:])  # the state did change
    venv.reset(seed=1)
    assert venv.preview_gains() is not seen[-1] and len(calls) == 26
    seen.append(venv.preview_gains())
    venv.reset(options={"reset_mask": np.array([True, False, False, False])})
    assert venv.preview_gains() is not seen[-1] and len(calls) == 27


def _row(obs: dict[str, np.ndarray], b: int) -> dict[str, np.ndarray]:
    return {key: value[b] for key, value in obs.items()}


def _compare_views(got: dict[str, np.ndarray], want: dict[str, np.ndarray], where: str) -> None:
    assert set(got) == set(want), where
    for key in want:
        x, y = np.asarray(got[key]), np.asarray(want[key])
        assert x.shape == y.shape and x.dtype == y.dtype, f"{where}[{key}]"
        if x.dtype.kind == "f":
            np.testing.assert_allclose(x, y, rtol=3e-7, atol=1e-6, err_msg=f"{where}[{key}]")
        else:
            np.testing.assert_array_equal(x, y, err_msg=f"{where}[{key}]")


@pytest.mark.parametrize("name", ["cl_pairs_fused", "cl_pairs_fused_top3"])
@pytest.mark.parametrize("kwargs", [{"horizon": 14}, {"preset": "dense", "horizon": 14}])
def test_fused_views_on_a_sub_env_equal_the_single_envs(name: str, kwargs: dict[str, Any]) -> None:
    seeds = [2, 8, 13]
    venv = CLSchedulingVectorEnv(len(seeds), **kwargs)
    singles = [gym.make(ENV_ID, **kwargs) for _ in seeds]
    obs, _ = venv.reset(seed=seeds)
    single_obs = [env.reset(seed=s)[0] for env, s in zip(singles, seeds, strict=True)]
    proxies = [venv.sub_env(b) for b in range(len(seeds))]
    views = [VIEWS[name](proxy) for proxy in proxies]  # built once, read the live state
    refs = [view_for(ENV_ID, env, name) for env in singles]
    assert all(v.name == name for v in views)
    rng = np.random.default_rng(0)
    kept = positive = 0
    for t in range(2 * kwargs["horizon"]):  # one episode (dense: budget 2)
        actions = []
        for b, (view, ref) in enumerate(zip(views, refs, strict=True)):
            got, want = view(_row(obs, b)), ref(single_obs[b])
            _compare_views(got, want, f"{name} step {t} sub-env {b}")
            kept += int(np.sum(got["action_mask"][:-1]))
            positive += int(np.sum(got["gain"] > 0.0))
            actions.append(int(rng.choice(np.flatnonzero(got["action_mask"]))))
        obs, _, term, trunc, _ = venv.step(np.array(actions))
        single_obs = [env.step(a)[0] for env, a in zip(singles, actions, strict=True)]
        if (term | trunc).any():  # random stops end an episode early: compare the first ones
            break
    assert kept > 0 and positive > 0


def test_sub_env_proxy_matches_the_single_env_on_masked_pairs() -> None:
    kwargs: dict[str, Any] = {"horizon": 20, "budget": 2}  # greedy's first pair is masked next
    venv = CLSchedulingVectorEnv(2, **kwargs)
    singles: list[Any] = [gym.make(ENV_ID, **kwargs) for _ in range(2)]
    venv.reset(seed=[5, 6])
    for env, s in zip(singles, [5, 6], strict=True):
        env.reset(seed=s)
    proxy = venv.sub_env(1)
    assert isinstance(proxy, CLSubEnv) and proxy.unwrapped is proxy
    assert proxy.pairs == singles[1].unwrapped.pairs and proxy.n_pairs == venv.n_pairs
    masked_seen = masked_nonzero = 0
    greedy = [make("greedy", ENV_ID) for _ in singles]
    for agent, env in zip(greedy, singles, strict=True):
        agent.reset(env)
    for _ in range(30):  # the first beacon fix (step 10) gives gains > 0
        acts = zip(greedy, singles, strict=True)
        actions = [a.act(None, {"action_mask": e.unwrapped.action_masks()}) for a, e in acts]
        venv.step(np.array(actions))
        for env, a in zip(singles, actions, strict=True):
            env.step(a)
        base = singles[1].unwrapped
        np.testing.assert_array_equal(proxy.action_masks(), base.action_masks())
        for p in range(venv.n_pairs):  # open or masked: the single env previews every pair
            want = base.preview_gain(p)
            assert proxy.preview_gain(p) == pytest.approx(want, rel=RTOL, abs=ATOL)
            masked = not proxy.action_masks()[p]
            masked_seen += masked
            masked_nonzero += masked and want != 0.0
    assert masked_seen > 0 and masked_nonzero > 0  # not the array's 0
    mask = proxy.action_masks()
    mask[:] = False  # a copy: the env's mask is untouched
    assert venv.action_masks()[1].any()
    with pytest.raises(AttributeError, match="read-only"):
        proxy.b = 0
    with pytest.raises(AttributeError):
        proxy.pairs = ()  # type: ignore[misc]
    for bad_p, exc in [(venv.n_pairs, ValueError), (-1, ValueError), (1.0, TypeError)]:
        with pytest.raises(exc, match="p \\(the pair index\\)"):
            proxy.preview_gain(bad_p)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("b", "exc"),
    [(-1, ValueError), (3, ValueError), (1.0, TypeError), (True, TypeError), ("0", TypeError)],
)
def test_bad_sub_env_index_is_named(b: Any, exc: type[Exception]) -> None:
    venv = CLSchedulingVectorEnv(3, horizon=3)
    with pytest.raises(exc, match="b \\(the sub-env index\\)"):
        venv.sub_env(b)
    assert venv.sub_env(np.int64(2)).b == 2  # type: ignore[arg-type]
