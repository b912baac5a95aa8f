"""Every family is wired from its record alone: ids, versions, agents, views, checkpoint, modules.

This is the check behind the "add a family" recipe (docs/guide/adding_a_family.md): a new folder
and one line in ``selenv.families.FAMILIES`` must give all of the below.
"""

from __future__ import annotations

import importlib
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import selenv
from selenv.agents import AGENTS, agents_for, make
from selenv.bench import multiagent_modules
from selenv.envs.actions import INVALID_ACTION_MODES
from selenv.families import ALL_ENV_IDS, ENV_IDS, FAMILIES, family_spec
from selenv.families.spec import FamilySpec, load_attr
from selenv.learned.rl.agent import DEFAULT_CHECKPOINTS
from selenv.learned.rl.views import VIEWS, view_for

IDS = [f.name for f in FAMILIES]


@pytest.mark.parametrize("spec", FAMILIES, ids=IDS)
def test_record_builds_both_versions_and_the_env(spec: FamilySpec) -> None:
    package = importlib.import_module(f"selenv.families.{spec.name}")
    assert package.SPEC is spec
    ids = [v.env_id for v in spec.versions]
    v0 = [f"selenv/{spec.env_name}-v0"] if spec.has_v0 else []  # a family added later has none
    frozen = [spec.version_id(k) for k in range(1, spec.version)]
    assert ids == [*v0, *frozen, spec.current_id]
    assert spec.current_id == f"selenv/{spec.env_name}-v{1 + len(spec.frozen)}"
    assert spec.current_id in ENV_IDS and set(ids) <= set(ALL_ENV_IDS) <= set(gym.registry)
    assert all(family_spec(i) is spec for i in ids)
    env = gym.make(spec.current_id)
    assert isinstance(env.unwrapped, load_attr(spec.env_class))
    check_env(env.unwrapped, skip_render_check=True)
    for old in v0:
        with pytest.warns(DeprecationWarning, match=spec.current_id):
            gym.make(old)
    for k, old in enumerate(frozen, start=1):  # Gymnasium's own "out of date" warning
        with pytest.warns(DeprecationWarning, match=f"upgrading to version `v{spec.version}`"):
            env = gym.make(old)
        assert isinstance(env.unwrapped, load_attr(spec.frozen[k - 1].env_class))


@pytest.mark.parametrize("spec", FAMILIES, ids=IDS)
def test_record_registers_agents_views_checkpoint(spec: FamilySpec) -> None:
    for module in spec.agent_modules:
        assert module in importlib.sys.modules  # imported by selenv.agents
    assert {"random", "greedy"} & set(agents_for(spec.current_id))
    assert set(agents_for(spec.agents_id)) <= set(agents_for(spec.current_id))
    env = gym.make(spec.agents_id)  # the version the views and policies are written for
    for version in spec.versions:
        if version.env_id != spec.current_id or spec.agent_adapter is None:
            assert list(VIEWS[version.env_id]) == list(load_attr(spec.views))
    view = view_for(spec.agents_id, env)
    obs, _ = env.reset(seed=0)
    assert view.space(env.observation_space).contains(view(obs))
    if spec.checkpoint is not None:
        assert DEFAULT_CHECKPOINTS[spec.agents_id].is_file()
        assert spec.agents_id in AGENTS["ppo"] and spec.current_id in AGENTS["ppo"]
        assert f"selenv/{spec.env_name}-v0" not in AGENTS["ppo"]  # trained on -v1 only
    if spec.multiagent_module is not None:
        module = importlib.import_module(spec.multiagent_module)
        assert callable(module.parallel_env) and module.__doc__
        assert spec.multiagent_module in multiagent_modules()


@pytest.mark.parametrize("spec", FAMILIES, ids=IDS)
def test_env_keeps_the_contract_the_bench_relies_on(spec: FamilySpec) -> None:
    """Unknown keywords refused, every ``invalid_action`` mode taken, ``info["objective"]`` given.

    ``selenv bench`` builds a family's env with ``invalid_action="raise"`` (a masked action
    fails loudly) and compares agents on ``info["objective"]``; a family's own agent plays a
    step of it without a masked action.
    """
    with pytest.raises(TypeError, match="no_such_keyword"):
        gym.make(spec.current_id, no_such_keyword=1)
    for mode in INVALID_ACTION_MODES:
        gym.make(spec.current_id, invalid_action=mode).close()
    with pytest.raises(ValueError, match="invalid_action"):
        gym.make(spec.current_id, invalid_action="no_such_mode")
    env = gym.make(spec.current_id, invalid_action="raise")
    obs, info = env.reset(seed=0)
    assert np.isfinite(float(info["objective"]))
    name = next(n for n in ("greedy", "random") if n in agents_for(spec.current_id))
    agent = make(name, spec.current_id)
    agent.reset(env, seed=0)
    obs, _, terminated, _, info = env.step(agent.act(obs, info))
    assert np.isfinite(float(info["objective"]))
    mask = np.asarray(env.unwrapped.action_masks(), dtype=bool)
    if isinstance(env.action_space, gym.spaces.Discrete) and not (mask.all() or terminated):
        with pytest.raises(ValueError, match="invalid"):
            env.step(int(np.flatnonzero(~mask)[0]))


def test_families_are_unique_and_in_selenv_list_order() -> None:
    assert len({f.name for f in FAMILIES}) == len({f.env_name for f in FAMILIES}) == len(FAMILIES)
    assert selenv.ENV_IDS == ENV_IDS == tuple(f.current_id for f in FAMILIES)


def test_a_family_added_later_starts_at_v1() -> None:
    spec = FamilySpec(name="toy", env_name="Toy", title="", env_class="a:b", has_v0=False)
    assert [v.env_id for v in spec.versions] == ["selenv/Toy-v1"]
    assert spec.versions[0].entry_point == "selenv.families.toy:make_env"


def test_record_fields_are_validated() -> None:
    with pytest.raises(ValueError, match="identifiers"):
        FamilySpec(name="no-dash", env_name="X", title="", env_class="a:b")
    with pytest.raises(ValueError, match="module:attr"):
        load_attr("selenv.families")


def test_moved_module_paths_still_import_with_a_warning() -> None:
    from selenv._compat import MOVED

    for old, new in MOVED.items():
        importlib.sys.modules.pop(old, None)  # an earlier import left the alias: find it anew
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            module = importlib.import_module(old)
        assert module is importlib.import_module(new)
        assert any(f"{old} moved to {new}" in str(w.message) for w in caught)
    from selenv.envs.fim_selection import FIMSelectionEnv  # the old spelling of a class

    assert FIMSelectionEnv is load_attr("selenv.families.fim.env:FIMSelectionEnv")


@pytest.mark.parametrize("spec", FAMILIES, ids=IDS)
def test_every_current_env_observes_its_action_mask(spec: FamilySpec) -> None:
    """The README's promise: ``action_masks()``, ``info["action_mask"]``, ``obs["action_mask"]``."""
    env = gym.make(spec.current_id)
    obs, info = env.reset(seed=1)
    mask = np.asarray(env.unwrapped.action_masks(), dtype=bool)
    assert mask.any()
    np.testing.assert_array_equal(np.asarray(obs["action_mask"], dtype=bool).ravel(), mask)
    np.testing.assert_array_equal(np.asarray(info["action_mask"], dtype=bool).ravel(), mask)
