"""The trainer base (:mod:`selenv.learned.trainer`): shared run options and ``--max-minutes``.

The wall-clock budget is tested without waiting: :func:`selenv.learned.trainer.clock` is
replaced by a counter that advances one minute each time it is read, so ``--max-minutes M``
expires at the ``M``-th safe point of the run (the first read is the run's start).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import torch

from selenv.learned import trainer
from selenv.learned.rl import training
from selenv.learned.rl.safe_load import read_weights
from selenv.learned.trainer import BUDGET, RunStop, TrainingBudgetReached, last_paths, run_cli
from selenv.train import train_fim_ppo

PPO_TINY = [
    "--n-envs=2",
    "--n-steps=16",
    "--batch-size=32",
    "--n-epochs=1",
    "--hidden=8",
    "--no-progress",
    "--total-timesteps=256",
    '--env-kwargs={"n_candidates": 8, "budget": 3}',
    "--eval-episodes=0",
    "--tensorboard-dir=",
]


@pytest.fixture
def minutes(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[int]]:
    """The trainer's clock as a counter: each read is one more minute; yields the reads."""
    reads: list[int] = []

    def fake() -> float:
        reads.append(len(reads))
        return 60.0 * (len(reads) - 1)

    monkeypatch.setattr(trainer, "clock", fake)
    yield reads


def _meta(path: Path) -> Any:
    return json.loads(path.with_suffix(".json").read_text())


def _same_weights(a: Path, b: Path) -> bool:
    wa, wb = read_weights(a), read_weights(b)
    return set(wa) == set(wb) and all(torch.equal(wa[k], wb[k]) for k in wa)


# -- the budget itself ---------------------------------------------------------------------------
def test_run_stop_expires_at_the_budget_and_not_before(minutes: list[int]) -> None:
    stop = RunStop(2.5)
    assert [stop.check_budget() for _ in range(2)] == [False, False]  # 1, 2 minutes
    assert stop.signal is None
    assert stop.check_budget() is True and stop.signal == BUDGET  # 3 minutes >= 2.5
    assert RunStop(None).check_budget() is False  # no budget: the clock is never the reason


@pytest.mark.parametrize("value", [0, 0.0, -1.0, float("nan"), float("inf"), "5", True])
def test_run_stop_refuses_a_bad_budget(value: object) -> None:
    with pytest.raises(ValueError, match="--max-minutes must be a finite number of minutes > 0"):
        RunStop(value)  # type: ignore[arg-type]


def test_stop_exception_for_the_budget_names_it_and_exits_75(tmp_path: Path) -> None:
    exc = trainer.stop_exception(BUDGET, "saved x")
    assert isinstance(exc, TrainingBudgetReached) and "--max-minutes" in str(exc)

    def main(argv: list[str] | None) -> None:
        raise exc

    assert run_cli(main, "prog", []) == 75


# -- bad values on every trainer's command line --------------------------------------------------
#: every trainer with --max-minutes, and the name of its --out
SCRIPTS = {
    "train_fim_ppo": "p.zip",
    "train_cl_ppo": "p.zip",
    "train_landmark_ppo": "p.zip",
    "train_clustering_ppo": "p.zip",
    "train_fim_marl": "p.zip",
    "train_cl_expert": "p.zip",
    "train_landmark_expert": "p.zip",
    "train_clustering_dagger": "p.zip",
    "train_cl_cem": "s.json",
    "train_rllib_marl": "p",  # the output stem: p.json, p.pth, p.metrics.json
}


@pytest.mark.parametrize("script", SCRIPTS)
@pytest.mark.parametrize("value", ["0", "-2", "nan", "inf", "soon"])
def test_bad_max_minutes_is_a_one_line_usage_error(
    script: str, value: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import importlib

    if script == "train_rllib_marl":
        pytest.importorskip("ray.rllib")
    module = importlib.import_module(f"selenv.train.{script}")
    with pytest.raises(SystemExit) as exc:
        module.main([f"--out={tmp_path / SCRIPTS[script]}", f"--max-minutes={value}"])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1, err
    assert "--max-minutes" in err and value in err
    assert list(tmp_path.iterdir()) == []  # refused before any work


# -- PPO: the budget stops at an iteration boundary, --resume continues -----------------------
def _ppo(out: Path, *extra: str) -> Callable[[], dict[str, Any]]:
    return lambda: train_fim_ppo.main([*PPO_TINY, f"--out={out}", *extra])


def test_ppo_budget_saves_the_boundary_and_resume_continues(
    tmp_path: Path, minutes: list[int]
) -> None:
    # reference: an uninterrupted run whose periodic checkpoint at 64 steps is kept
    ref = tmp_path / "ref.zip"
    with pytest.MonkeyPatch.context() as mp:  # keep the periodic .last pair of step 64
        mp.setattr(training, "save_checkpoint", _keeping(training.save_checkpoint, 64))
        _ppo(ref, "--checkpoint-every=64")()
    kept = tmp_path / "ref.kept64.zip"
    assert _meta(kept)["num_timesteps"] == 64

    # budget 3 minutes: read at the start, then at each iteration boundary (0, 32, 64 steps)
    out = tmp_path / "p.zip"
    last = last_paths(out)[0]
    with pytest.raises(TrainingBudgetReached) as exc:
        _ppo(out, "--max-minutes=3", "--checkpoint-every=0")()
    assert f"--resume {last}" in str(exc.value)
    meta = _meta(last)
    assert meta["interrupted"] == BUDGET and meta["complete"] is False
    assert meta["num_timesteps"] == 64 and meta["resume_state"]["num_timesteps"] == 64
    assert meta["training"]["max_minutes"] == 3
    assert _same_weights(last, kept)  # the budget's checkpoint is the uninterrupted run's
    assert not out.exists()

    # resumed (no budget): the same as resuming the uninterrupted run's checkpoint
    final = _ppo(out, f"--resume={last}")()
    again = tmp_path / "again.zip"
    _ppo(again, f"--resume={kept}")()
    assert final["complete"] is True and final["num_timesteps"] == 256
    assert final["resume_state"]["n_updates"] == 8
    assert [e["timesteps"] for e in final["training_log"]] == list(range(32, 257, 32))
    assert _same_weights(out, again)
    assert not last.exists()


def _keeping(save: Callable[..., Path], step: int) -> Callable[..., Path]:
    """``save_checkpoint`` that copies the ``.last`` pair written at ``step`` to ``.kept<step>``."""

    def saving(model: Any, meta: dict[str, Any], path: str | Path, **kw: Any) -> Path:
        out = save(model, meta, path, **kw)
        if ".last." in str(path) and meta.get("num_timesteps") == step:
            keep = Path(path).with_name(Path(path).name.replace(".last.", f".kept{step}."))
            for suffix in (".zip", ".json"):
                keep.with_suffix(suffix).write_bytes(Path(path).with_suffix(suffix).read_bytes())
        return out

    return saving


# -- expert iteration and the DAgger round: the budget at a fit epoch, resumed bit for bit ------
#: a tiny expert-iteration run: 2 rounds of 6 labelled picks, 3 fit epochs
LM_ARGS = ["--rounds", "2", "--states-per-round", "6", "--horizon", "1", "--workers", "1",
           "--epochs", "3", "--eval-episodes", "0", "--no-progress"]  # fmt: skip
#: a tiny DAgger round on a 9-receiver clustering: 8 labelled states, 3 fit epochs
DAG_ARGS = ['--env-kwargs={"n_agents": 9, "horizon": 10}', "--states=8", "--epochs=3",
            "--workers=1", "--no-progress", "--eval-episodes=0", "--label-every=2"]  # fmt: skip


def test_expert_iteration_budget_stops_mid_fit_and_resumes_bit_identically(
    tmp_path: Path, minutes: list[int]
) -> None:
    from selenv.train import train_landmark_expert

    ref = tmp_path / "ref.zip"
    train_landmark_expert.main(["--out", str(ref), *LM_ARGS])
    out = tmp_path / "p.zip"
    last = last_paths(out)[0]
    del minutes[:]  # reads: the start, round 0's labels, then one per fit epoch
    with pytest.raises(TrainingBudgetReached) as exc:
        train_landmark_expert.main(["--out", str(out), *LM_ARGS, "--max-minutes", "3"])
    assert str(exc.value) == (
        "stopped at its --max-minutes budget: saved the last completed step (round 0's labels "
        f"collected, 2 of 3 fit epochs) as {last} (+ .json); continue with the same command "
        f"and --resume {last}"
    )
    meta = _meta(last)
    assert meta["interrupted"] == BUDGET and meta["resume_state"]["fit"]["epochs_done"] == 2
    assert meta["expert_iteration"]["max_minutes"] == 3
    resumed = train_landmark_expert.main(["--out", str(out), *LM_ARGS, "--resume", str(last)])
    assert resumed["complete"] is True and len(resumed["expert_iteration"]["rounds_log"]) == 2
    assert _same_weights(out, ref) and not last.exists()


def test_dagger_budget_after_the_labels_and_resume(tmp_path: Path, minutes: list[int]) -> None:
    from selenv.train import train_clustering_dagger

    ref = tmp_path / "ref.zip"
    train_clustering_dagger.main([f"--out={ref}", *DAG_ARGS])
    out = tmp_path / "d.zip"
    last = last_paths(out)[0]
    del minutes[:]  # reads: the start, the labels collected, then one per fit epoch
    with pytest.raises(TrainingBudgetReached, match=r"after 1 of 3 epochs"):
        train_clustering_dagger.main([f"--out={out}", *DAG_ARGS, "--max-minutes=2"])
    meta = _meta(last)
    assert meta["interrupted"] == BUDGET and meta["resume_state"]["fit"]["epochs_done"] == 1
    final = train_clustering_dagger.main([f"--out={out}", *DAG_ARGS, f"--resume={last}"])
    assert final["dagger"]["epochs_done"] == 3
    assert _same_weights(out, ref) and not last.exists()


# -- the cross-entropy method: the budget after a generation -------------------------------------
CEM_TINY = ["--env-kwargs", '{"horizon": 8}', "--generations", "2", "--population", "3",
            "--elite", "1", "--train-episodes", "2", "--workers", "1", "--eval-episodes", "0",
            "--no-progress", "--horizon", "0", "--init-std", "50"]  # fmt: skip


def test_cem_budget_keeps_the_generation_and_resumes_to_the_same_theta(
    tmp_path: Path, minutes: list[int]
) -> None:
    from selenv.learned.families.cooperative import read_scorer
    from selenv.train import train_cl_cem

    whole = tmp_path / "whole.json"
    train_cl_cem.main(["--out", str(whole), *CEM_TINY])
    out = tmp_path / "part.json"
    state = train_cl_cem.state_path(out)
    del minutes[:]  # reads: the start, then one per completed generation
    with pytest.raises(
        TrainingBudgetReached, match=f"keeps generation 1; continue with --resume {state}"
    ):
        train_cl_cem.main(["--out", str(out), *CEM_TINY, "--max-minutes", "1"])
    saved = json.loads(state.read_text())
    assert saved["interrupted"] == BUDGET and saved["state"]["generation"] == 1
    assert not out.exists()
    data = train_cl_cem.main(["--out", str(out), *CEM_TINY, "--resume", str(state)])
    assert data["training"]["generations"] == 2
    assert "max_minutes" not in data["training"]["options"]  # a run option, not the method's
    assert read_scorer(out)["theta"].tolist() == read_scorer(whole)["theta"].tolist()
    assert not state.exists()


# -- the surrogate fit: the budget after an epoch ------------------------------------------------
SUR_TINY = ["--hidden", "8", "--patience", "1000", "--tensorboard-dir", "", "--no-progress",
            "--epochs", "6"]  # fmt: skip


@pytest.fixture(scope="module")
def surrogate_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from selenv.learned.surrogate_data import generate_dataset, save_dataset

    ds = generate_dataset(300, seed=3, workers=1, progress=False)
    return save_dataset(ds, tmp_path_factory.mktemp("data") / "d.npz")


@pytest.mark.parametrize("value", ["0", "-2", "nan", "inf", "soon"])
def test_surrogate_bad_max_minutes_is_a_one_line_usage_error(
    value: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from selenv.train import train_surrogate

    with pytest.raises(SystemExit) as exc:
        train_surrogate.cli([f"--out={tmp_path / 's.pt'}", f"--max-minutes={value}"])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1, err
    assert "--max-minutes" in err and value in err
    assert list(tmp_path.iterdir()) == []


def test_surrogate_budget_keeps_the_best_weights_and_resumes_to_the_same_fit(
    tmp_path: Path, minutes: list[int], surrogate_data: Path
) -> None:
    from selenv.train import train_surrogate

    argv = ["--data", str(surrogate_data), *SUR_TINY]
    ref = tmp_path / "ref.pt"
    train_surrogate.main([*argv, "--out", str(ref)])
    out = tmp_path / "b.pt"
    del minutes[:]  # reads: the start, then one per epoch
    meta = train_surrogate.main([*argv, "--out", str(out), "--max-minutes", "2"])
    assert meta["complete"] is False and meta["interrupted"] == BUDGET
    assert meta["training"]["epochs_run"] == 2 and train_surrogate._exit_code(meta) == 75
    state = tmp_path / "b.resume.pt"
    meta = train_surrogate.main([*argv, "--out", str(out), "--resume", str(state)])
    assert meta["complete"] is True and meta["training"]["epochs_run"] == 6
    from selenv.learned.surrogates import Surrogate

    got, want = (Surrogate.load(p).net.state_dict() for p in (out, ref))
    assert want and set(got) == set(want) and all(torch.equal(got[k], want[k]) for k in want)
    assert not state.exists()
