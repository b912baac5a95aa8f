"""Versioned ids: ``-v0`` replays release 0.1's episodes, ``-v1`` carries the current defaults.

``tests/data/episodes_v0.json`` was recorded by ``scripts/record_version_episodes.py`` with the
code of release 0.1 (commit ``c70af56``) on the ids of that release. Here the same seeded valid
actions are replayed: the valid action sets must be identical (digests of their int indices)
and the rewards equal to ``rtol = 1e-9`` (portable across BLAS kernels).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import selenv
from selenv.agents import agents_for
from selenv.families import (
    ADAPTED,
    ALL_ENV_IDS,
    ENV_IDS,
    ENV_VERSIONS,
    family_of,
    version_ids,
)

DATA = Path(__file__).parent / "data" / "episodes_v0.json"
RECORD = json.loads(DATA.read_text())
CASES = [(c["env_id"], c["kwargs"], e) for c in RECORD["cases"] for e in c["episodes"]]


def _load_recorder() -> Any:
    import importlib.util

    path = Path(__file__).parents[1] / "scripts" / "record_version_episodes.py"
    spec = importlib.util.spec_from_file_location("record_version_episodes", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


RECORDER = _load_recorder()


def _replay(env_id: str, kwargs: dict[str, Any], episode: dict[str, Any]) -> dict[str, Any]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        env = gym.make(env_id, **kwargs)
    env.reset(seed=episode["seed"])
    masks, rewards, ends = [], [], []
    for action in episode["actions"]:
        masks.append(RECORDER.mask_digest(env.unwrapped.action_masks()))
        a = np.asarray(action, dtype=np.int64) if isinstance(action, list) else action
        _, r, term, trunc, _ = env.step(a)
        rewards.append(r)
        ends.append([bool(term), bool(trunc)])
    env.close()
    return {"masks": masks, "rewards": rewards, "ends": ends}


@pytest.mark.parametrize(
    ("env_id", "kwargs", "episode"),
    CASES,
    ids=[f"{e}-{k}-seed{ep['seed']}" for e, k, ep in CASES],
)
def test_v0_replays_release_0_1(env_id, kwargs, episode) -> None:
    got = _replay(env_id, kwargs, episode)
    assert got["masks"] == episode["masks"]
    assert got["ends"] == episode["ends"]
    np.testing.assert_allclose(got["rewards"], episode["rewards"], rtol=1e-9, atol=1e-12)


def test_the_recorder_policy_reproduces_its_own_record_today() -> None:
    """The recorder run on today's -v0 gives the stored record (same actions, masks, rewards)."""
    env_id, kwargs, episode = CASES[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        now = RECORDER.record_episode(env_id, kwargs, episode["seed"])
    assert now["actions"] == episode["actions"] and now["masks"] == episode["masks"]
    np.testing.assert_allclose(now["rewards"], episode["rewards"], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize(
    "family", ["selenv/CLScheduling", "selenv/FIMSelection", "selenv/ReceiverClustering"]
)
def test_v1_differs_from_v0_where_the_defaults_changed(family) -> None:
    """The recorded v0 episodes are not what -v1 does: the test above can fail."""
    env_id, kwargs, episode = next(c for c in CASES if family_of(c[0]) == family and c[1] == {})
    v1 = env_id.replace("-v0", "-v1")
    if family == "selenv/FIMSelection":  # the default is the same scenario; example3 is not
        env_id, kwargs, episode = next(
            c for c in CASES if family_of(c[0]) == family and c[1].get("preset") == "example3"
        )
    try:
        got = _replay(v1, kwargs, episode)
    except (ValueError, IndexError):
        return  # the recorded actions are not even valid there
    same = got["masks"] == episode["masks"] and np.allclose(got["rewards"], episode["rewards"])
    assert not same


def test_v1_defaults_are_the_benchmark_presets() -> None:
    cl = gym.make("selenv/CLScheduling-v1").unwrapped
    rc = gym.make("selenv/ReceiverClustering-v1").unwrapped
    assert (cl.config.n_agents, cl.budget, cl.horizon, cl.objective) == (6, 1, 60, "trace")
    assert rc.preset == "multipath"
    with pytest.warns(DeprecationWarning, match="CLScheduling-v1"):
        cl0 = gym.make("selenv/CLScheduling-v0").unwrapped
    assert (cl0.config.n_agents, cl0.budget, cl0.horizon, cl0.objective) == (4, 2, 200, "logdet")
    with pytest.warns(DeprecationWarning, match="ReceiverClustering-v2"):
        assert gym.make("selenv/ReceiverClustering-v0").unwrapped.preset == "paper"
    fim1 = gym.make("selenv/FIMSelection-v1", preset="example2").unwrapped
    with pytest.warns(DeprecationWarning):
        fim0 = gym.make("selenv/FIMSelection-v0", preset="example2").unwrapped
    assert fim1.config.stationary and not fim0.config.stationary
    assert fim0.config.preset == "example2_moving"


def test_v0_keywords_still_override_and_are_validated() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        env = gym.make("selenv/CLScheduling-v0", preset="benchmark").unwrapped
        assert env.config.n_agents == 6
        with pytest.raises(ValueError, match="preset"):
            gym.make("selenv/FIMSelection-v0", preset="example9")
        with pytest.raises(TypeError):
            gym.make("selenv/ReceiverClustering-v0", no_such_keyword=1)


def test_version_table_registration_and_agents() -> None:
    assert set(ENV_IDS) <= set(ALL_ENV_IDS) <= set(gym.registry)
    assert [i.rsplit("-v", 1)[1] for i in ENV_IDS] == ["1", "1", "1", "2"] and len(ENV_IDS) == 4
    assert {family_of(i) for i in ALL_ENV_IDS} == {family_of(i) for i in ENV_IDS}
    for v in ENV_VERSIONS:
        assert gym.spec(v.env_id).kwargs == dict(v.kwargs)
        assert v.env_id in version_ids(v.env_id)
    assert family_of("selenv.multiagent.fim_selection_v0") == "selenv.multiagent.fim_selection_v0"
    for new in ENV_IDS:  # heuristics apply to every version; the shipped policies to theirs
        old = new.rsplit("-v", 1)[0] + "-v0"
        source = ADAPTED.get(new, (new,))[0]  # ReceiverClustering-v2 plays -v1's agents
        names = agents_for(source)
        learned = {a for a in names if a in ("ppo", "cem", "learned") or a.startswith("ppo_")}
        assert "ppo" in learned
        assert set(agents_for(old)) == set(agents_for(source)) - learned
        assert set(agents_for(new)) == set(names)
        assert "greedy" in agents_for(old) or "ga" in agents_for(old)
    assert set(ADAPTED) == {"selenv/ReceiverClustering-v2"}
    assert selenv.ENV_IDS == ENV_IDS


MA_CASES = [(c["module"], c["kwargs"], e) for c in RECORD["multiagent"] for e in c["episodes"]]


def _ma_env(module: str, kwargs: dict[str, Any]) -> Any:
    import importlib

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return importlib.import_module(module).parallel_env(**kwargs)


@pytest.mark.parametrize(
    ("module", "kwargs", "episode"),
    [c for c in MA_CASES if "receiver_clustering" in c[0]],
    ids=lambda v: f"{v}" if isinstance(v, str) else None,
)
def test_receiver_clustering_v0_replays_release_0_1(module, kwargs, episode) -> None:
    """Same agents, same masks (digest), same per-agent rewards to rtol 1e-9."""
    env = _ma_env(module, kwargs)
    obs, _ = env.reset(seed=episode["seed"])
    for act, masks, want in zip(
        episode["actions"], episode["masks"], episode["rewards"], strict=True
    ):
        agent_masks = [np.asarray(obs[a]["action_mask"], dtype=bool) for a in env.agents]
        assert RECORDER.mask_digest(np.concatenate(agent_masks)) == masks
        obs, rew, _, _, _ = env.step(act)
        assert sorted(rew) == sorted(want)
        np.testing.assert_allclose([rew[a] for a in sorted(want)], [want[a] for a in sorted(want)],
                                   rtol=1e-9, atol=1e-12)  # fmt: skip
    from selenv.multiagent import receiver_clustering_v0

    with pytest.warns(DeprecationWarning, match="receiver_clustering_v1"):
        receiver_clustering_v0.parallel_env(n_agents=4, horizon=2)


def test_receiver_clustering_v1_is_not_release_0_1() -> None:
    """The replay above can fail: v1 (multipath noise) rewards the same actions differently."""
    module, kwargs, episode = next(c for c in MA_CASES if "receiver_clustering" in c[0])
    env = _ma_env(module.replace("_v0", "_v1"), kwargs)
    env.reset(seed=episode["seed"])
    _, rew, _, _, _ = env.step(episode["actions"][0])
    want = episode["rewards"][0]
    assert not np.allclose([rew[a] for a in sorted(want)], [want[a] for a in sorted(want)])


def test_fim_selection_v0_picks_give_release_0_1_gains() -> None:
    """fim_selection_v0 kept its trajectories: the same picks give the same step gains.

    Its turn API changed since 0.1 (documented in its Version History): waiting agents are
    now present, pass with action 0, and every agent receives the team's step reward; in 0.1
    only the acting agent was present and rewarded (both agents at a change of turn).
    """
    for module, kwargs, episode in (c for c in MA_CASES if "fim_selection" in c[0]):
        env = _ma_env(module, kwargs)
        env.reset(seed=episode["seed"])
        for act, want in zip(episode["actions"], episode["rewards"], strict=True):
            ((acting, pick),) = act.items()
            obs, rew, _, _, infos = env.step({a: pick if a == acting else 0 for a in env.agents})
            np.testing.assert_allclose(rew[acting], want[acting], rtol=1e-9, atol=1e-12)
            assert set(rew) == set(env.possible_agents)  # now: everyone gets the team reward
