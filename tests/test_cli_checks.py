"""selenv bench checks every argument before any work; selenv train dispatches the scripts."""

from __future__ import annotations

import json
from pathlib import Path

import _proc
import pytest

import selenv.cli as cli
from selenv.cli import main, training_scripts

FIM = "selenv/FIMSelection-v1"
LANDMARK = "selenv/LandmarkSelection-v1"


@pytest.fixture
def no_run(monkeypatch):
    """Fail the test if any env is run (the checks must stop the command first)."""

    def boom(*args, **kwargs):
        raise AssertionError("the bench ran although an argument was bad")

    monkeypatch.setattr(cli, "_run_envs", boom)


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--agents", "greedy,ppo:nope.zip"], "cannot build agent 'ppo:nope.zip'"),
        (["--agents", "greedy", "--env-kwargs", '{"k": 3}'], "--env-kwargs"),  # FIM rejects k
        (["--agents", "greedy", "--plot", "/proc/selenv_plots"], "--plot"),
        (["--agents", "greedy", "--json", "/proc/x.json"], "--json"),
        (["--agents", "greedy", "--json", "DIR"], "is a folder"),
        (["--agents", "greedy", "--plot", "FILE"], "is not a folder"),
        (["--agents", "rollout:top_k=0"], "rollout:top_k=0"),
    ],
)
def test_bad_arguments_stop_before_any_env_runs(tmp_path, capsys, no_run, extra, needle):
    (tmp_path / "f").write_text("x")
    extra = [str(tmp_path) if e == "DIR" else str(tmp_path / "f") if e == "FILE" else e
             for e in extra]  # fmt: skip
    argv = ["bench", FIM, LANDMARK, "--episodes", "1", "--no-progress", *extra]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]  # nothing written


def test_kwargs_rejected_by_the_second_env_only(capsys, no_run):
    # LandmarkSelection accepts n_landmarks, FIMSelection does not: fails before FIM runs
    argv = ["bench", LANDMARK, FIM, "--agents", "greedy", "--env-kwargs", '{"n_landmarks": 5}']
    assert main([*argv, "--no-progress"]) == 2
    assert FIM in capsys.readouterr().err


def test_good_arguments_still_run_and_create_output_folders(tmp_path):
    out = tmp_path / "new" / "deeper" / "r.json"
    argv = ["bench", FIM, "--agents", "greedy,random", "--episodes", "1", "--no-progress",
            "--env-kwargs", '{"n_candidates": 8, "budget": 2}', "--json", str(out),
            "--plot", str(tmp_path / "plots")]  # fmt: skip
    assert main(argv) == 0
    assert json.loads(out.read_text())["results"][0]["env_id"] == FIM
    assert list((tmp_path / "plots").glob("*.png"))


def test_train_lists_every_entry_point():
    scripts = training_scripts()
    folder = Path(cli.__file__).parent / "train"
    expected = {p.stem for p in folder.glob("*.py")} - {"__init__", "tune_results"}
    assert set(scripts) == expected
    assert all(scripts.values())  # each has a one-line description


def test_train_dispatches_and_reports_exit_codes(capsys):
    assert main(["train", "train_fim_ppo", "--help"]) == 0
    assert "--total-timesteps" in capsys.readouterr().out
    assert main(["train", "no_such_script"]) == 2
    assert "invalid choice" in capsys.readouterr().err


def test_cli_start_imports_no_heavy_package() -> None:
    """``selenv list`` (and ``--help``) start without torch, matplotlib, scipy.optimize/stats."""
    import sys

    code = (
        "import sys, contextlib, io\n"
        "from selenv.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    main(['list'])\n"
        "heavy = ('torch', 'matplotlib', 'scipy.optimize', 'scipy.stats', 'ray', 'cvxpy')\n"
        "print(sorted(m for m in heavy if m in sys.modules))\n"
    )
    out = _proc.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "[]", out.stdout


def _every_agent_and_env() -> list[tuple[str, str]]:
    import selenv  # noqa: F401  (registers the agents)
    from selenv.agents.base import AGENTS

    return sorted((name, env_id) for name, by_env in AGENTS.items() for env_id in by_env)


@pytest.mark.parametrize(("name", "env_id"), _every_agent_and_env())
def test_every_agent_refuses_an_unknown_option_when_built(name: str, env_id: str) -> None:
    """A misspelt option is a ValueError naming it at construction, not a TypeError mid-run."""
    from selenv.agents.base import make

    with pytest.raises(ValueError, match="no_such_option"):
        make(f"{name}:no_such_option=1", env_id)


@pytest.mark.parametrize(
    "spec",
    ["ga:population=10", "greedy:k=3", "ppo:foo=1", 'greedy:objective="x"', "swap:objective=3"],
)
def test_unknown_agent_option_is_one_line_exit_2(spec: str, capsys, no_run) -> None:
    env = "selenv/ReceiverClustering-v1" if spec.startswith("ga") else FIM
    assert main(["bench", env, "--agents", spec, "--episodes", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"cannot build agent {spec!r}" in err, err
