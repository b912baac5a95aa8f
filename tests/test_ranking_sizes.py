"""The ranking trainers (expert iteration, the DAgger round) check every size before any work."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from selenv.exits import UsageError
from selenv.learned.rl.ranking import RANKING_SIZES, check_ranking_sizes
from selenv.learned.rl.training import run_cli
from selenv.parallel.executors import max_pool_workers
from selenv.train import train_cl_expert, train_clustering_dagger, train_landmark_expert

SCRIPTS = [train_cl_expert, train_landmark_expert, train_clustering_dagger]


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda m: m.__name__.rsplit(".", 1)[1])
@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (
            ["--epochs", "1000000000"],
            "--epochs: 1,000,000,000 exceeds the ceiling of 10,000; pass --allow-large",
        ),
        (["--epochs", "0"], "--epochs: must be >= 1, got 0"),
        (["--epochs", "0", "--allow-large"], "--epochs: must be >= 1, got 0"),
        (["--workers", "100000"], "--workers: must be in [1, "),
        (["--explore", "1.5"], "--explore: must be in [0, 1], got 1.5"),
        (["--learning-rate", "nan"], "--learning-rate: must be finite and > 0"),
        (["--temperature", "-1"], "--temperature: must be finite and > 0"),
    ],
)
def test_bad_sizes_exit_2_with_one_line_before_any_work(
    script, argv: list[str], needle: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run" / "p.zip"
    prog = f"python -m {script.SCRIPT}"
    assert run_cli(script.main, prog, [*argv, "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"{prog}: ") and needle in err, err
    assert not (tmp_path / "run").exists()  # nothing written


@pytest.mark.parametrize("script", [train_cl_expert, train_landmark_expert])
def test_expert_rounds_states_top_k_and_horizon(script) -> None:
    cfg = script.Config()
    for field, low, high in (("top_k", 1, 256), ("horizon", 1, 10_000)):
        check_ranking_sizes(dataclasses.replace(cfg, **{field: high}))
        for bad in (low - 1, high + 1):  # never lifted
            with pytest.raises(UsageError, match=f"--{field.replace('_', '-')}: must be in"):
                check_ranking_sizes(dataclasses.replace(cfg, **{field: bad}, allow_large=True))
    for field in ("rounds", "states_per_round"):
        ceiling = RANKING_SIZES[field][1]
        assert ceiling is not None
        check_ranking_sizes(dataclasses.replace(cfg, **{field: ceiling}))  # at the ceiling: ok
        above = dataclasses.replace(cfg, **{field: ceiling + 1})
        with pytest.raises(UsageError, match="pass --allow-large"):
            check_ranking_sizes(above)
        check_ranking_sizes(dataclasses.replace(above, allow_large=True))
    check_ranking_sizes(dataclasses.replace(cfg, workers=max_pool_workers()))


def test_allow_large_may_differ_on_resume() -> None:
    assert "allow_large" in train_cl_expert._FREE
    assert "allow_large" in train_clustering_dagger._FREE
