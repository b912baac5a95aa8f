"""``python -m selenv.train.tune_sweep``: a real 2-trial sweep, usage errors, no Ray left behind."""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("ray.tune")

import selenv.parallel
from selenv.agents import make
from selenv.learned.rl.agent import SB3PolicyAgent
from selenv.learned.rl.training import evaluate
from selenv.train import tune_sweep

FIM_ID = "selenv/FIMSelection-v1"
ENV_KWARGS = {"n_candidates": 8, "budget": 3}
TINY = [
    "--script=fim_ppo",
    f"--env-kwargs={json.dumps(ENV_KWARGS)}",
    "--set=n_envs=2",
    "--set=n_steps=64",
    "--set=batch_size=64",
    "--set=n_epochs=1",
    "--timesteps=256",
    "--eval-episodes=3",
    "--eval-seed=1000",
]


def _procs() -> dict[int, tuple[str, int]]:
    """pid -> (command name, parent pid), from /proc."""
    out = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        comm = stat[stat.index("(") + 1 : stat.rindex(")")]
        out[int(d.name)] = (comm, int(stat[stat.rindex(")") + 2 :].split()[1]))
    return out


def _my_raylets() -> list[int]:
    """raylet processes descended from this (test) process."""
    procs, mine, grew = _procs(), {os.getpid()}, True
    while grew:
        new = {pid for pid, (_, ppid) in procs.items() if ppid in mine} - mine
        mine |= new
        grew = bool(new)
    return [pid for pid in mine if procs.get(pid, ("",))[0] == "raylet"]


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """One real sweep: fim_ppo, 2 seeds x 1 configuration, 256 steps, 3 held-out episodes."""
    out = tmp_path_factory.mktemp("sweep") / "out"
    seen: list[list[int]] = []
    original = selenv.parallel.ray_session

    @contextlib.contextmanager
    def spy(*args, **kwargs):  # records the raylets alive inside the session
        with original(*args, **kwargs) as ray:
            seen.append(_my_raylets())
            yield ray

    mp = pytest.MonkeyPatch()
    mp.setattr(selenv.parallel, "ray_session", spy)
    try:
        code = tune_sweep.main([*TINY, "--seeds=0,1", "--grid=learning_rate=3e-4", f"--out={out}"])
    finally:
        mp.undo()
    return {"code": code, "out": out, "raylets_inside": seen, "raylets_after": _my_raylets()}


def test_sweep_writes_results_that_match_a_reevaluation(sweep: dict) -> None:
    assert sweep["code"] == 0
    res = json.loads((sweep["out"] / "results.json").read_text())
    trials = res["trials"]
    assert len(trials) == 2 and sorted(t["seed"] for t in trials) == [0, 1]
    assert all(t["error"] is None and len(t["returns"]) == 3 for t in trials)
    assert res["eval_seeds"] == [1000, 1001, 1002]
    for t in trials:  # inside --out, never checkpoints/
        assert Path(t["checkpoint"]).is_relative_to(sweep["out"]) and Path(t["checkpoint"]).exists()
    # independent re-evaluation of one trial's saved policy (and the baseline) on the eval seeds
    t = trials[1]
    agents = {
        "ppo": SB3PolicyAgent(t["checkpoint"], env_id=FIM_ID),
        "greedy": make("greedy", FIM_ID),
    }
    again = evaluate(lambda: gym.make(FIM_ID, **ENV_KWARGS), agents, res["eval_seeds"])
    np.testing.assert_allclose(t["returns"], again["ppo"]["returns"], atol=1e-4)
    np.testing.assert_allclose(t["baseline_returns"], again["greedy"]["returns"], atol=1e-4)
    # the table: one configuration, 2 seeds, the mean of the trial means inside its CIs
    (row,) = res["configs"]
    assert row["params"] == {"learning_rate": 3e-4} and row["n_trials"] == 2
    means = [float(np.mean(t["returns"])) for t in trials]
    assert row["mean_return"] == pytest.approx(np.mean(means), abs=1e-4)
    assert row["min"] == pytest.approx(min(means), abs=1e-4)
    for lo, hi in (row["ci95"], row["ci95_t"]):
        assert lo <= row["mean_return"] <= hi
    pooled = np.concatenate([t["returns"] for t in trials])
    base = np.concatenate([t["baseline_returns"] for t in trials])
    p = row["paired"]
    assert p["baseline"] == "greedy" and p["n"] == 6
    assert p["mean_diff"] == pytest.approx(float(np.mean(pooled - base)), abs=1e-9)
    assert p["wins"] + p["ties"] + p["losses"] == 6
    assert p["ci95"][0] <= p["mean_diff"] <= p["ci95"][1]
    assert res["best"]["params"] == row["params"]
    table = (sweep["out"] / "results.md").read_text()
    assert "learning_rate=0.0003" in table and f"{row['mean_return']:.4g}" in table


def test_sweep_leaves_no_ray_behind(sweep: dict) -> None:
    import ray

    assert sweep["raylets_inside"] and sweep["raylets_inside"][0]  # the check does see raylets
    assert sweep["raylets_after"] == [] and _my_raylets() == []
    assert not ray.is_initialized()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--grid=lr=1e-3,3e-4"], "--grid lr: unknown key; valid keys: env_kwargs, algo"),
        (["--grid=learning_rate=fast"], "--grid learning_rate='fast': not a valid float"),
        (["--grid=n_steps=64,0"], "--grid n_steps='0': not a valid int"),
        (["--grid=seed=1,2"], "--grid seed: set by --seeds"),
        (["--set=algo=dqn"], "--set algo='dqn'"),
        (["--eval-seed=1"], "--eval-seed 1: held-out seeds must exceed"),
        (["--baseline=nope"], "--baseline 'nope': not an agent"),
        (["--address=127.0.0.1:1"], "--address '127.0.0.1:1': no Ray cluster reachable"),
        (["--script=nope"], "invalid choice: 'nope' (choose from 'fim_ppo', 'landmark_ppo'"),
    ],
)
def test_usage_errors_exit_2_before_anything_starts(
    args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import ray

    out = tmp_path / "out"
    assert tune_sweep.main([*TINY, *args, f"--out={out}"]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()[-1]) > 0
    assert not out.exists() and not ray.is_initialized() and _my_raylets() == []


def test_existing_out_needs_force(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import ray

    (tmp_path / "keep.txt").write_text("earlier run")
    assert tune_sweep.main([*TINY, f"--out={tmp_path}"]) == 2
    assert "exists and is not empty; pass --force" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]
    assert not ray.is_initialized() and _my_raylets() == []
