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
SCRIPTS = ["train_fim_ppo"]


@pytest.mark.parametrize("script", SCRIPTS)
@pytest.mark.parametrize("value", ["0", "-2", "nan", "inf", "soon"])
def test_bad_max_minutes_is_a_one_line_usage_error(
    script: str, value: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import importlib

    module = importlib.import_module(f"selenv.train.{script}")
    with pytest.raises(SystemExit) as exc:
        module.main([f"--out={tmp_path / 'p.zip'}", f"--max-minutes={value}"])
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
