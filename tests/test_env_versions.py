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
from selenv.families import ALL_ENV_IDS, ENV_IDS, ENV_VERSIONS, family_of, version_ids

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
    with pytest.warns(DeprecationWarning, match="ReceiverClustering-v1"):
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
    assert all(i.endswith("-v1") for i in ENV_IDS) and len(ENV_IDS) == 4
    assert {family_of(i) for i in ALL_ENV_IDS} == {family_of(i) for i in ENV_IDS}
    for v in ENV_VERSIONS:
        assert gym.spec(v.env_id).kwargs == dict(v.kwargs)
        assert v.env_id in version_ids(v.env_id)
    assert family_of("selenv.multiagent.fim_selection_v0") == "selenv.multiagent.fim_selection_v0"
    for new in ENV_IDS:  # heuristics apply to every version; the shipped policies to theirs
        old = new.replace("-v1", "-v0")
        assert set(agents_for(old)) == set(agents_for(new)) - {"ppo", "ppo_top4", "ppo_top8"}
        assert "greedy" in agents_for(old) or "ga" in agents_for(old)
    assert selenv.ENV_IDS == ENV_IDS
