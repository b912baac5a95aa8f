"""The benchmark runner, its report and the ``selenv`` CLI, on a toy env with a known optimum."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import _proc
import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.envs.registration import EnvSpec

from selenv.agents import AGENTS, Agent, AgentSpec
from selenv.bench import format_table, run_bench
from selenv.bench.runner import BenchError
from selenv.cli import main

TOY = "selenv_test/Toy-v0"
TOY2 = "selenv_test/Toy2-v0"
FIM = "selenv/FIMSelection-v1"
CONTRACT_KEYS = {"env_id", "env_kwargs", "seed", "episodes", "agents"}
AGENT_KEYS = {
    "returns",
    "mean_return",
    "final_objectives",
    "mean_final_objective",
    "decision_seconds_mean",
    "paired",
    "normalized_score",
}
PAIRED_KEYS = {"baseline", "mean_diff", "ci95", "wins", "ties", "losses"}
PROVENANCE_KEYS = {
    "selenv_version",
    "git_commit",
    "python",
    "platform",
    "packages",
    "argv",
    "timestamp",
}


class ToyEnv(gym.Env[np.ndarray, np.int64]):
    """Pick ``k`` of ``n`` values drawn U(0, 1) at reset; reward = picked value.

    The optimal return is the sum of the ``k`` largest values; ``info["objective"]`` is
    ``10 x`` the sum picked so far (so it differs from the return and grows every step).
    """

    def __init__(self, n: int = 5, k: int = 2) -> None:
        self.n, self.k = n, k
        self.action_space = spaces.Discrete(n)
        self.observation_space = spaces.Box(0.0, 1.0, (n,), np.float64)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self.values = self.np_random.uniform(0.0, 1.0, self.n)
        self.picked = np.zeros(self.n, bool)
        return self._obs(), self._info()

    def step(self, action: Any):
        a = int(action)
        if self.picked[a]:
            raise ValueError(f"action {a} is masked: already picked")
        self.picked[a] = True
        done = int(self.picked.sum()) == self.k
        return self._obs(), float(self.values[a]), done, False, self._info()

    def _obs(self) -> np.ndarray:
        return np.where(self.picked, 0.0, self.values)

    def _info(self) -> dict[str, Any]:
        return {"objective": 10.0 * float(self.values[self.picked].sum()), "mask": ~self.picked}


#: agent name -> what it saw at each reset: (seed, initial values)
SEEN: dict[str, list[tuple[int | None, np.ndarray]]] = {}


class ToyAgent(Agent):
    """Records the scenario and seed of every episode; subclasses choose the action."""

    def reset(self, env: gym.Env[Any, Any], seed: int | None = None) -> None:
        super().reset(env, seed)
        SEEN.setdefault(self.name, []).append((seed, env.unwrapped.values.copy()))

    def act(self, obs: Any, info: dict[str, Any]) -> Any:
        return int(np.argmax(obs))


class BestAgent(ToyAgent):
    name = "toy_best"


class FirstAgent(ToyAgent):
    name = "toy_first"

    def act(self, obs: Any, info: dict[str, Any]) -> Any:
        return int(np.flatnonzero(info["mask"])[0])


class SlowAgent(FirstAgent):
    name = "toy_slow"

    def act(self, obs: Any, info: dict[str, Any]) -> Any:
        time.sleep(0.003)
        return super().act(obs, info)


class RefuseAgent(ToyAgent):
    name = "toy_refuse"

    def act(self, obs: Any, info: dict[str, Any]) -> Any:
        raise ValueError("toy_refuse refuses C(5, 2) = 10 subsets")


class RandomToyAgent(ToyAgent):
    name = "random"

    def act(self, obs: Any, info: dict[str, Any]) -> Any:
        return int(self.rng.choice(np.flatnonzero(info["mask"])))


class CrashAgent(ToyAgent):
    name = "toy_crash"

    def act(self, obs: Any, info: dict[str, Any]) -> Any:
        raise RuntimeError("toy_crash is broken")


class MaskedAgent(ToyAgent):
    """Always picks action 0: the env raises ValueError at the second step (a bug, not a skip)."""

    name = "toy_masked"

    def act(self, obs: Any, info: dict[str, Any]) -> Any:
        return 0


@pytest.fixture(autouse=True)
def toy_registry(monkeypatch: pytest.MonkeyPatch) -> None:
    """Register the toy envs and agents for one test (restored afterwards)."""
    monkeypatch.setitem(gym.registry, TOY, EnvSpec(id=TOY, entry_point=ToyEnv))
    monkeypatch.setitem(
        gym.registry, TOY2, EnvSpec(id=TOY2, entry_point=ToyEnv, kwargs={"n": 4, "k": 1})
    )
    for cls, env_ids, desc in [
        (BestAgent, (TOY, TOY2), "optimal: largest value left"),
        (FirstAgent, (TOY,), "lowest index left"),
        (SlowAgent, (TOY,), "lowest index left, 3 ms per decision"),
        (RefuseAgent, (TOY,), "always refuses"),
        (FirstAgent, (TOY2,), "only for Toy2"),
    ]:
        name = "toy_only2" if desc == "only for Toy2" else cls.name
        spec = AgentSpec(name, env_ids, cls, desc)
        monkeypatch.setitem(AGENTS, name, dict.fromkeys(env_ids, spec))
    SEEN.clear()


def _scenario(seed: int, n: int = 5) -> np.ndarray:
    """What ``env.reset(seed=seed)`` draws (Gymnasium seeds np_random like default_rng)."""
    return np.random.default_rng(seed).uniform(0.0, 1.0, n)


# -- runner ------------------------------------------------------------------------------------
def test_every_agent_sees_the_same_seeded_episodes() -> None:
    run_bench(TOY, ["toy_best", "toy_first"], episodes=3, seed=7, progress=False)
    for name in ("toy_best", "toy_first"):
        seeds = [s for s, _ in SEEN[name]]
        assert seeds == [7, 8, 9]  # agent.reset(env, seed=seed + e)
        for e, (_, values) in enumerate(SEEN[name]):
            np.testing.assert_array_equal(values, _scenario(7 + e))  # env.reset(seed=seed + e)
    for (_, a), (_, b) in zip(SEEN["toy_best"], SEEN["toy_first"], strict=True):
        np.testing.assert_array_equal(a, b)


def test_returns_final_objectives_and_gap_are_computed_right() -> None:
    res = run_bench(TOY, ["toy_first", "toy_best"], episodes=4, seed=3, progress=False)
    assert list(res.agents) == ["toy_first", "toy_best"]
    best, first = res.agents["toy_best"], res.agents["toy_first"]
    opt = [np.sort(_scenario(3 + e))[-2:].sum() for e in range(4)]
    naive = [_scenario(3 + e)[:2].sum() for e in range(4)]
    np.testing.assert_allclose(best.returns, opt)
    np.testing.assert_allclose(best.final_objectives, 10 * np.array(opt))
    np.testing.assert_allclose(first.returns, naive)
    np.testing.assert_allclose(first.final_objectives, 10 * np.array(naive))
    assert best.mean_return == pytest.approx(np.mean(opt))
    assert best.std_return == pytest.approx(np.std(opt))
    assert best.decisions == first.decisions == 4 * 2
    assert res.gap_percent("toy_best") == 0.0
    assert res.gap_percent("toy_first") == pytest.approx(
        100 * (np.mean(opt) - np.mean(naive)) / np.mean(opt)
    )
    assert res.gap_percent("toy_first") > 0


def test_decision_time_measures_act() -> None:
    res = run_bench(TOY, ["toy_best", "toy_slow"], episodes=2, progress=False)
    assert res.agents["toy_slow"].decision_seconds_mean >= 0.003
    assert res.agents["toy_best"].decision_seconds_mean < 0.003


def test_value_error_skips_the_agent_and_the_run_goes_on() -> None:
    res = run_bench(TOY, ["toy_refuse", "toy_best"], episodes=2, progress=False)
    assert res.agents["toy_refuse"].skipped == "toy_refuse refuses C(5, 2) = 10 subsets"
    assert res.agents["toy_refuse"].to_json() == {"skipped": res.agents["toy_refuse"].skipped}
    assert len(res.agents["toy_best"].returns) == 2
    table = format_table(res)
    assert "skipped: toy_refuse refuses C(5, 2) = 10 subsets" in table


def test_other_exceptions_propagate(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(AGENTS, "toy_crash", {TOY: AgentSpec("toy_crash", (TOY,), CrashAgent)})
    monkeypatch.setitem(AGENTS, "toy_masked", {TOY: AgentSpec("toy_masked", (TOY,), MaskedAgent)})
    with pytest.raises(RuntimeError, match="broken"):
        run_bench(TOY, ["toy_best", "toy_crash"], episodes=1, progress=False)
    # a ValueError raised by the env (masked action) is the agent's bug: it is not a skip
    with pytest.raises(ValueError, match="masked"):
        run_bench(TOY, ["toy_masked"], episodes=1, progress=False)


def test_default_agents_and_usage_errors() -> None:
    res = run_bench(TOY, episodes=1, progress=False)
    assert list(res.agents) == ["toy_best", "toy_first", "toy_slow", "toy_refuse"]
    with pytest.raises(BenchError, match="does not apply"):
        run_bench(TOY, ["toy_only2"], episodes=1, progress=False)
    skipped = run_bench(TOY, ["toy_only2"], episodes=1, progress=False, skip_inapplicable=True)
    assert "does not apply" in skipped.agents["toy_only2"].skipped
    with pytest.raises(BenchError, match="episodes"):
        run_bench(TOY, episodes=0, progress=False)
    with pytest.raises(BenchError, match="unknown agent"):
        run_bench(TOY, ["nope"], progress=False)
    with pytest.raises(BenchError, match="unknown env id"):
        run_bench("selenv_test/Nope-v0", progress=False)


# -- CLI ---------------------------------------------------------------------------------------
def test_json_follows_the_contract_and_round_trips(tmp_path: Path) -> None:
    out = tmp_path / "sub" / "res.json"
    argv = ["bench", TOY, "--agents", "toy_best,toy_refuse", "--episodes", "3", "--seed", "5"]
    rc = main([*argv, "--env-kwargs", '{"n": 6}', "--json", str(out), "--no-progress"])
    assert rc == 0
    with out.open() as fh:
        top = json.load(fh)
    # one shape, whatever the number of envs
    assert set(top) == {"provenance", "complete", "results"}
    assert top["complete"] is True
    assert PROVENANCE_KEYS <= set(top["provenance"])
    assert top["provenance"]["argv"][:3] == ["selenv", "bench", TOY]
    assert len(top["results"]) == 1
    doc = top["results"][0]
    assert CONTRACT_KEYS | {"selenv_version", "timestamp", "baseline"} <= set(doc)
    assert doc["env_id"] == TOY and doc["env_kwargs"] == {"n": 6}
    assert doc["seed"] == 5 and doc["episodes"] == 3 and doc["complete"] is True
    assert "episodes_done" not in doc and "paired_seeds" not in doc
    best = doc["agents"]["toy_best"]
    assert "seeds" not in best
    assert AGENT_KEYS <= set(best)
    assert len(best["returns"]) == len(best["final_objectives"]) == 3
    opt = [np.sort(_scenario(5 + e, n=6))[-2:].sum() for e in range(3)]
    np.testing.assert_allclose(best["returns"], opt)
    assert best["mean_final_objective"] == pytest.approx(10 * np.mean(opt))
    assert doc["agents"]["toy_refuse"] == {"skipped": "toy_refuse refuses C(5, 2) = 10 subsets"}
    assert doc["agent_specs"]["toy_best"] == {"agent": "toy_best", "kwargs": {}}
    assert json.loads(json.dumps(doc)) == doc


def test_several_envs_give_the_same_shape_and_skip_inapplicable_agents(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out, one = tmp_path / "res.json", tmp_path / "one.json"
    argv = ["bench", TOY, TOY2, "--agents", "toy_best,toy_only2", "--episodes", "2"]
    rc = main([*argv, "--json", str(out), "--no-progress"])
    assert rc == 0
    cap = capsys.readouterr()
    assert f"skipping toy_only2 on {TOY}" in cap.err
    top = json.loads(out.read_text())
    doc = top["results"]
    assert [d["env_id"] for d in doc] == [TOY, TOY2]
    assert "does not apply" in doc[0]["agents"]["toy_only2"]["skipped"]
    assert AGENT_KEYS <= set(doc[1]["agents"]["toy_only2"])
    assert TOY in cap.out and TOY2 in cap.out
    # the same keys at every level as a one-env run
    assert main(["bench", TOY, "--agents", "toy_best", "--episodes", "2", "--json", str(one),
                 "--no-progress"]) == 0  # fmt: skip
    single = json.loads(one.read_text())
    assert set(single) == set(top)
    assert set(single["provenance"]) == set(top["provenance"])
    assert set(single["results"][0]) == set(doc[0]) == set(doc[1])
    assert set(single["results"][0]["agents"]["toy_best"]) == set(doc[0]["agents"]["toy_best"])


def test_json_has_paired_statistics_and_normalized_score(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(AGENTS["random"], TOY, AgentSpec("random", (TOY,), RandomToyAgent))
    out = tmp_path / "res.json"
    argv = ["bench", TOY, "--agents", "toy_first,toy_best,random", "--episodes", "6"]
    assert main([*argv, "--json", str(out), "--no-progress"]) == 0
    doc = json.loads(out.read_text())["results"][0]
    assert doc["baseline"] == "toy_best"  # default: the best mean return
    assert doc["random_reference"] == "random"
    agents = doc["agents"]
    for name, entry in agents.items():
        assert PAIRED_KEYS <= set(entry["paired"]), name
        assert entry["paired"]["baseline"] == "toy_best"
        assert "normalized_score" in entry
    first, best, rand = agents["toy_first"], agents["toy_best"], agents["random"]
    diffs = np.subtract(first["returns"], best["returns"])
    assert first["paired"]["mean_diff"] == pytest.approx(diffs.mean())
    lo, hi = first["paired"]["ci95"]
    assert lo <= diffs.mean() <= hi < 0  # toy_best is optimal: every difference is <= 0
    w, t, lo_ = (first["paired"][k] for k in ("wins", "ties", "losses"))
    assert (w, t + lo_) == (0, 6) and lo_ == int(np.sum(diffs < -1e-9))
    assert best["paired"] == {**best["paired"], "mean_diff": 0.0, "ci95": [0.0, 0.0], "ties": 6}
    assert best["normalized_score"] == pytest.approx(1.0)
    assert rand["normalized_score"] == pytest.approx(0.0)
    want = (first["mean_return"] - rand["mean_return"]) / (
        best["mean_return"] - rand["mean_return"]
    )
    assert first["normalized_score"] == pytest.approx(want)


def test_explicit_baseline(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "res.json"
    argv = ["bench", TOY, "--agents", "toy_first,toy_best", "--episodes", "4"]
    assert main([*argv, "--baseline", "toy_first", "--json", str(out), "--no-progress"]) == 0
    doc = json.loads(out.read_text())["results"][0]
    assert doc["baseline"] == "toy_first" and doc["random_reference"] is None
    best = doc["agents"]["toy_best"]
    assert best["paired"]["baseline"] == "toy_first"
    assert best["paired"]["mean_diff"] > 0 and best["paired"]["ci95"][0] > 0
    assert best["normalized_score"] is None  # no random agent ran
    lines = capsys.readouterr().out.splitlines()
    assert "Δ vs toy_first [95 % CI]" in lines[1]
    assert "baseline" in next(ln for ln in lines if ln.startswith("toy_first"))


@pytest.mark.parametrize(
    "argv",
    [
        [TOY, "--agents", "toy_first,toy_best", "--baseline", "nope"],  # not among the agents
        [TOY, "--agents", "toy_first,toy_best", "--baseline", "toy_slow"],  # registered, not run
        [TOY, "--agents", "toy_best,toy_refuse", "--baseline", "toy_refuse"],  # skipped
        [TOY, TOY2, "--agents", "toy_best,toy_first", "--baseline", "toy_first"],  # not on TOY2
        [TOY, "--baseline", "toy_refuse"],  # default agents, baseline skipped
    ],
)
def test_unknown_or_skipped_baseline_exits_2_and_writes_nothing(
    argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out, plots = tmp_path / "res.json", tmp_path / "plots"
    rc = main(["bench", *argv, "--episodes", "2", "--json", str(out), "--plot", str(plots),
               "--no-progress"])  # fmt: skip
    assert rc == 2
    assert "baseline" in capsys.readouterr().err
    assert not out.exists() and not plots.exists()


def test_unknown_pettingzoo_module_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "res.json"
    for module in ("selenv.multiagent.nope_v0", "selenv.multiagent", "os.path"):
        assert main(["bench", module, "--json", str(out), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert repr(module) in err and "selenv.multiagent.fim_selection_v0" in err
    assert not out.exists()


def test_table_on_stdout(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["bench", TOY, "--agents", "toy_first,toy_best,toy_refuse", "--no-progress"])
    assert rc == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].startswith(TOY)
    header = lines[1]
    for col in ("Δ vs toy_best [95 % CI]", "W/T/L", "norm. score", "decision ms", "episodes"):
        assert col in header
    best_row = next(ln for ln in lines if ln.startswith("toy_best"))
    assert " baseline " in best_row and best_row.endswith(" 10")
    first_row = next(ln for ln in lines if ln.startswith("toy_first"))
    assert "*" in first_row and " 0/" in first_row  # CI excludes 0; no win against the optimum
    assert any(ln.startswith("toy_refuse") and "skipped: toy_refuse refuses" in ln for ln in lines)


def test_plot_writes_a_png(tmp_path: Path) -> None:
    plots = tmp_path / "plots"
    rc = main(["bench", TOY, "--episodes", "2", "--plot", str(plots), "--no-progress"])
    assert rc == 0
    png = plots / "Toy-v0.png"
    assert png.stat().st_size > 1000
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_list_shows_envs_and_agents(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert FIM in out
    assert TOY in out and "optimal: largest value left" in out


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--env-kwargs", '{"n": '], "--env-kwargs"),  # not JSON
        (["--env-kwargs", "[1, 2]"], "--env-kwargs"),  # not an object
        (["--env-kwargs", '{"nope": 1}'], "--env-kwargs"),  # rejected by the env
        (["--episodes", "0"], "--episodes"),
        (["--agents", "toy_only2"], "does not apply"),
        (["--agents", "nope"], "unknown agent"),
    ],
)
def test_usage_errors_exit_2(
    argv: list[str], needle: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", TOY, "--no-progress", *argv]) == 2
    assert needle in capsys.readouterr().err


def test_unknown_env_lists_known_ids(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "selenv/Nope-v0"]) == 2
    err = capsys.readouterr().err
    assert "unknown env id" in err and FIM in err


def test_python_dash_m_selenv() -> None:
    proc = _proc.run(
        [sys.executable, "-m", "selenv", "list"], capture_output=True, text=True, check=True
    )
    assert FIM in proc.stdout


# -- the real env ------------------------------------------------------------------------------
def test_real_fim_bench_greedy_beats_random(tmp_path: Path) -> None:
    pytest.importorskip(
        "selenv.families.fim.scenario",
        reason="selenv.families.fim.scenario (the FIM scenario) is not written yet",
    )
    out = tmp_path / "fim.json"
    kwargs = '{"n_candidates": 20, "budget": 4}'
    argv = ["bench", FIM, "--agents", "greedy,random", "--episodes", "2", "--env-kwargs", kwargs]
    rc = main([*argv, "--json", str(out), "--no-progress"])
    assert rc == 0
    doc = json.loads(out.read_text())["results"][0]
    assert CONTRACT_KEYS <= set(doc)
    greedy, rand = doc["agents"]["greedy"], doc["agents"]["random"]
    assert AGENT_KEYS <= set(greedy) and AGENT_KEYS <= set(rand)
    assert len(greedy["returns"]) == 2
    # the return of FIMSelection is the objective f(F) itself
    np.testing.assert_allclose(greedy["returns"], greedy["final_objectives"], rtol=1e-6)
    assert greedy["mean_final_objective"] >= rand["mean_final_objective"]


def test_provenance_never_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    from selenv.bench import provenance as prov

    doc = prov.provenance(["selenv", "bench"])
    assert PROVENANCE_KEYS <= set(doc) and doc["argv"] == ["selenv", "bench"]
    assert set(doc["packages"]) == set(prov.PACKAGES)
    assert doc["packages"]["numpy"] == np.__version__
    assert prov._version("no_such_distribution_xyz") is None

    def no_git(*args: Any, **kwargs: Any) -> Any:
        raise FileNotFoundError("git")

    monkeypatch.setattr(prov.subprocess, "run", no_git)
    assert prov.git_commit() == (None, None)
    assert prov.provenance()["git_commit"] is None


def test_agent_spec_options_and_bad_options_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from selenv.agents import parse_spec

    assert parse_spec("ppo:runs/my.zip") == ("ppo", {"checkpoint": "runs/my.zip"})
    assert parse_spec("rollout:top_k=5:horizon=3:base=greedy") == (
        "rollout",
        {"top_k": 5, "horizon": 3, "base": "greedy"},
    )
    with pytest.raises(ValueError, match="two checkpoints"):
        parse_spec("ppo:a.zip:b.zip")
    out = tmp_path / "r.json"
    env = "selenv/CLScheduling-v1"
    for spec, why in (("rollout:top_k=0", "top_k"), ("rollout:horizon=-1", "horizon")):
        argv = ["bench", env, "--agents", f"greedy,{spec}", "--episodes", "1", "--json", str(out)]
        assert main([*argv, "--no-progress", "--env-kwargs", '{"horizon": 2}']) == 2
        assert why in capsys.readouterr().err and not out.exists()
    argv = ["bench", env, "--agents", "greedy,rollout:top_k=2:horizon=1", "--episodes", "1"]
    assert main([*argv, "--no-progress", "--env-kwargs", '{"horizon": 3}']) == 0
