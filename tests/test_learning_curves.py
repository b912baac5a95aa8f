"""Learning curves of the PPO trainer (``--curve-every``) and ``scripts/plot_learning_curves.py``.

Tiny in-process runs of ``train_fim_ppo`` (10 candidates, 2 envs x 64 steps per iteration,
256 steps): the recorded points and baselines, the final point against the final evaluation,
identical weights with and without the curve, a SIGINT-stopped run resumed, bad options, and
the plot script.
"""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path
from typing import Any

import pytest
import torch
from conftest import load_script

from selenv.exits import guarded_main
from selenv.learned.rl import training
from selenv.learned.rl.safe_load import read_weights
from selenv.learned.rl.training import last_paths, run_cli
from selenv.train import train_fim_ppo

PROG = "python -m selenv.train.train_fim_ppo"
TINY = [
    "--total-timesteps=256",
    "--n-envs=2",
    "--n-steps=64",
    "--batch-size=64",
    "--n-epochs=1",
    "--hidden=16",
    "--eval-episodes=2",
    "--tensorboard-dir=",
    "--no-progress",
    "--checkpoint-every=0",
    '--env-kwargs={"n_candidates": 10, "budget": 3}',
]
CURVE = ["--curve-every=128", "--curve-episodes=2"]


def _meta(path: Path) -> Any:
    return json.loads(path.with_suffix(".json").read_text())


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The same tiny run with and without a learning curve (paid once for the module)."""
    folder = tmp_path_factory.mktemp("curves")
    out = {"curve": folder / "curve.zip", "plain": folder / "plain.zip"}
    train_fim_ppo.main([*TINY, *CURVE, f"--out={out['curve']}"])
    train_fim_ppo.main([*TINY, f"--out={out['plain']}"])
    return out


def test_curve_points_baselines_and_the_final_point(runs: dict[str, Path]) -> None:
    meta = _meta(runs["curve"])
    curve = meta["learning_curve"]
    assert curve["seeds"] == [10_000, 10_001] and curve["episodes"] == 2
    # step 0, the boundary after 128 steps, the end
    assert [p["timesteps"] for p in curve["points"]] == [0, 128, 256]
    walls = [p["wall_seconds"] for p in curve["points"]]
    assert walls == sorted(walls) and walls[0] >= 0
    agents = meta["metrics"]["agents"]
    assert set(curve["baselines"]) == {"greedy", "random"}
    for name in ("greedy", "random"):  # once, on the same seeds as the final evaluation
        assert curve["baselines"][name] == agents[name]["mean_return"]
    # the last point is the saved checkpoint played through the ppo agent on the same seeds
    assert curve["points"][-1]["mean_return"] == agents["ppo"]["mean_return"]
    assert meta["training"]["curve_every"] == 128
    assert "learning_curve" not in _meta(runs["plain"])


def test_the_curve_does_not_change_the_trained_weights(runs: dict[str, Path]) -> None:
    with_curve, without = read_weights(runs["curve"]), read_weights(runs["plain"])
    assert with_curve.keys() == without.keys()
    for key in with_curve:
        assert torch.equal(with_curve[key], without[key]), key
    a, b = _meta(runs["curve"]), _meta(runs["plain"])
    assert a["training_log"] == b["training_log"]
    assert a["metrics"]["agents"]["ppo"]["returns"] == b["metrics"]["agents"]["ppo"]["returns"]
    assert a["resume_state"]["rng"] == b["resume_state"]["rng"]


def test_a_stopped_run_keeps_its_points_and_resume_continues_them(
    runs: dict[str, Path],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "p.zip"
    last = last_paths(out)[0]
    real = training.save_checkpoint

    def save_then_sigint(model: Any, meta: dict[str, Any], path: Any, **kw: Any) -> Any:
        done = real(model, meta, path, **kw)
        if ".last." in str(path) and "interrupted" not in meta:
            os.kill(os.getpid(), signal.SIGINT)  # deferred: stops after this iteration
        return done

    monkeypatch.setattr(training, "save_checkpoint", save_then_sigint)
    argv = [*TINY, *CURVE, f"--out={out}"]
    assert run_cli(train_fim_ppo.main, PROG, [*argv, "--checkpoint-every=128"]) == 130
    assert "SIGINT" in capsys.readouterr().err
    stopped = _meta(last)
    assert stopped["interrupted"] == "SIGINT" and stopped["num_timesteps"] == 128
    kept = stopped["learning_curve"]["points"]
    assert [p["timesteps"] for p in kept] == [0, 128]
    uninterrupted = _meta(runs["curve"])["learning_curve"]
    # the same weights up to the stop: the same scores as the uninterrupted run
    assert [p["mean_return"] for p in kept] == [
        p["mean_return"] for p in uninterrupted["points"][:2]
    ]
    monkeypatch.undo()

    # another held-out set cannot continue this curve
    bad = [*argv, "--curve-episodes=3", f"--resume={last}"]
    assert run_cli(train_fim_ppo.main, PROG, bad) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "learning curve" in err and "--curve-episodes" in err

    assert run_cli(train_fim_ppo.main, PROG, [*argv, f"--resume={last}"]) == 0
    curve = _meta(out)["learning_curve"]
    assert curve["points"][:2] == kept  # continued, not recomputed
    assert [p["timesteps"] for p in curve["points"]] == [0, 128, 256]
    assert curve["baselines"] == stopped["learning_curve"]["baselines"]
    assert not last.exists()


# the curve options' bounds: tests/test_training_faults.py (one table of every option's limits)


def test_a_script_that_evaluates_on_its_own_refuses_the_curve(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from selenv.train import train_fim_marl  # its env is not a Gymnasium env

    out = tmp_path / "m.zip"
    argv = [*TINY[:5], "--no-progress", "--tensorboard-dir=", *CURVE, f"--out={out}"]
    assert run_cli(train_fim_marl.main, "marl", argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--curve-every" in err, err
    assert not out.exists() and not out.with_suffix(".json").exists()


def test_check_bounds_names_the_curve_options() -> None:
    cfg = train_fim_ppo.Config(curve_episodes=0)
    with pytest.raises(training.UsageError, match="--curve-episodes"):
        training.check_bounds(cfg)
    training.check_bounds(train_fim_ppo.Config(curve_episodes=20_000, allow_large=True))


def test_plot_script_writes_a_figure_and_refuses_a_checkpoint_without_curve(
    runs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    script = load_script("plot_learning_curves")
    fig = tmp_path / "curves.png"
    json_path = runs["curve"].with_suffix(".json")
    code = guarded_main(script.main, script.PROG, [str(json_path), str(runs["curve"]), "--out",
                                                   str(fig)])  # fmt: skip
    assert code == 0
    assert fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["curves.png"]  # no temporary left
    capsys.readouterr()

    other = tmp_path / "other.png"
    plain = runs["plain"].with_suffix(".json")
    assert guarded_main(script.main, script.PROG, [str(plain), "--out", str(other)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(plain) in err and "learning_curve" in err
    assert not other.exists()


def test_the_wall_minutes_axis_reads_the_recorded_points() -> None:
    from matplotlib.figure import Figure

    script = load_script("plot_learning_curves")
    ax = Figure().add_subplot()
    script._wall_axis(ax, [0.0, 100.0, 300.0], [0.5, 1.5, 3.5])
    (axis,) = ax.child_axes
    forward, inverse = axis._functions
    assert forward(100.0) == pytest.approx(1.5) and forward(200.0) == pytest.approx(2.5)
    assert inverse(3.5) == pytest.approx(300.0)
    assert forward(400.0) == pytest.approx(4.5)  # extended past the last point at its rate
    for steps, minutes in (([0.0], [1.0]), ([0.0, 10.0, 20.0], [1.0, 3.0, 2.0])):
        ax = Figure().add_subplot()
        script._wall_axis(ax, steps, minutes)  # one point, or a clock that restarted: none
        assert not ax.child_axes
