"""``python -m selenv.train.train_cl_cem``: a tiny search end to end, refusals, resumption."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from selenv.agents import make
from selenv.learned.families.cooperative import read_scorer
from selenv.learned.rl.training import run_cli
from selenv.train import train_cl_cem

PROG = "python -m selenv.train.train_cl_cem"
TINY = [
    "--env-kwargs",
    '{"horizon": 8}',
    "--generations",
    "2",
    "--population",
    "3",
    "--elite",
    "1",
    "--train-episodes",
    "2",
    "--workers",
    "1",
    "--eval-episodes",
    "0",
    "--no-progress",
    "--horizon",
    "0",
    "--init-std",
    "50",
]


def _run(argv: list[str]) -> int:
    """The exit code of the command (usage errors exit 2 from the option checks)."""
    try:
        return run_cli(train_cl_cem.main, PROG, argv)
    except SystemExit as exc:
        return int(exc.code or 0)


def test_a_tiny_search_writes_a_loadable_checkpoint(tmp_path: Path) -> None:
    out = tmp_path / "s.json"
    assert _run(["--out", str(out), *TINY, "--eval-episodes", "1"]) == 0
    data = read_scorer(out)
    held_out = json.loads(out.read_text())["held_out_bench"]
    assert set(held_out["agents"]) == {"greedy", "rollout", "fast_rollout", f"cem:checkpoint={out}"}
    assert held_out["command"].startswith("selenv bench selenv/CLScheduling-v1")
    assert train_cl_cem.bench_path(out).is_file()
    assert data["env_config"]["n_agents"] == 6 and data["lookahead"] == {"horizon": 0, "top_k": 3}
    training = json.loads(out.read_text())["training"]
    assert training["generations"] == 2 and len(training["history"]) == 2
    assert training["episodes_played"] == 2 * 3 * 2
    assert training["command"].startswith(PROG)
    assert not train_cl_cem.state_path(out).exists()  # removed when the run completes
    agent = make("cem", "selenv/CLScheduling-v1", checkpoint=str(out))
    np.testing.assert_array_equal(agent.theta, data["theta"])


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--elite", "9"], "--elite"),
        (["--train-seed", "5"], "--train-seed"),
        (["--horizon", "9"], "--horizon"),
        (["--env-kwargs", "[1]"], "--env-kwargs"),
        (["--population", "5000"], "--allow-large"),
    ],
)
def test_bad_options_exit_2_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str
) -> None:
    out = tmp_path / "s.json"
    assert _run(["--out", str(out), *TINY, *extra]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_existing_outputs_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "s.json"
    out.write_text("{}")
    assert _run(["--out", str(out), *TINY]) == 2
    assert "--force" in capsys.readouterr().err
    assert out.read_text() == "{}"
    assert _run(["--out", str(tmp_path / "s.zip"), *TINY]) == 2


def test_an_interrupted_search_resumes_to_the_uninterrupted_result(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    whole = tmp_path / "whole.json"
    assert _run(["--out", str(whole), *TINY]) == 0
    out = tmp_path / "part.json"
    real = train_cl_cem.cem_generation
    calls = {"n": 0}

    def stop_at_the_second(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(train_cl_cem, "cem_generation", stop_at_the_second)
    assert _run(["--out", str(out), *TINY]) == 130
    assert f"--resume {train_cl_cem.state_path(out)}" in capsys.readouterr().err
    state = train_cl_cem.state_path(out)
    assert state.exists() and not out.exists()
    assert json.loads(state.read_text())["state"]["generation"] == 1
    monkeypatch.setattr(train_cl_cem, "cem_generation", real)
    # other options are refused; the same ones finish the search
    assert _run(["--out", str(out), *TINY, "--seed", "4", "--resume", str(state)]) == 2
    assert "seed" in capsys.readouterr().err
    assert _run(["--out", str(out), *TINY, "--resume", str(state)]) == 0
    assert read_scorer(out)["theta"].tolist() == read_scorer(whole)["theta"].tolist()


def test_the_plot_script_draws_a_trained_checkpoint_and_refuses_others(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from conftest import load_script

    from selenv.exits import guarded_main
    from selenv.learned.resources import checkpoint_path

    script = load_script("plot_cem_training")
    shipped = checkpoint_path("cl_scheduling_cem.json")
    fig = tmp_path / "cem.png"
    argv = [str(shipped), "--out", str(fig), "--no-references"]
    assert guarded_main(script.main, script.PROG, argv) == 0
    assert fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["cem.png"]  # no temporary left
    capsys.readouterr()
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"format": "something else"}))
    assert guarded_main(script.main, script.PROG, [str(other), "--out", str(fig)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(other) in err
