"""Learned policies as records: one declaration site, standings from the JSONs, ``learned``."""

from __future__ import annotations

import ast
import json
import warnings
from pathlib import Path
from types import MappingProxyType
from typing import Any

import gymnasium as gym
import pytest

import selenv  # noqa: F401  (registers the ids)
from selenv.agents import AGENTS, Agent, default_agents, make
from selenv.agents import learned as learned_mod
from selenv.agents.learned import (
    OutsideValidityWarning,
    all_policies,
    learned_target,
    resolve_learned,
)
from selenv.families.policy import METHODS, PolicySpec, Standing, read_standings
from selenv.families.spec import load_attr
from selenv.shipped import checkpoint_dir

ROOT = Path(__file__).resolve().parents[1]
FIM = "selenv/FIMSelection-v1"


def _standing(agent: str, diff: float, lo: float, env_id: str = FIM, **kwargs: Any) -> Standing:
    return Standing(
        agent=agent,
        env_id=env_id,
        env_kwargs=MappingProxyType(kwargs),
        baseline="greedy",
        seed=30000,
        episodes=30,
        mean_difference=diff,
        ci95=(lo, diff + (diff - lo)),
        wins=20,
        ties=0,
        losses=10,
        decision_time_ratio=2.0,
        command="selenv bench ...",
    )


def _record(name: str, checkpoint: str = "a.zip", **kwargs: Any) -> PolicySpec:
    fields: dict[str, Any] = {
        "plays": (FIM,),
        "factory": "tests.test_policies:_DummyAgent",
        "checkpoint": checkpoint,
        "method": "rl",
        "description": name,
    }
    fields.update(kwargs)
    return PolicySpec(name=name, **fields)


class _DummyAgent(Agent):
    """Stands in for a loader: records its options, picks the first allowed candidate."""

    def __init__(self, **options: Any) -> None:
        self.options = options

    def act(self, obs: Any, info: dict[str, Any]) -> Any:
        return 0


@pytest.fixture
def fake(monkeypatch: pytest.MonkeyPatch) -> dict[str, list[Standing]]:
    """Replace the records and their JSON standings by test ones (filled by the test)."""
    table: dict[str, list[Standing]] = {}
    records: list[PolicySpec] = []
    monkeypatch.setattr(learned_mod, "all_policies", lambda: tuple(records))
    monkeypatch.setattr(
        PolicySpec,
        "standings",
        lambda self: tuple(s for s in table.get(self.checkpoint, []) if s.agent == self.name),
    )
    table["__records__"] = records  # type: ignore[assignment]
    return table


# -- the shipped records --------------------------------------------------------------------


def test_every_record_is_complete_and_its_files_exist() -> None:
    records = all_policies()
    assert records, "no policy record"
    names = [(r.name, e) for r in records for e in r.plays]
    assert len(names) == len(set(names)), "two records of one name on one env"
    for record in records:
        assert record.method in METHODS
        assert callable(load_attr(record.factory))
        stem = record.checkpoint.rsplit(".", 1)[0]
        assert (checkpoint_dir() / f"{stem}.json").is_file(), record.checkpoint
        assert record.trainer.startswith("python -m selenv.train."), record.name
        config = record.trainer.split("--config ")[-1].split()[0]
        assert (ROOT / config).is_file(), config
        for env_id in record.plays:
            assert AGENTS[record.name][env_id].learned


def test_learned_agents_are_declared_only_by_the_records() -> None:
    """No module other than the registry of the records registers a learned agent."""
    offenders = []
    for path in (ROOT / "selenv").rglob("*.py"):
        if path.name == "learned.py" and path.parent.name == "agents":
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.keyword) and node.arg == "learned":
                if isinstance(node.value, ast.Constant) and node.value.value is True:
                    offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert offenders == []
    # and every learned agent of the registry comes from a record, an alias of one, or `learned`
    names = {r.name for r in all_policies()} | {a for r in all_policies() for a in r.aliases}
    for name, by_env in AGENTS.items():
        if any(spec.learned for spec in by_env.values()):
            assert name in names | {"learned"}, name


def test_every_current_record_beats_its_baseline_at_the_defaults() -> None:
    """A shipped learned agent a user can reach beats its heuristic on held-out seeds, or is
    retired (the standing comes from a bench run, recorded by scripts/record_standings.py)."""
    for record in all_policies():
        if record.retired:
            continue
        for env_id in record.plays:
            at_defaults = [
                s for s in record.standings() if s.env_id == env_id and not s.env_kwargs
            ] or [s for s in record.standings() if s.env_id == env_id]
            assert at_defaults, f"{record.name} on {env_id}: no held-out standing recorded"
            for standing in at_defaults:
                assert standing.episodes >= 30, (record.name, env_id)
                assert standing.beats_baseline, (record.name, env_id, standing.summary())


def test_learned_exists_on_every_env_and_module_and_plays_the_best_record() -> None:
    for env_id in {e for r in all_policies() for e in r.plays}:
        target = learned_target(env_id)
        assert target is not None, f"no learned agent on {env_id}"
        chosen = resolve_learned(env_id)
        assert chosen is not None
        best = max(
            (
                s.mean_difference
                for r in all_policies()
                if env_id in r.plays and not r.retired
                for s in r.standings()
                if s.env_id == env_id
                and not s.env_kwargs
                and s.beats_baseline
                and r.within_budget(s)
            ),
        )
        assert chosen[1].mean_difference == best
        # the bench runs `learned` by default and not the record it plays a second time
        assert "learned" in default_agents(env_id)
        assert target not in default_agents(env_id)


def test_malformed_standings_are_refused_with_the_file_named(tmp_path: Path, monkeypatch) -> None:
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    (folder / "bad.json").write_text(json.dumps({"standings": [{"agent": "x"}]}))
    (folder / "nan.json").write_text(
        json.dumps({"standings": [{**_entry(), "mean_difference": float("nan")}]})
    )
    (folder / "ok.json").write_text(json.dumps({"standings": [_entry()]}))
    monkeypatch.setattr("selenv.families.policy.checkpoint_dir", lambda: folder)
    read_standings.cache_clear()
    try:
        with pytest.raises(ValueError, match=r"bad\.json: malformed standing"):
            read_standings("bad.zip")
        with pytest.raises(ValueError, match="non-finite"):
            read_standings("nan.zip")
        (ok,) = read_standings("ok.zip")
        assert ok.beats_baseline and ok.ci95 == (0.01, 0.05)
        assert read_standings("absent.zip") == ()
    finally:
        read_standings.cache_clear()


def _entry() -> dict[str, Any]:
    return {
        "agent": "ppo",
        "env_id": FIM,
        "env_kwargs": {},
        "baseline": "greedy",
        "seed": 30000,
        "episodes": 30,
        "mean_difference": 0.03,
        "ci95": [0.01, 0.05],
        "wins": 25,
        "ties": 0,
        "losses": 5,
        "decision_time_ratio": 3.0,
        "command": "selenv bench",
    }


def test_record_fields_are_checked() -> None:
    with pytest.raises(ValueError, match="method"):
        _record("a", method="magic")
    with pytest.raises(ValueError, match="resolved from the records"):
        _record("learned")
    with pytest.raises(ValueError, match="module:attr"):
        _record("a", factory="nowhere")
    with pytest.raises(ValueError, match="plays"):
        _record("a", plays=())


# -- resolution of `learned` -----------------------------------------------------------------


def test_learned_picks_the_best_significant_standing(fake) -> None:
    records = fake["__records__"]
    records += [_record("a", "a.zip"), _record("b", "b.zip"), _record("c", "c.zip")]
    fake["a.zip"] = [_standing("a", 0.03, 0.01)]
    fake["b.zip"] = [_standing("b", 0.05, -0.01)]  # larger but not significant
    fake["c.zip"] = [_standing("c", 0.02, 0.005)]
    assert resolve_learned(FIM)[0].name == "a"  # type: ignore[index]
    fake["c.zip"] = [_standing("c", 0.04, 0.02)]
    assert resolve_learned(FIM)[0].name == "c"  # type: ignore[index]
    records[2] = _record("c", "c.zip", retired="worse than greedy")
    assert resolve_learned(FIM)[0].name == "a"  # type: ignore[index]
    records[0] = _record("a", "a.zip", max_decision_ratio=1.5)  # its standing: 2.0x
    assert resolve_learned(FIM) is None  # over its own decision budget: not `learned`
    records[0] = _record("a", "a.zip", max_decision_ratio=2.0)
    assert resolve_learned(FIM)[0].name == "a"  # type: ignore[index]
    fake["a.zip"] = [_standing("a", 0.03, -0.01)]
    assert resolve_learned(FIM) is None


def test_learned_prefers_a_standing_measured_at_the_envs_own_mode(fake) -> None:
    records = fake["__records__"]
    records += [_record("coop", "c.zip"), _record("indep", "i.zip")]
    fake["c.zip"] = [_standing("coop", 0.05, 0.02)]  # at the defaults (cooperative)
    fake["i.zip"] = [_standing("indep", 0.40, 0.30, mode="independent")]
    assert resolve_learned(FIM)[0].name == "coop"  # type: ignore[index]
    assert resolve_learned(FIM, {"mode": "cooperative"})[0].name == "coop"  # type: ignore[index]
    assert resolve_learned(FIM, {"mode": "independent"})[0].name == "indep"  # type: ignore[index]


# -- deprecated names, retired policies, validity ---------------------------------------------


def test_a_deprecated_name_warns_naming_the_new_spelling_and_keeps_working() -> None:
    with pytest.warns(DeprecationWarning, match="use 'ppo:verify_top_k=4'"):
        agent = make("ppo_top4", "selenv/ReceiverClustering-v1")
    assert agent.inner.verify_top_k == 4
    with pytest.warns(DeprecationWarning, match="use 'ppo'"):
        general = make("ppo_general", FIM)
    assert Path(general.checkpoint).name == "fim_selection_ppo_general.zip"
    assert "ppo_top4" not in default_agents("selenv/ReceiverClustering-v1")


def test_a_retired_policy_warns_unless_it_plays_the_users_own_checkpoint() -> None:
    with pytest.warns(DeprecationWarning, match="retired"):
        make("ppo", "selenv/CLScheduling-v1")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        make("ppo:checkpoint=checkpoints/cl_scheduling_ppo.zip", "selenv/CLScheduling-v1")
    assert "ppo" not in default_agents("selenv/CLScheduling-v1")


def test_outside_its_verified_configurations_a_policy_warns_in_one_line() -> None:
    agent = make("ppo", FIM)
    inside = gym.make(FIM, budget=10)
    inside.reset(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        agent.reset(inside, seed=0)
    outside = gym.make(FIM, budget=3)
    outside.reset(seed=0)
    with pytest.warns(OutsideValidityWarning, match=r"budget=3.*budget in \[5, 10, 15, 20\]"):
        agent.reset(outside, seed=0)
    own = make(f"ppo:checkpoint={checkpoint_dir() / 'fim_selection_ppo_general.zip'}", FIM)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        own.reset(outside, seed=0)  # the user's own file: no claim about where it is valid


def _env(env_id: str, kwargs: Any) -> Any:
    if env_id.startswith("selenv/"):
        return gym.make(env_id, **kwargs)
    import importlib

    return importlib.import_module(env_id).parallel_env(**kwargs)


def test_every_record_is_valid_where_its_standings_were_measured() -> None:
    """A record never warns on a configuration its held-out standing was measured on."""
    from selenv.agents.learned import env_parameters

    for record in all_policies():
        for standing in record.standings():
            env = _env(standing.env_id, dict(standing.env_kwargs))
            assert record.outside(env_parameters(env)) == {}, (record.name, standing.env_kwargs)
