"""``python -m selenv.train.tune_sweep``: a real 2-trial sweep stopped and resumed, usage errors
and ceilings (exit 2 before Ray), no Ray left behind."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import _proc
import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("ray.tune")

import selenv.parallel
from selenv.agents import make
from selenv.atomic import write_json
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


def _start_time(pid: int) -> str | None:
    """Start time of a live process (``None``: gone or a zombie), so a reused PID never counts."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return None if fields[0] in ("Z", "X") else fields[19]


def _tree(root: int) -> dict[int, tuple[str, str]]:
    """``root`` and every process below it -> (its start time, its command name)."""
    procs, mine, grew = _procs(), {root}, True
    while grew:
        new = {pid for pid, (_, ppid) in procs.items() if ppid in mine} - mine
        mine |= new
        grew = bool(new)
    return {pid: (start, procs[pid][0]) for pid in mine if (start := _start_time(pid)) is not None}


def _stopped_sweep(out: Path) -> dict:
    """``python -m selenv.train.tune_sweep``, 2 trials on 1 worker, SIGTERM once 1 has its record.

    The trigger is the first trial's record file (polled), so the stop always falls between
    the two trials' records (the second trial needs a new Ray worker: seconds).
    """
    argv = [*TINY, "--seeds=0,1", "--grid=learning_rate=3e-4", "--num-workers=1", f"--out={out}"]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    proc = _proc.popen(
        [sys.executable, "-m", "selenv.train.tune_sweep", *argv],
        cwd=Path(__file__).resolve().parents[1],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    record = out / "trials" / "0000_seed0" / "result.json"
    deadline = time.monotonic() + 300
    try:
        while not record.exists():
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                _, err = _proc.communicate(proc, 30)
                pytest.fail(f"no trial record (exit {proc.returncode}): {err}")
            time.sleep(0.05)
        tree = _tree(proc.pid)  # the sweep's Ray processes, before the stop
        proc.send_signal(signal.SIGTERM)
        _, err = _proc.communicate(proc, 120)
    finally:
        _proc.stop(proc)
    deadline = time.monotonic() + 30  # the raylet's workers end shortly after the driver
    while (alive := [p for p, (t, _) in tree.items() if _start_time(p) == t]) and (
        time.monotonic() < deadline
    ):
        time.sleep(0.1)
    stat = record.stat()
    return {
        "code": proc.returncode,
        "stderr": err,
        "tree": tree,
        "alive": alive,
        "record": (stat.st_mtime_ns, record.read_bytes()),
        "results": json.loads((out / "results.json").read_text()),
        "table": (out / "results.md").read_text(),
    }


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A real sweep (fim_ppo, 2 seeds x 1 configuration, 256 steps, 3 held-out episodes).

    Stopped by SIGTERM after its first trial (a subprocess), then resumed in this process.
    """
    out = tmp_path_factory.mktemp("sweep") / "out"
    stopped = _stopped_sweep(out)
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
        code = tune_sweep.main(
            [*TINY, "--seeds=0,1", "--grid=learning_rate=3e-4", f"--out={out}", "--resume"]
        )
    finally:
        mp.undo()
    return {
        "code": code,
        "out": out,
        "stopped": stopped,
        "raylets_inside": seen,
        "raylets_after": _my_raylets(),
    }


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
    assert "exists and is not empty; pass --resume" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]
    assert not ray.is_initialized() and _my_raylets() == []


def test_sigterm_stops_the_sweep_keeping_the_finished_trial(sweep: dict) -> None:
    stopped = sweep["stopped"]
    assert stopped["code"] == 143
    lines = [line for line in stopped["stderr"].splitlines() if line.strip()]
    assert len(lines) == 1, stopped["stderr"]  # no traceback, no Ray crash dump
    assert lines[0].startswith("python -m selenv.train.tune_sweep: terminated (SIGTERM): ")
    assert "1 of 2 trials completed" in lines[0] and str(sweep["out"] / "results.json") in lines[0]
    assert "--resume" in lines[0]
    res = stopped["results"]
    assert res["complete"] is False and res["stopped"] == "SIGTERM"
    assert res["n_completed"] == 1 and res["not_run"] == ["0001_seed1"]
    (trial,) = res["trials"]
    assert trial["key"] == "0000_seed0" and trial["seed"] == 0 and len(trial["returns"]) == 3
    assert trial["returns"] == json.loads(stopped["record"][1])["returns"]
    assert res["configs"][0]["n_trials"] == 1
    assert "INCOMPLETE" in stopped["table"] and "1 of 2 trials completed" in stopped["table"]
    # every process of the sweep (its Ray instance, the trial workers) ended with it
    assert "raylet" in {comm for _, comm in stopped["tree"].values()}  # the snapshot sees Ray
    assert stopped["alive"] == []


def test_resume_runs_only_the_missing_trial(sweep: dict) -> None:
    out = sweep["out"]
    record = out / "trials" / "0000_seed0" / "result.json"
    mtime, data = sweep["stopped"]["record"]
    assert record.stat().st_mtime_ns == mtime and record.read_bytes() == data  # not re-run
    res = json.loads((out / "results.json").read_text())
    assert res["complete"] is True and res["stopped"] is None and res["not_run"] == []
    assert [t["key"] for t in res["trials"]] == ["0000_seed0", "0001_seed1"]
    assert res["trials"][0]["returns"] == json.loads(data)["returns"]
    # the resumed Tune experiment ran the second trial only
    resumed = out / "tune" / "resume_1"
    assert sorted(p.name for p in resumed.iterdir() if p.is_dir()) == ["0001_seed1"]
    assert "INCOMPLETE" not in (out / "results.md").read_text()


def _write_stopped_sweep(out: Path, argv: list[str]) -> dict:
    """``out`` as a sweep stopped before any trial finished: its ``sweep.json`` only."""
    args = tune_sweep.build_parser().parse_args([*argv, f"--out={out}"])
    planned = tune_sweep.plan(args)
    write_json(out / "sweep.json", tune_sweep._described(planned))
    return planned


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--timesteps=512"], "--resume: --timesteps differs from the stopped sweep in"),
        (["--seeds=0,1,2"], "--resume: --seeds differs from the stopped sweep in"),
        (["--grid=learning_rate=1e-3"], "--resume: --grid differs"),
        (["--set=n_epochs=2"], "--resume: --set n_epochs differs"),
        (["--force"], "--resume continues the sweep in --out, --force deletes it"),
    ],
)
def test_resume_refuses_other_options(
    args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import ray

    base = [*TINY, "--seeds=0,1", "--grid=learning_rate=3e-4"]
    _write_stopped_sweep(tmp_path, base)
    before = sorted(p.name for p in tmp_path.iterdir())
    assert tune_sweep.main([*base, *args, f"--out={tmp_path}", "--resume"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert not ray.is_initialized() and _my_raylets() == []


def test_resume_refuses_a_foreign_record_and_an_empty_out(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = [*TINY, "--seeds=0,1"]
    assert tune_sweep.main([*base, f"--out={tmp_path / 'none'}", "--resume"]) == 2
    assert "holds no sweep to continue (no sweep.json)" in capsys.readouterr().err
    _write_stopped_sweep(tmp_path, base)
    record = tmp_path / "trials" / "0001_seed1" / "result.json"
    write_json(record, {"key": "0001_seed1", "params": {}, "seed": 7, "sample": 0})
    assert tune_sweep.main([*base, f"--out={tmp_path}", "--resume"]) == 2
    err = capsys.readouterr().err
    assert f"{record}: records seed = 7, trial 0001_seed1 of this sweep has 1" in err
    assert "remove the folder" in err and len(err.strip().splitlines()) == 1


LIFT = "pass --allow-large to lift the ceilings"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["--timesteps=1000000000000"],
            "--timesteps 1000000000000 is above its ceiling 10",
        ),
        (["--eval-episodes=1000000000"], "--eval-episodes 1000000000 is above its ceiling 100000"),
        (["--set=n_envs=5000"], "--set n_envs 5000 is above its ceiling 1024"),
        (["--grid=n_steps=64,100000"], "--grid n_steps 100000 is above its ceiling 65536"),
        (["--set=hidden=8192"], "--set hidden (width) 8192 is above its ceiling 4096"),
        (
            ["--num-samples=100000000"],
            "--seeds x --grid x --num-samples: 3 seeds x 1 configurations x 100000000 samples "
            f"= 300000000 trials is above the ceiling of {tune_sweep.MAX_TRIALS} trials",
        ),
        (
            ["--grid=learning_rate=" + ",".join(f"{i + 1}e-5" for i in range(400))],
            "3 seeds x 400 configurations x 1 samples = 1200 trials is above the ceiling",
        ),
        (
            ["--timesteps=900000000", "--seeds=" + ",".join(map(str, range(12)))],
            "--timesteps 900000000 x 12 trials = 10800000000 timesteps over all trials is above "
            f"the ceiling of {tune_sweep.MAX_SWEEP_TIMESTEPS}",
        ),
        (["--num-workers=100000"], "--num-workers 100000 is above its ceiling"),
    ],
)
def test_sizes_above_their_ceiling_exit_2_before_anything_starts(
    args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import ray

    out = tmp_path / "out"
    assert tune_sweep.main([*TINY, *args, f"--out={out}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and LIFT in err[0], err
    assert err[0].startswith("python -m selenv.train.tune_sweep: error: ")
    assert not out.exists() and not ray.is_initialized() and _my_raylets() == []


@pytest.mark.parametrize(
    "args",
    [
        ["--timesteps=1000000000000"],
        ["--set=n_envs=5000", "--eval-seed=6000"],
        ["--num-samples=400"],
        ["--num-workers=100000"],
    ],
)
def test_allow_large_lifts_the_ceilings(args: list[str], tmp_path: Path) -> None:
    parsed = tune_sweep.build_parser().parse_args([*TINY, *args, f"--out={tmp_path}"])
    with pytest.raises(tune_sweep.UsageError, match=LIFT):
        tune_sweep.plan(parsed)
    lifted = argparse.Namespace(**{**vars(parsed), "allow_large": True})
    planned = tune_sweep.plan(lifted)  # checks only: nothing is started
    assert planned["fixed"]["allow_large"] is True  # the trials' own ceilings are lifted too
    assert planned["n_trials"] == 3 * parsed.num_samples


def test_lower_bounds_are_never_lifted(tmp_path: Path) -> None:
    parsed = tune_sweep.build_parser().parse_args(
        [*TINY, "--set=n_envs=0", "--allow-large", f"--out={tmp_path}"]
    )
    with pytest.raises(tune_sweep.UsageError, match="--set n_envs"):
        tune_sweep.plan(parsed)
